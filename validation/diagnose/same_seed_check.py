"""Why diagnose misreads a cause's magnitude: a same-seed pair of captures, with and without it.

    nice -n 10 python -m validation.diagnose.same_seed_check --work /tmp/blind --effect vignetting=0.2
    nice -n 10 python -m validation.diagnose.same_seed_check --work /tmp/blind --effect stray_light=0.007

WORK is a blind-study work folder (validation/diagnose/blind_study.py): its calibration,
reference, material fit and null capture (whose poses every capture is measured with) are
reused. Two sample_2_6 captures of one seed (--seed, default 4242: same renders, same noise
stream), one with the twin's effect, are measured alike, so comparing them pixel by pixel
reads what the data carry, free of anything the two captures share:

* vignetting: the BRDF ratio is (1 - k q) / (1 - k q_patch), q = r^2 / r_corner^2 (the
  twin's and diagnose's fall-off variable): a straight line in q gives k;
* stray_light: the BRDF becomes A (f + s d^2 / (pi D^2 cos theta_in)) (A < 1: the white
  patch's own stray light): a fit of f1 = A f0 + s' extra gives s' = A s, on all rows and
  on rows with cos theta_in > 0.1.

Diagnose's model of the cause (its BRDF rows, noise model and budget) is then fitted to
each capture alone: on the null capture it reads the null offset, on the other the hidden
value plus that offset. Prints JSON.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from validation.diagnose import blind_study


def data_k(ratio: np.ndarray, q: np.ndarray) -> float:
    """k from a least-squares line ratio = a (1 - k q)."""
    ok = np.isfinite(ratio)
    (a, b), *_ = np.linalg.lstsq(np.stack([np.ones(ok.sum()), q[ok]], 1), ratio[ok], rcond=None)
    return float(-b / a)


def diagnose_reading(data, fit, cause: str) -> dict:
    """Diagnose's model of ``cause`` fitted on all rows (its BRDF model, noise and budget)."""
    import glossrig.core.diagnose.catalogue as cat

    cat.MAX_BRDF_ROWS = blind_study.ROWS
    m = cat.BrdfModel.build(data, fit)
    return next(c for c in cat.brdf_causes(m) if c.name == cause).params


def diagnose_stray_without_grazing(data, fit, min_cos: float = 0.1) -> float:
    """Diagnose's stray-light fit (rho_d, rho_s and s linear, its rows and noise) on the rows
    with cos theta_in > min_cos only."""
    import glossrig.core.diagnose.catalogue as cat

    cat.MAX_BRDF_ROWS = blind_study.ROWS
    m = cat.BrdfModel.build(data, fit)
    c = m.cols
    extra = stray_extra(data.table.iloc[m.rows], data.lamps)
    coef, _, _ = m.solve_linear([np.full_like(c["L"], 1 / np.pi), c["L"], extra], c["cos_in"] > min_cos)
    return float(coef[2])


def stray_extra(table, lamps) -> np.ndarray:
    """The stray-light column of diagnose: d^2 / (pi D^2 cos theta_in)."""
    pts = table[["x", "y", "z"]].to_numpy(float)
    lamp = np.array([lamps[int(led)] for led in table["led"]], float)
    ratio = np.sum((lamp - pts) ** 2, axis=1) / np.sum(lamp ** 2, axis=1)
    return ratio / (np.pi * np.maximum(table["cos_in"].to_numpy(float), 0.05))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True, help="a blind-study work folder")
    ap.add_argument("--effect", default="vignetting=0.2", help="vignetting=K or stray_light=S")
    ap.add_argument("--seed", type=int, default=4242)
    a = ap.parse_args(argv)
    cause, value = a.effect.split("=")
    if cause not in ("vignetting", "stray_light"):
        raise SystemExit("--effect: vignetting=K or stray_light=S")
    from glossrig.core.diagnose import load_fit
    from glossrig.core.diagnose.catalogue import vignetting_factor
    from glossrig.core.diagnose.data import load_brdf
    from glossrig.core.extraction.extract import measure_capture
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.calibration.lamps import load_lamps

    work = Path(a.work)
    cal = work / "calibration"
    cam, lamps = load_camera(cal / "camera.json"), load_lamps(cal / "lamps.json")
    ref = measure_capture(cal / "reference", cam, lamps)
    blind_study.one_calibration(work / "null_base", str(cal / "camera.json"))
    fit = load_fit(work / "fit.json")
    out = work / "same_seed_check"
    out.mkdir(exist_ok=True)
    caps = {"none": out / f"none_{a.seed}", cause: out / f"{cause}_{float(value):g}_{a.seed}"}
    for name, cap in caps.items():
        if not (cap / "capture.json").exists():
            blind_study.simulate(cap, a.seed, None if name == "none" else f"{cause}={float(value):g}")
    d = {name: load_brdf(cap, cal / "reference", cam, lamps, reference=ref) for name, cap in caps.items()}
    m = d["none"].table.merge(d[cause].table, on=["u", "v", "led", "rotation"], suffixes=("0", "1"))
    led = m.led.to_numpy()
    res = {"effect": cause, "hidden": float(value), "seed": a.seed, "rows": len(m)}
    if cause == "vignetting":
        dv = d[cause]
        q = vignetting_factor(m.u.to_numpy() + 1.0, m.v.to_numpy() + 1.0, dv.image_size, dv.principal_point)
        ratio = (m.f1 / m.f0).to_numpy()
        res |= {"q_range": [float(q.min()), float(q.max())], "data_k": data_k(ratio, q),
                "data_k_per_led": {int(k): data_k(ratio[led == k], q[led == k]) for k in np.unique(led)}}
    else:
        t = m.rename(columns={"x0": "x", "y0": "y", "z0": "z", "cos_in0": "cos_in"})
        extra = stray_extra(t, lamps)
        f0, f1 = m.f0.to_numpy(), m.f1.to_numpy()
        for label, sel in (("all rows", np.isfinite(f0 + f1)),
                           ("cos_in > 0.1", np.isfinite(f0 + f1) & (t["cos_in"].to_numpy() > 0.1))):
            (A, s), *_ = np.linalg.lstsq(np.stack([f0[sel], extra[sel]], 1), f1[sel], rcond=None)
            res[f"data_A_s ({label})"] = [float(A), float(s)]
    res["diagnose_null"] = diagnose_reading(d["none"], fit, cause)
    res["diagnose"] = diagnose_reading(d[cause], fit, cause)
    if cause == "stray_light":
        res["diagnose_s (cos_in > 0.1)"] = diagnose_stray_without_grazing(d[cause], fit)
    print(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
