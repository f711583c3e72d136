"""What the uncertainty budget adds to one material's fit time (issue 15; target < 50 %).

    python -m validation.uncertainty_benchmark SAMPLES.parquet [--repeats 3] [--channels luminance,r,g,b] \
        [--point] [--calibration-draws 24] [--extract]

Fits the samples table (``glossrig fit``'s defaults: every channel, the footprint-averaged
model where the table allows it) with and without the budget
(:func:`glossrig.core.fitting.fit.fit_samples` ``budget=True/False``), alternating the two
in the same process so that both see the same machine load, ``--repeats`` times each
after one warm-up of each; prints the median times, their ratio, the budget's own time
as the fits record it (``uncertainty.budget.time_s`` summed over the channels), and a
JSON line with the numbers. Both fits give the same parameters (checked). ``--point``
also times the point-model fit (``footprint=False``, with its budget) in the same
rotation, for what the footprint-averaged model costs.

``--calibration-draws N`` (N >= 2) adds the calibration component as ``glossrig fit``
computes it by default (:mod:`glossrig.core.fitting.calibration_uncertainty`: the poses the
table records - ``glossrig extract`` stores them - or, for a table made before it did or with
another camera.json, solved again from the capture's calibration images; then N Monte Carlo
draws), with
the camera, lamps and capture the table's provenance names, timed in the same rotation
as ``budget + calibration``. ``--extract`` also times, once in the same run, the
extraction that made the table (``extract_samples`` on the captures and calibration of
its provenance), so the ratio is also given against the whole processing
(extraction + fit) of the material.
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
    ap.add_argument("--calibration-draws", type=int, default=0,
                    help="also time the budget with its calibration component of N draws (default 0: not)")
    ap.add_argument("--extract", action="store_true", help="also time the extraction once (see the docstring)")
    a = ap.parse_args(argv)
    df = read_samples(a.samples)
    channels = a.channels.split(",")
    times: dict = {True: [], False: [], "point": [], "calibration": []}
    cpu: dict = {True: [], False: [], "point": [], "calibration": []}     # this process's CPU time
    budget_own = []
    params = {}
    files = _provenance_files(df) if (a.calibration_draws or a.extract) else {}
    extract_s, extract_cpu = _time_extract(files) if a.extract else (None, None)
    for k in range(a.repeats + 1):
        for budget in (False, True) + (("point",) if a.point else ()) + \
                (("calibration",) if a.calibration_draws else ()):
            t0, c0 = time.perf_counter(), time.process_time()
            if budget == "point":
                fit_samples(df, channels=channels, footprint=False)
            elif budget == "calibration":
                _calibration(df, files, channels, a.calibration_draws)
            else:
                m = fit_samples(df, channels=channels, budget=budget)
                params[budget] = {c: f.params for c, f in m.fits.items()}
            dt, dc = time.perf_counter() - t0, time.process_time() - c0
            if k == 0:
                continue            # warm-up (imports, caches)
            times[budget].append(dt)
            cpu[budget].append(dc)
            if budget in ("point", "calibration"):
                continue
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
    if a.calibration_draws:
        t_cal = statistics.median(times["calibration"])
        res.update({"calibration_draws": a.calibration_draws, "calibration_s": times["calibration"],
                    "median_calibration_s": t_cal, "ratio_with_calibration": (t_on + t_cal) / t_off})
        poses = "recorded by extract" if recorded_poses_usable(df) else "solved again"
        res["poses"] = poses
        print(f"the calibration component ({a.calibration_draws} draws, poses {poses}): {t_cal:.2f} s; fit with "
              f"the whole budget {t_on + t_cal:.2f} s, ratio {(t_on + t_cal) / t_off:.3f} to the fit without it")
        c_off, c_on, c_cal = (statistics.median(cpu[x]) for x in (False, True, "calibration"))
        res.update({"cpu_s": {str(k): v for k, v in cpu.items()}, "cpu_ratio_with_calibration": (c_on + c_cal) / c_off})
        print(f"CPU time of this process (medians): fit {c_off:.2f} s without the budget, {c_on:.2f} s with it, "
              f"calibration component {c_cal:.2f} s: ratio {(c_on + c_cal) / c_off:.3f}")
    if extract_s is not None:
        res["extract_s"] = extract_s
        base = extract_s + t_off
        full = extract_s + t_on + (res.get("median_calibration_s") or 0.0)
        res["ratio_processing"] = full / base
        print(f"extraction {extract_s:.2f} s (once); processing (extraction + fit) {base:.2f} s without the budget, "
              f"{full:.2f} s with it: ratio {full / base:.3f} (+{100 * (full / base - 1):.1f} %)")
        if "cpu_s" in res:
            # CPU time is what a loaded machine does not inflate: the extraction's own and its workers'
            c_off, c_on, c_cal = (statistics.median(cpu[x]) for x in (False, True, "calibration"))
            res["extract_cpu_s"] = extract_cpu
            res["cpu_ratio_processing"] = (extract_cpu + c_on + c_cal) / (extract_cpu + c_off)
            print(f"CPU: extraction {extract_cpu:.2f} s (with its workers); processing {extract_cpu + c_off:.2f} s "
                  f"without the budget, {extract_cpu + c_on + c_cal:.2f} s with it: ratio "
                  f"{res['cpu_ratio_processing']:.3f} (+{100 * (res['cpu_ratio_processing'] - 1):.1f} %)")
    print(json.dumps(res))
    return res


def _provenance_files(df) -> dict:
    """The sample and reference captures, camera.json and lamps.json that the table's
    provenance records (``glossrig extract``)."""
    prov = (df.attrs.get("provenance") or {}).get("inputs") or {}
    out = {}
    for k in ("sample", "reference", "camera", "lamps"):
        e = prov.get(k) or {}
        out[k] = e.get("resolved") or e.get("path")
    missing = [k for k, v in out.items() if not v]
    if missing:
        raise SystemExit(f"the samples table's provenance names no {', '.join(missing)}")
    out["albedo"] = ((df.attrs.get("provenance") or {}).get("options") or {}).get("reference_albedo", 0.8)
    return out


def recorded_poses_usable(df) -> bool:
    """Whether the table's recorded poses are the ones its calibration would solve
    (:func:`glossrig.core.fitting.calibration_uncertainty.recorded_poses`)."""
    from glossrig.core.fitting import calibration_uncertainty as cu

    files = _provenance_files(df)
    return cu.recorded_poses(df.attrs.get("poses"), files["camera"], files["sample"])[0] is not None


def _time_extract(files: dict) -> tuple[float, float]:
    """Wall and CPU time (this process's and its worker processes', which the pool has ended and
    the OS has counted when extract_samples returns) of the table's extraction."""
    import resource

    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.calibration.lamps import load_lamps
    from glossrig.core.extraction.extract import extract_samples

    def cpu() -> float:
        ch = resource.getrusage(resource.RUSAGE_CHILDREN)
        return time.process_time() + ch.ru_utime + ch.ru_stime

    t0, c0 = time.perf_counter(), cpu()
    extract_samples(files["sample"], files["reference"], load_camera(files["camera"]), load_lamps(files["lamps"]),
                    albedo=float(files["albedo"]))
    return time.perf_counter() - t0, cpu() - c0


def _calibration(df, files: dict, channels, draws: int) -> None:
    """What ``glossrig fit`` adds for the calibration component, given the fits' parameters
    (taken from a point-model fit once; the component's cost does not depend on them)."""
    from glossrig.core.fitting import calibration_uncertainty as cu

    global _PARAMS
    if _PARAMS is None:
        from glossrig.core.fitting.fit import fit_samples

        _PARAMS = {c: f.params for c, f in fit_samples(df, channels=channels, footprint=False,
                                                          budget=False).fits.items()}
    # the poses the table records when they are this calibration's (glossrig fit does the same), else solved again
    solved, _ = cu.recorded_poses(df.attrs.get("poses"), files["camera"], files["sample"])
    cal = cu.load_inputs(files["camera"], files["lamps"], files["sample"], sorted(df["rotation"].unique()), solved=solved)
    cu.calibration_component(df, _PARAMS, cal, n_draws=draws, footprint=True)   # refits as glossrig fit's default


_PARAMS = None


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
