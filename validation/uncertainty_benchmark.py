"""What the uncertainty budget adds to one material's fit time (issue 15; target < 50 %).

    python -m validation.uncertainty_benchmark SAMPLES.parquet [--repeats 3] [--channels luminance,r,g,b] \
        [--point]

Fits the samples table (``glossrig fit``'s defaults: every channel, the footprint-averaged
model where the table allows it) with and without the budget
(:func:`glossrig.core.fitting.fit.fit_samples` ``budget=True/False``), alternating the two
in the same process so that both see the same machine load, ``--repeats`` times each
after one warm-up of each; prints the median times, their ratio, the budget's own time
as the fits record it (``uncertainty.budget.time_s`` summed over the channels), and a
JSON line with the numbers. Both fits give the same parameters (checked). ``--point``
also times the point-model fit (``footprint=False``, with its budget) in the same
rotation, for what the footprint-averaged model costs.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time


def main(argv=None) -> dict:
    from glossrig.core.fitting.fit import fit_samples
    from glossrig.core.samples import read_samples

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("samples")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--channels", default="luminance,r,g,b")
    ap.add_argument("--point", action="store_true", help="also time the point-model fit")
    a = ap.parse_args(argv)
    df = read_samples(a.samples)
    channels = a.channels.split(",")
    times: dict = {True: [], False: [], "point": []}
    budget_own = []
    params = {}
    for k in range(a.repeats + 1):
        for budget in (False, True) + (("point",) if a.point else ()):
            t0 = time.perf_counter()
            if budget == "point":
                fit_samples(df, channels=channels, footprint=False)
                if k:
                    times["point"].append(time.perf_counter() - t0)
                continue
            m = fit_samples(df, channels=channels, budget=budget)
            dt = time.perf_counter() - t0
            params[budget] = {c: f.params for c, f in m.fits.items()}
            if k == 0:
                continue            # warm-up (imports, caches)
            times[budget].append(dt)
            if budget:
                budget_own.append(sum(f.uncertainty["budget"]["time_s"] for f in m.fits.values()))
    assert params[True] == params[False], "the budget changed the fit"
    t_off, t_on = statistics.median(times[False]), statistics.median(times[True])
    res = {"samples": a.samples, "rows": len(df), "channels": channels, "repeats": a.repeats,
           "fit_s_without_budget": times[False], "fit_s_with_budget": times[True],
           "median_without_s": t_off, "median_with_s": t_on, "ratio": t_on / t_off,
           "budget_own_s_median": statistics.median(budget_own)}
    if a.point:
        res["point_model_fit_s"] = times["point"]
        res["median_point_s"] = statistics.median(times["point"])
    print(f"{len(df)} samples, channels {','.join(channels)}: fit {t_off:.2f} s without the budget, "
          f"{t_on:.2f} s with it (median of {a.repeats}); ratio {t_on / t_off:.3f} "
          f"(+{100 * (t_on / t_off - 1):.1f} %); the budget's own time {res['budget_own_s_median']:.3f} s")
    if a.point:
        print(f"the point-model fit (with its budget): {res['median_point_s']:.2f} s; the footprint-averaged fit "
              f"with its budget takes {t_on / res['median_point_s']:.2f} times as long")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
