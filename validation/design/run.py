"""Regenerate validation/design (issue 8: coverage and geometry-based design).

    .venv/bin/python validation/design/run.py            # everything (about an hour on 2 busy cores)
    .venv/bin/python validation/design/run.py coverage   # one step: coverage | optimise | check

Steps (each a glossrig command, printed before it runs):

coverage  glossrig design coverage of the thesis rig at image scales 1, 0.5 and
          0.25 and camera distances 450 and 550 mm -> validation/design/coverage/
optimise  glossrig design optimise, 16 LEDs, on a local Dask cluster with two
          workers -> scenes/optimised_rig.toml and validation/design/optimise/
check     the same optimisation in one process (--workers 0); the two rig files
          and design results must be identical -> validation/design/dask_check.json
"""
from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
HERE = ROOT / "validation" / "design"
GLOSSRIG = [sys.executable, "-m", "glossrig.cli.main"]
MATERIALS = "brushed_original,sanded_original,base_2"
OPTIMISE = ["design", "optimise", "--rig", "scenes/thesis_rig.toml", "--leds", "16", "--materials", MATERIALS]


def sh(args: list[str]) -> float:
    print("$ glossrig " + " ".join(args), flush=True)
    t0 = time.perf_counter()
    subprocess.run(GLOSSRIG + args, cwd=ROOT, check=True)
    return time.perf_counter() - t0


def coverage() -> None:
    sh(["design", "coverage", "--rig", "scenes/thesis_rig.toml", "--out", "validation/design/coverage",
        "--scales", "1.0,0.5,0.25", "--camera-distances", "450,550"])


def optimise() -> float:
    return sh(OPTIMISE + ["--out", "scenes/optimised_rig.toml", "--report", "validation/design/optimise",
                          "--workers", "2", "--force"])


def _comparable(design_json: Path) -> dict:
    d = json.loads(design_json.read_text())["design"]
    return {k: v for k, v in d.items() if k not in ("runner", "timings_s")}


def check(dask_seconds: float | None = None) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        t = sh(OPTIMISE + ["--out", f"{tmp}/one_process.toml", "--report", f"{tmp}/report", "--workers", "0",
                           "--final-scale", "0.1"])
        one_rig = Path(f"{tmp}/one_process.toml").read_text()
        one = _comparable(Path(f"{tmp}/report/design.json"))
    dask_rig = (ROOT / "scenes" / "optimised_rig.toml").read_text()
    dask_json = json.loads((HERE / "optimise" / "design.json").read_text())["design"]
    dask = {k: v for k, v in dask_json.items() if k not in ("runner", "timings_s")}
    out = {"rig_files_identical": one_rig == dask_rig, "design_results_identical": one == dask,
           "dask": {"runner": dask_json["runner"], "timings_s": dask_json["timings_s"], "wall_s": dask_seconds},
           "one_process": {"runner": "one process", "wall_s": t},
           "command_dask": "glossrig " + " ".join(OPTIMISE + ["--out", "scenes/optimised_rig.toml", "--workers", "2"]),
           "command_one_process": "glossrig " + " ".join(OPTIMISE + ["--out", "ONE.toml", "--workers", "0"])}
    (HERE / "dask_check.json").write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))
    if not (out["rig_files_identical"] and out["design_results_identical"]):
        sys.exit("Dask and one-process sweeps differ")


def main(argv: list[str]) -> None:
    steps = argv or ["coverage", "optimise", "check"]
    bad = [s for s in steps if s not in ("coverage", "optimise", "check")]
    if bad:
        sys.exit(f"unknown step(s) {bad}; choose from coverage, optimise, check")
    dask_s = None
    if "coverage" in steps:
        coverage()
    if "optimise" in steps:
        dask_s = optimise()
    if "check" in steps:
        check(dask_s)


if __name__ == "__main__":
    main(sys.argv[1:])
