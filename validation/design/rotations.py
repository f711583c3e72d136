"""Anisotropic coverage against the number of sample rotations (validation/design/rotations.md).

    .venv/bin/python validation/design/rotations.py [--scale 0.25]

per_mount.md bounds what 16 LED mounts reach at the thesis's 4 sample rotations (about
1.3x the 16-LED thesis rig). The other lever the issue names is the sample rotations:
each rotation turns every azimuth of the sample's frame, so its bins barely overlap
another rotation's, and coverage grows with their number - at the price of one more
capture per rotation. For the thesis rig (all 16 LEDs) and the optimised rig
(scenes/optimised_rig.toml), rotations are added greedily from a 15-degree grid
(-90..75 deg), each step the one that adds the most anisotropic bins (thesis 7.1.3: 1-degree
bins, lit samples, no folding, this project's headline convention; glossrig.core.design.coverage).
The image scale is the design sweep's (0.25); the headline figures of README section 1 are
at full resolution, so compare ratios, not percentages.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from glossrig.core.design import coverage as cov
from glossrig.core.rig import load_rig

ROOT = Path(__file__).resolve().parents[2]
GRID = [float(r) for r in range(-90, 90, 15)]


def greedy(data: cov.CoverageData, conv: cov.Convention, n_max: int, start: list[float]) -> list[tuple]:
    """Rotations in greedy order, starting from ``start``: (rotations, anisotropic fraction, isotropic)."""
    chosen, rows = list(start), []
    if chosen:
        c = cov.coverage(data, conv, rotations=chosen)
        rows.append((list(chosen), c["anisotropic"], c["isotropic"]))
    while len(chosen) < n_max:
        best, c = max(((r, cov.coverage(data, conv, rotations=chosen + [r]))
                       for r in data.rotations if r not in chosen), key=lambda rc: rc[1]["anisotropic_bins"])
        chosen.append(best)
        rows.append((list(chosen), c["anisotropic"], c["isotropic"]))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=0.25)
    ap.add_argument("--max-rotations", type=int, default=8)
    ap.add_argument("--out", default=str(ROOT / "validation" / "design" / "rotations.md"))
    a = ap.parse_args(argv)
    conv = cov.Convention()
    rigs = {"thesis (16 LEDs)": load_rig(ROOT / "scenes/thesis_rig.toml"),
            "optimised (16 LEDs)": load_rig(ROOT / "scenes/optimised_rig.toml")}
    ref = None
    lines = ["# Anisotropic coverage against the number of sample rotations", "",
             f"`python validation/design/rotations.py --scale {a.scale}`. Convention: {conv.label()} (1-degree bins); image "
             f"scale {a.scale}. Rotations added greedily from {GRID[0]:g}..{GRID[-1]:g} deg in 15-degree steps, "
             "starting from each rig's own four; ratios against the thesis rig with all 16 LEDs at its own four "
             "rotations (-45/0/45/90).", "",
             "| rig | rotations | anisotropic | x thesis 16 LEDs, 4 rotations | isotropic | rotations used |",
             "|---|---|---|---|---|---|"]
    for name, rig in rigs.items():
        rots = sorted(set(GRID) | set(rig.sample_rotations))
        data = cov.collect(rig, rotations=rots, scale=a.scale, filters=("lit",))
        rows = greedy(data, conv, a.max_rotations, list(rig.sample_rotations))
        if ref is None:
            ref = rows[0][1]
        for rs, an, iso in rows:
            lines.append(f"| {name} | {len(rs)} | {100 * an:.4f} % | x{an / ref:.2f} | {100 * iso:.3f} % | "
                         f"{', '.join(f'{r:g}' for r in rs)} |")
        print(name, "done", flush=True)
    lines += ["", "Each added rotation is one more capture of every LED (the exposure plans' minutes per "
              "rotation, README section 4)."]
    Path(a.out).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
