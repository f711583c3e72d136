"""Regenerate validation/design (issue 8: coverage and geometry-based design).

    .venv/bin/python -m validation.design.run            # everything (about an hour on 2 busy cores)
    .venv/bin/python -m validation.design.run optimise   # one step: coverage | optimise | one_process | compare

Steps (each a glossrig command, printed before it runs):

coverage  glossrig design coverage of the thesis rig at image scales 1 and 0.25,
          camera distances 450 and 550 mm at 0.25 -> validation/design/coverage/
optimise  glossrig design optimise, 16 LEDs, on a local Dask cluster with two
          workers -> scenes/optimised_rig.toml and validation/design/optimise/
one_process  the same optimisation in one process (--workers 0)
          -> validation/design/one_process/
compare   the two rig files and design results must be identical
          -> validation/design/dask_check.json
exposures glossrig design exposures for every Table 9.1 material on the thesis rig
          (8 middle LEDs, rotation 0: the thesis's 120-minute basis)
          -> validation/design/exposures/ (plans, per-LED figures, exposures.md)
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from validation.common import glossrig
from validation.paths import ROOT, thesis_dir

HERE = ROOT / "validation" / "design"
MATERIALS = "brushed_original,sanded_original,base_2"
OPTIMISE = ["design", "optimise", "--rig", "scenes/thesis_rig.toml", "--leds", "16", "--materials", MATERIALS]


def sh(args: list[str]) -> float:
    t0 = time.perf_counter()
    glossrig(*args, echo="$", cwd=ROOT)
    return time.perf_counter() - t0


def coverage() -> None:
    sh(["design", "coverage", "--rig", "scenes/thesis_rig.toml", "--out", "validation/design/coverage",
        "--scales", "1.0,0.25", "--camera-distances", "450,550"])


def optimise() -> float:
    return sh(OPTIMISE + ["--out", "scenes/optimised_rig.toml", "--report", "validation/design/optimise",
                          "--workers", "2", "--force"])


def one_process() -> float:
    return sh(OPTIMISE + ["--out", "validation/design/one_process/optimised_rig.toml", "--report",
                          "validation/design/one_process", "--workers", "0", "--final-scale", "0.1", "--force"])


def _design(path: Path) -> dict:
    d = json.loads(path.read_text())["design"]
    return {k: v for k, v in d.items() if k not in ("runner", "timings_s")}


def compare() -> None:
    """The Dask and one-process sweeps must give the same design, bit for bit."""
    one_rig = (HERE / "one_process" / "optimised_rig.toml").read_text()
    dask_rig = (ROOT / "scenes" / "optimised_rig.toml").read_text()
    one = _design(HERE / "one_process" / "design.json")
    dask = _design(HERE / "optimise" / "design.json")
    runs = {name: json.loads((HERE / sub / "design.json").read_text())["design"]
            for name, sub in (("dask", "optimise"), ("one_process", "one_process"))}
    out = {"rig_files_identical": one_rig == dask_rig, "design_results_identical": one == dask,
           "runs": {k: {"runner": v["runner"], "timings_s": v["timings_s"]} for k, v in runs.items()},
           "command_dask": "glossrig " + " ".join(OPTIMISE + ["--out", "scenes/optimised_rig.toml", "--workers", "2"]),
           "command_one_process": "glossrig " + " ".join(OPTIMISE + ["--out", "validation/design/one_process/"
                                                                     "optimised_rig.toml", "--workers", "0"])}
    (HERE / "dask_check.json").write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))
    if not (out["rig_files_identical"] and out["design_results_identical"]):
        sys.exit("Dask and one-process sweeps differ")


def exposures() -> None:
    """Capture time of the planned exposures per material against the thesis's plan."""
    import csv

    out = HERE / "exposures"
    out.mkdir(exist_ok=True)
    rows = [r for r in csv.DictReader(l for l in open(thesis_dir() / "ward_params.csv")
                                      if not l.startswith("#"))]
    lines = ["# Exposure plans per material (thesis rig, 8 middle LEDs, one rotation)", "",
             "Command: `python -m validation.design.run exposures`, i.e. per material",
             "`glossrig design exposures --rig scenes/thesis_rig.toml --material M --rotations 0 "
             "--out validation/design/exposures/M.toml --report validation/design/exposures/M.json` "
             "(noise target 3 %, margin 1.1, 9.94 s per shot; LED jitter 0.5 % per frame, frame-gain error "
             "after neighbour correction within 0.1 % or twice the whole table's, full-resolution capture).", "",
             "| material | shots | exposures (s) | time (min) | worst noise | pixels within the target "
             "| worst frame-gain error (whole table) | frames left uncorrected |",
             "|---|---|---|---|---|---|---|---|"]
    thesis = None
    for r in rows:
        m = r["name"]
        sh(["design", "exposures", "--rig", "scenes/thesis_rig.toml", "--material", m, "--rotations", "0",
            "--out", f"validation/design/exposures/{m}.toml", "--report", f"validation/design/exposures/{m}.json"])
        d = json.loads((out / f"{m}.json").read_text())
        thesis = d
        n = sum(len(e["exposures_s"]) for e in d["leds"])
        span = sorted({t for e in d["leds"] for t in e["exposures_s"]})
        lines.append(f"| {m} | {n} | {span[0]:g}-{span[-1]:g} | {d['time_s_per_rotation'] / 60:.1f} | "
                     f"{100 * max(e['worst_noise'] for e in d['leds']):.2f} % | "
                     f"{100 * min(e['target_fraction'] for e in d['leds']):.0f}-"
                     f"{100 * max(e['target_fraction'] for e in d['leds']):.0f} % | "
                     f"{100 * max(e['gain_noise_worst'] for e in d['leds']):.3f} % "
                     f"({100 * max(e['gain_noise_worst_full'] for e in d['leds']):.3f} %) | "
                     f"{sum(e['unlinked_frames'] for e in d['leds'])} |")
    lines += ["", f"Thesis plan for the same LEDs and rotation (3 sequences x 18 exposures): "
              f"{thesis['thesis_plan_s_per_rotation'] / 60:.1f} min with the measured overhead (the thesis "
              f"states 120 min), {thesis['thesis_floor_s_per_rotation'] / 60:.1f} min of exposure alone.", ""]
    (out / "exposures.md").write_text("\n".join(lines))
    print("\n".join(lines))


STEPS = {"coverage": coverage, "optimise": optimise, "one_process": one_process, "compare": compare,
         "exposures": exposures}


def main(argv: list[str]) -> None:
    steps = argv or list(STEPS)
    bad = [s for s in steps if s not in STEPS]
    if bad:
        sys.exit(f"unknown step(s) {bad}; choose from {', '.join(STEPS)}")
    for s in steps:
        STEPS[s]()


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main, sys.argv[1:]))
