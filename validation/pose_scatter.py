"""Scatter of the pose step's tilts over whole twin captures (the bounds of
tests/test_calibration.py::test_poses_recover_the_twin_geometry).

For each scene seed, the twin simulates the test fixture's capture (``lambert:0.8``, LED 9,
rotation 0, one repeat, scale 0.15: each seed draws the LED fluctuations and the sensor
noise), the poses are solved with the twin's **true** intrinsics (so only the pose step's
own error is measured: eq. 4.3-4.25 of the thesis, marker corners then the white patch's raw
edges) and the tilt of each solved rotation against the truth is printed: holder, cylinder,
and cylinder in the holder frame, in degrees. The test's bounds are three times the RMS
over seeds (a half-normal tilt exceeds 3 sigma with probability 0.3 %).

    python -m validation.pose_scatter --work /tmp/pose --seeds 2,3,4,5

Captures are reused when complete (validation.common.simulate's rule). The figures cited in
the test's docstring combine this script's rows for the current sensor with the same rows
made by commit 559ff71's code (NumPy sensor), 8 captures in all.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from validation import common

SCALE = 0.15           # tests/conftest.py's capture scale
LED = "9"


def tilts(capture: Path, camera_json: Path) -> dict[str, float]:
    """Tilt (deg) of the solved holder, cylinder and cylinder-in-holder rotations."""
    from glossrig.core.calibration.poses import calibrate_capture, rotation_angle_deg

    t = json.loads((capture / "truth.json").read_text())
    Rh, Rci = np.array(t["camera_R_holder_to_camera"]), np.array(t["cylinder_R_in_holder"])
    g = calibrate_capture(capture, camera_json)
    return {"holder": rotation_angle_deg(g["holder"]["R"], Rh),
            "cylinder": rotation_angle_deg(g["cylinder"]["R"], Rh @ Rci),
            "cylinder_in_holder": rotation_angle_deg(g["cylinder_in_holder"]["R"], Rci)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True, help="folder for the captures")
    ap.add_argument("--seeds", default="2,3,4,5", help="scene seeds (default 2,3,4,5)")
    a = ap.parse_args(argv)
    rows = []
    for seed in (int(s) for s in a.seeds.split(",")):
        cap = a.work / f"seed{seed}" / "sample"
        common.capture(cap, "lambert:0.8", SCALE, seed, rotations="0", repeats=1, leds=LED)
        cam = common.truth_camera(cap, a.work / f"seed{seed}" / "camera.json")
        r = tilts(cap, cam)
        rows.append(r)
        print(f"seed {seed}: holder {r['holder']:.3f}  cylinder {r['cylinder']:.3f}  "
              f"cylinder in holder {r['cylinder_in_holder']:.3f} deg", flush=True)
    for k in ("holder", "cylinder", "cylinder_in_holder"):
        v = np.array([r[k] for r in rows])
        print(f"{k}: RMS {np.sqrt(np.mean(v ** 2)):.3f} deg, range {v.min():.3f}-{v.max():.3f} "
              f"over {len(v)} captures; bound 3 x RMS = {3 * np.sqrt(np.mean(v ** 2)):.3f} deg")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
