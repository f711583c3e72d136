"""Why diagnose reads vignetting low: a same-seed pair of captures, with and without it.

    nice -n 10 python validation/diagnose/vignetting_check.py --work /tmp/blind [--k 0.2 --seed 4242]

WORK is a blind-study work folder (validation/diagnose/blind_study.py): its calibration,
reference, material fit and null capture (whose poses every capture is measured with) are
reused. Two sample_2_6 captures of one seed (same renders, same noise stream), one with the
twin's ``vignetting=K``, are measured alike. Their per-pixel BRDF ratio is
(1 - k q) / (1 - k q_patch), q = r^2 / r_corner^2 (the twin's and diagnose's fall-off
variable), so a straight-line fit of the ratio against q reads the vignetting the data
carry, free of anything the two captures share. Diagnose's vignetting model (all rows,
with its noise model) is then fitted to each capture alone: on the null capture it reads
the null offset, on the vignetted one the hidden k plus that offset. Prints JSON.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import blind_study  # noqa: E402


def data_k(ratio: np.ndarray, q: np.ndarray) -> float:
    """k from a least-squares line ratio = a (1 - k q)."""
    ok = np.isfinite(ratio)
    (a, b), *_ = np.linalg.lstsq(np.stack([np.ones(ok.sum()), q[ok]], 1), ratio[ok], rcond=None)
    return float(-b / a)


def diagnose_k(data, fit) -> float:
    """Diagnose's vignetting cause fitted on all rows (its BRDF model, noise and budget)."""
    import glossrig.core.diagnose.catalogue as cat

    cat.MAX_BRDF_ROWS = blind_study.ROWS
    m = cat.BrdfModel.build(data, fit)
    return float(next(c for c in cat.brdf_causes(m) if c.name == "vignetting").params["k"])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True, help="a blind-study work folder")
    ap.add_argument("--k", type=float, default=0.2)
    ap.add_argument("--seed", type=int, default=4242)
    a = ap.parse_args(argv)
    from glossrig.core.diagnose import load_fit
    from glossrig.core.diagnose.catalogue import vignetting_factor
    from glossrig.core.diagnose.data import load_brdf
    from glossrig.core.extract import measure_capture
    from glossrig.core.intrinsics import load_camera
    from glossrig.core.lamps import load_lamps

    work = Path(a.work)
    cal = work / "calibration"
    cam, lamps = load_camera(cal / "camera.json"), load_lamps(cal / "lamps.json")
    ref = measure_capture(cal / "reference", cam, lamps)
    blind_study.one_calibration(work / "null_base", str(cal / "camera.json"))
    fit = load_fit(work / "fit.json")
    out = work / "vignetting_check"
    out.mkdir(exist_ok=True)
    caps = {"none": out / f"none_{a.seed}", "vignetting": out / f"vignetting_{a.seed}"}
    for name, cap in caps.items():
        if not (cap / "capture.json").exists():
            blind_study.simulate(cap, a.seed, None if name == "none" else f"vignetting={a.k:g}")
    d = {name: load_brdf(cap, cal / "reference", cam, lamps, reference=ref) for name, cap in caps.items()}
    m = d["none"].table.merge(d["vignetting"].table, on=["u", "v", "led", "rotation"], suffixes=("0", "1"))
    dv = d["vignetting"]
    q = vignetting_factor(m.u.to_numpy() + 1.0, m.v.to_numpy() + 1.0, dv.image_size, dv.principal_point)
    ratio = (m.f1 / m.f0).to_numpy()
    res = {"hidden_k": a.k, "seed": a.seed, "rows": len(m), "q_range": [float(q.min()), float(q.max())],
           "data_k": data_k(ratio, q),
           "data_k_per_led": {int(l): data_k(ratio[m.led.to_numpy() == l], q[m.led.to_numpy() == l])
                              for l in sorted(m.led.unique())},
           "diagnose_k_null": diagnose_k(d["none"], fit), "diagnose_k": diagnose_k(dv, fit)}
    print(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main()
