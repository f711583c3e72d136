"""Speed of ``glossrig diagnose`` on a scale-0.25, 8-LED twin capture (issue 14: "diagnose
shows progress and takes under 2 minutes ... on this 2-core machine"), against the code
before the speed-up, in one command:

    python -m validation.diagnose.speed_benchmark --work /tmp/diagnose_bench

1. Makes (once; reused when complete) the calibrated twin of validation/common.py: a
   ``sample_2_6`` capture (thesis Table 9.1 material) and a ``lambert:0.8`` reference of the
   8 middle-row LEDs at scale 0.25, rotation 0, one repeat of the 18 exposures of Table 4.1,
   and the camera and lamp calibrations made from twin checkerboards and a transparency
   sheet (``glossrig calibrate camera`` / ``lamps``). ``--sample --reference --camera
   --lamps`` take existing ones instead.
2. Runs ``glossrig diagnose`` on it twice, each in a fresh process with stderr a pipe (as a
   log file sees it): the code in this checkout, and the code of ``--baseline`` (default
   HEAD: a ``git archive`` of its ``core/`` and ``cli/``, put first on PYTHONPATH as
   validation/extract_benchmark.py does). The order alternates with ``--runs`` > 1.
3. Records per run the wall time, the CPU time of the process and its worker processes
   (``RUSAGE_CHILDREN``), the time each stderr line arrived (the stage split: measurement
   of both captures - the only part run by worker processes -, the material fit, the
   BRDF-space causes, the frame-space causes and the rest), the longest silence on stderr,
   and the verdict; the two verdicts must be equal, and every cause's held-out gain is
   compared (largest difference).
4. Writes validation/diagnose/speed_benchmark.md (``--out``).

The machine is shared: the load average before and after each run is written down, and
CPU seconds are the figures to compare between runs of a loaded machine; the target
(2 minutes) is wall time on an idle 2-core machine.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

from validation.common import GLOSSRIG, calibrate, capture
from validation.paths import ROOT

MATERIAL = "sample_2_6"          # thesis Table 9.1
SCALE = 0.25
LEDS = "middle"                  # the 8 middle-row LEDs
SEED = 40
#: stderr lines that end a stage, as the current code words them (the baseline's are matched too)
STAGES = (("measurement (sample + reference, worker processes)", re.compile(r"measured \d+ BRDF samples")),
          ("material fit", re.compile(r"^material: ")),
          ("BRDF-space causes", re.compile(r"BRDF-space causes done")),
          ("frame-space causes", re.compile(r"frame-space causes done")),
          ("open-world tests and report", re.compile(r"^verdict: ")))


def make_captures(w: Path) -> dict:
    """The calibrated twin (module docstring, step 1) in ``w``; paths by role."""
    cam, lamps = calibrate(w / "calibration", SCALE, SEED)
    ref = capture(w / "reference", "lambert:0.8", SCALE, SEED + 2, leds=LEDS)
    sample = capture(w / "sample", MATERIAL, SCALE, SEED + 3, leds=LEDS)
    return {"sample": sample, "reference": ref, "camera": cam, "lamps": lamps}


def baseline_tree(w: Path, commit: str) -> Path:
    """A folder holding a ``glossrig`` package whose ``core`` and ``cli`` are those of ``commit``
    (git archive); first on PYTHONPATH it takes the place of this checkout's."""
    sha = subprocess.run(["git", "-C", str(ROOT), "rev-parse", commit], check=True, capture_output=True,
                         text=True).stdout.strip()
    pkg = w / f"baseline-{sha[:10]}"
    if not (pkg / "glossrig" / "core").is_dir():
        src = w / f"baseline-src-{sha[:10]}"
        shutil.rmtree(src, ignore_errors=True)
        src.mkdir(parents=True)
        arch = subprocess.run(["git", "-C", str(ROOT), "archive", sha, "core", "cli"], check=True,
                              capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(src)], input=arch, check=True)
        (pkg / "glossrig").mkdir(parents=True, exist_ok=True)
        for f in (src / "cli" / "toplevel").glob("*.py"):
            (pkg / "glossrig" / f.name).write_bytes(f.read_bytes())
        (pkg / "glossrig" / "core").symlink_to(src / "core")
        (pkg / "glossrig" / "cli").symlink_to(src / "cli")
    return pkg


def run_diagnose(caps: dict, out: Path, env: dict | None) -> dict:
    """One ``glossrig diagnose`` in a fresh process; wall, CPU (with its workers), stderr lines
    with their arrival times, the verdict and the causes' gains."""
    if out.exists():
        shutil.rmtree(out)
    argv = [*GLOSSRIG, "diagnose", str(caps["sample"]), "--reference", str(caps["reference"]), "--camera",
            str(caps["camera"]), "--lamps", str(caps["lamps"]), "--out", str(out)]
    load0 = os.getloadavg()[0]
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    assert proc.stdout is not None
    for line in proc.stdout:
        lines.append((time.perf_counter() - t0, line.rstrip("\n")))
    proc.wait()
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode:
        tail = "\n".join(x for _, x in lines[-20:])
        raise SystemExit(f"{' '.join(argv)} exited {proc.returncode}:\n{tail}")
    rep = json.loads((out / "report.json").read_text())
    times = [t for t, _ in lines]
    return {"wall_s": wall, "cpu_s": (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime),
            "load_before": load0, "load_after": os.getloadavg()[0], "lines": lines,
            "longest_silence_s": max(b - a for a, b in zip([0.0] + times, times + [wall])),
            "stages": stage_split(lines, wall), "verdict": rep["verdict"],
            "gains": {c["name"]: c["gain"] for c in rep["causes"]},
            "significant": sorted(c["name"] for c in rep["causes"] if c["significant"])}


def stage_split(lines: list, wall: float) -> list[tuple[str, float]]:
    """Wall seconds of each stage of :data:`STAGES`, from the arrival of the line that ends it."""
    out, prev = [], 0.0
    for name, pat in STAGES:
        hit = next((t for t, x in lines if pat.search(x.removeprefix("glossrig diagnose: "))), None)
        if hit is None:
            continue
        out.append((name, hit - prev))
        prev = hit
    out.append(("process start-up and exit", wall - prev))
    return out


def describe_capture(folder) -> str:
    """A capture's material, LEDs, rotations and scale, read from its manifest (the benchmark may be given
    captures other than its own)."""
    from glossrig.core.capture import load_manifest

    man = load_manifest(folder)
    seq = man.select("sequence")
    leds = sorted({led for im in seq for led in im.leds})
    return (f"{man.material}, {len(leds)} LEDs ({','.join(map(str, leds))}), rotations "
            f"{','.join(f'{r:g}' for r in man.rotations())}, scale {man.meta.get('scale', '?')}, "
            f"{len({im.exposure_s for im in seq})} exposures")


def write_md(path: Path, res: dict, cmd: str) -> None:
    runs = res["runs"]
    new = [r for r in runs if r["code"] == "new"]
    old = [r for r in runs if r["code"] == "baseline"]
    mean = lambda rs, k: sum(r[k] for r in rs) / len(rs)
    lines = ["# `glossrig diagnose` speed (issue 14)", "",
             "Written by `validation/diagnose/speed_benchmark.py`; command:", "", f"    {cmd}", "",
             f"Capture: `{res['captures']['sample']}` ({describe_capture(res['captures']['sample'])}) against "
             f"`{res['captures']['reference']}` ({describe_capture(res['captures']['reference'])}), calibrated "
             "camera and lamps. "
             f"Machine: {os.cpu_count()} cores; load average (1 min) around the runs: "
             + ", ".join(f"{r['load_before']:.1f}" for r in runs) + ". Baseline: the code of commit "
             f"`{res['baseline_commit']}` (core/ and cli/, git archive).", "",
             "| code | wall s | CPU s (with workers) | longest silence on stderr, s | verdict |",
             "|---|---|---|---|---|"]
    for r in runs:
        lines.append(f"| {r['code']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['longest_silence_s']:.1f} | "
                     f"{r['verdict']} |")
    if new and old:
        lines += ["", f"Mean: new {mean(new, 'wall_s'):.1f} s wall / {mean(new, 'cpu_s'):.1f} s CPU; baseline "
                  f"{mean(old, 'wall_s'):.1f} s wall / {mean(old, 'cpu_s'):.1f} s CPU; CPU ratio "
                  f"{mean(old, 'cpu_s') / mean(new, 'cpu_s'):.2f}x."]
    lines += ["", "Stage split (wall s; from the arrival of the stderr line that ends each stage):", "",
              "| stage | " + " | ".join(f"{r['code']} run {i + 1}" for i, r in enumerate(runs)) + " |",
              "|---|" + "---|" * len(runs)]
    names = list(dict.fromkeys(n for r in runs for n, _ in r["stages"]))
    for n in names:
        cells = [next((f"{s:.1f}" for m, s in r["stages"] if m == n), "-") for r in runs]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    same = len({r["verdict"] for r in runs}) == 1
    lines += ["", f"Verdicts {'equal' if same else 'DIFFER'}: " + ", ".join(f"{r['code']} {r['verdict']}" for r in runs)
              + "."]
    if new and old:
        a, b = new[0]["gains"], old[0]["gains"]
        common = sorted(set(a) & set(b))
        worst = max(common, key=lambda k: abs(a[k] - b[k]), default=None)
        if worst is not None:
            lines.append(f"Largest difference of a cause's held-out gain (new - baseline): {worst} "
                         f"{a[worst] - b[worst]:+.2e} ({len(common)} causes compared; significant: new "
                         f"{', '.join(new[0]['significant']) or 'none'}, baseline "
                         f"{', '.join(old[0]['significant']) or 'none'}).")
    lines += ["", "The new code's stderr (first run), with each line's arrival time:", "", "```"]
    lines += [f"{t:7.1f} s  {x}" for t, x in new[0]["lines"]] if new else []
    lines += ["```", ""]
    path.write_text("\n".join(lines))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True, help="folder for the captures, calibrations and reports")
    ap.add_argument("--sample")
    ap.add_argument("--reference")
    ap.add_argument("--camera")
    ap.add_argument("--lamps")
    ap.add_argument("--baseline", default="HEAD", help="commit whose core/ and cli/ are the 'before'")
    ap.add_argument("--runs", type=int, default=1, help="runs of each code (alternating)")
    ap.add_argument("--out", default=str(ROOT / "validation" / "diagnose" / "speed_benchmark.md"))
    a = ap.parse_args()
    w = Path(a.work)
    w.mkdir(parents=True, exist_ok=True)
    given = [a.sample, a.reference, a.camera, a.lamps]
    if any(given) and not all(given):
        ap.error("--sample, --reference, --camera and --lamps go together")
    caps = ({"sample": Path(a.sample), "reference": Path(a.reference), "camera": Path(a.camera),
             "lamps": Path(a.lamps)} if all(given) else make_captures(w))
    base_env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(baseline_tree(w, a.baseline)), str(ROOT)])}
    sha = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", a.baseline], check=True,
                         capture_output=True, text=True).stdout.strip()
    res: dict = {"captures": {k: str(v) for k, v in caps.items()}, "baseline_commit": sha, "runs": []}
    for i in range(a.runs):
        order = [("baseline", base_env), ("new", None)] if i % 2 == 0 else [("new", None), ("baseline", base_env)]
        for code, env in order:
            print(f"run {i + 1}: {code} ...", flush=True)
            r = run_diagnose(caps, w / f"diagnose_{code}", env)
            r["code"] = code
            res["runs"].append(r)
            print(f"  {r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s CPU, verdict {r['verdict']}", flush=True)
    (w / "speed_benchmark.json").write_text(json.dumps(res, indent=1))
    cmd = " ".join(["python -m validation.diagnose.speed_benchmark", *sys.argv[1:]])
    write_md(Path(a.out), res, cmd)
    if len({r["verdict"] for r in res["runs"]}) != 1:
        raise SystemExit("the verdicts differ between the runs (see the report)")
    print(f"written {a.out}")


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
