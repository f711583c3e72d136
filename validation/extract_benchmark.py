"""Benchmark of ``glossrig extract`` at full resolution (issue 3): seconds, megapixels
per second and peak memory, split by stage.

    python -m validation.extract_benchmark --work /tmp/bench_extract [--leds 9,10] [--repeats 3]

1. Simulates (once; reused when complete) full-resolution (scale 1.0, 6032 x 4032)
   twin captures of the sample (``sample_2_6``) and the ``lambert:0.8`` reference with
   the given middle-row LEDs x repeats x the thesis's 18 exposures, and a camera file
   (checkerboards calibrated at scale 0.25, camera matrix scaled by 4: the twin's K
   scales exactly so).
2. For each LED count k of ``--counts`` (default 1, 2 and all simulated LEDs), builds
   captures holding only the first k LEDs (manifests filtered, raw files linked,
   nothing copied) and runs the extraction of sample + reference - the function
   ``glossrig extract`` calls, with the same Parquet output - in a fresh process per k,
   with every stage timed by wrapping the pipeline's own functions, the process's peak
   resident memory (ru_maxrss) recorded after each stage, and the machine's load
   average before and after (the machine is shared: CPU seconds are the figures to read).
3. Writes the Markdown report (``--out``). With all 8 middle-row LEDs simulated
   (``--leds 9,10,5,6,7,8,11,12``) the thesis capture (8 LEDs x 3 repeats) is measured;
   with fewer it is stated as a linear extrapolation in the number of LEDs, labelled so.

Lamp positions are the rig file's nominal ones (the benchmark times the work, the
accuracy is in validation/pipeline_report.md).

With ``--compare`` (issue 19; the "after" section of validation/extract_benchmark.md)
one command measures, each in a fresh process, one after the other on the same captures
(all their LEDs):

(a) the decode floor: rawpy decoding every raw file an extraction reads (both captures'
    sequence and calibration images; ``rawpy.imread`` + the visible raw image) in
    ``--workers`` processes;
(b) ``extract_samples`` (what ``glossrig extract`` runs) with ``--workers`` processes,
    then with one; (c) the peak resident memory of each run's whole process tree
    (the extraction and its workers, summed, sampled every 0.1 s from /proc);
(d) the tables' largest differences: the run with workers against the one without, and
    against the code of the ``--baseline`` commit (by default the last before issue 19; run
    from a ``git archive`` of its ``core/``, with ``--workers`` processes where its
    ``extract_samples`` takes them, else one), per column, on the rows both have.

The captures are made once and reused; captures of fewer LEDs in ``--work`` (an earlier
run's) are extended to ``--leds`` by simulating only the added LEDs (:func:`simulate_captures`).

The camera file is the twin's true intrinsics (truth.json); it changes no timing.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

from validation.common import camera, capture, truth_camera
from validation.paths import RIG, ROOT

FRAME_MP = 6032 * 4032 / 1e6


def prepare(w: Path, leds: str, repeats: int) -> None:
    if not (w / "camera.json").exists():
        camera(w / "camera_q.json", w / "checker", 10, 0.25, 1)
        c = json.loads((w / "camera_q.json").read_text())
        for k in ("fx", "fy"):
            c[k] *= 4
        for k in ("cx", "cy"):
            c[k] = (c[k] + 0.5) * 4 - 0.5
        c["camera_matrix"] = [[c["fx"], 0, c["cx"]], [0, c["fy"], c["cy"]], [0, 0, 1]]
        c["image_size"] = [6032, 4032]
        (w / "camera.json").write_text(json.dumps(c))
    simulate_captures(w, leds, repeats)


def simulate_captures(w: Path, leds: str, repeats: int, scale: float = 1.0) -> None:
    """The sample and reference captures in ``w`` (``sample``, ``reference``): made once and
    reused; a capture of the first of ``leds`` (an earlier run with fewer) is extended to
    all of them, its images kept (:func:`validation.common.extend_leds`), and an interrupted
    one completed."""
    for name, mat, seed in (("sample", "sample_2_6", 2), ("reference", "lambert:0.8", 3)):
        capture(w / name, mat, scale, seed, "0", repeats, leds=leds, mode="extend")


def subset(src: Path, dst: Path, leds: list[int]) -> Path:
    """A capture folder with only the calibration image and ``leds``' sequences of ``src``."""
    d = json.loads((src / "capture.json").read_text())
    d["images"] = [im for im in d["images"] if im["role"] != "sequence" or im["leds"][0] in leds]
    # the manifest's rig may be relative to its folder (captures hold a rig.toml copy): point at the original
    d["rig"] = str((src / d["rig"]).resolve())
    dst.mkdir(parents=True, exist_ok=True)
    for im in d["images"]:
        link = dst / im["file"]
        if not link.exists():
            os.symlink(src / im["file"], link)
    (dst / "capture.json").write_text(json.dumps(d))
    return dst


# ----------------------------------------------------------------- measuring (child process)

STAGES = [  # (label, module, attribute); nested ones are subtracted from their parent
    ("geometry", "glossrig.core.extraction.extract", "rotation_geometry"),
    ("poses", "glossrig.core.calibration.poses", "calibrate_capture"),
    ("raw_read", "glossrig.core.calibration.raw", "read_raw"),     # via Manifest.read_raw (checksum + decode)
    ("linearise_stack", "glossrig.core.radiometry.hdr", "stream_stack"),   # reads its frames (raw_read) inside
    ("hdr", "glossrig.core.radiometry.hdr", "hdr_from_stack"),
    ("patch_blocks", "glossrig.core.extraction.extract", "normalise_by_patch"),
    ("patch_blocks", "glossrig.core.extraction.extract", "block_values"),
    ("angles", "glossrig.core.extraction.extract", "sample_angles"),
    ("diffuse_normalise", "glossrig.core.extraction.extract", "diffuse_normalize"),
    ("write_parquet", "glossrig.core.samples", "write_samples"),
]


def peak_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2


def measure(sample: Path, reference: Path, camera: Path, out_json: Path) -> None:
    import importlib

    import numpy as np

    secs, cpu, calls, peak_after, crop = {}, {}, {}, {}, []

    def wrap(label, fn):
        def timed(*a, **k):
            t0, c0 = time.perf_counter(), time.process_time()
            try:
                res = fn(*a, **k)
                if label == "geometry":
                    crop.append(list(res.crop))
                return res
            finally:
                secs[label] = secs.get(label, 0.0) + time.perf_counter() - t0
                cpu[label] = cpu.get(label, 0.0) + time.process_time() - c0
                calls[label] = calls.get(label, 0) + 1
                peak_after[label] = peak_gb()
        return timed

    for label, mod, attr in STAGES:
        m = importlib.import_module(mod)
        setattr(m, attr, wrap(label, getattr(m, attr)))
    from glossrig.core import samples
    from glossrig.core.extraction.extract import extract_samples
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.rig import load_rig

    cam = load_camera(camera)
    lamps = {l.id: np.array(l.position) for l in load_rig(RIG).leds}
    base = peak_gb()
    load0 = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    df = extract_samples(sample, reference, cam, lamps)
    pq = out_json.with_suffix(".parquet")
    samples.write_samples(df, pq)
    total, total_cpu = time.perf_counter() - t0, time.process_time() - c0
    out_json.write_text(json.dumps({"seconds": secs, "cpu_seconds": cpu, "total_cpu_s": total_cpu, "calls": calls, "peak_gb_after": peak_after, "total_s": total,
                                    "peak_gb": peak_gb(), "peak_gb_after_imports": base, "rows": len(df),
                                    "parquet_mb": pq.stat().st_size / 1e6, "crops": crop,
                                    "load_average": [load0, os.getloadavg()[0]]}))


# ----------------------------------------------------------------- issue 19: floor, workers, memory, differences

MARK_BEGIN, MARK_END = "<!-- compare:begin -->", "<!-- compare:end -->"


def raw_files(*captures: Path) -> list[Path]:
    """Every image file of the captures' manifests that an extraction reads."""
    out = []
    for c in captures:
        d = json.loads((c / "capture.json").read_text())
        out += [c / im["file"] for im in d["images"] if im["role"] in ("sequence", "calibration")]
    return out


def _decode(path: str) -> int:
    import rawpy

    with rawpy.imread(path) as raw:
        return int(raw.raw_image_visible.shape[0])


def decode_floor(files: list[Path], workers: int, out_json: Path) -> None:
    """(a): rawpy decoding ``files`` in ``workers`` spawned processes (as the extraction's pool)."""
    from concurrent.futures import ProcessPoolExecutor
    import multiprocessing

    t0 = time.perf_counter()
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        list(pool.map(_decode, [str(f) for f in files], chunksize=4))
    wall = time.perf_counter() - t0
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    out_json.write_text(json.dumps({"wall_s": wall, "cpu_s": ru.ru_utime + ru.ru_stime, "files": len(files),
                                    "bytes": sum(f.stat().st_size for f in files)}))


def extract_run(sample: Path, reference: Path, camera_json: Path, workers: int, out_parquet: Path) -> None:
    """(b): ``extract_samples`` with ``workers`` processes; code whose ``extract_samples`` has
    no ``workers`` (before issue 19) is called without it (one process). The processes used
    are recorded."""
    import inspect
    import pickle

    import numpy as np

    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.extraction.extract import extract_samples
    from glossrig.core.rig import load_rig

    cam = load_camera(camera_json)
    lamps = {l.id: np.array(l.position) for l in load_rig(RIG).leds}
    has_workers = "workers" in inspect.signature(extract_samples).parameters
    t0, c0 = time.perf_counter(), time.process_time()
    df = extract_samples(sample, reference, cam, lamps, **({"workers": workers} if has_workers else {}))
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    df.to_parquet(out_parquet)
    out_parquet.with_suffix(".report.pkl").write_bytes(pickle.dumps(df.attrs.get("dynamic_range")))
    out_parquet.with_suffix(".json").write_text(json.dumps({"wall_s": wall, "cpu_s": cpu + ru.ru_utime + ru.ru_stime,
                                                            "rows": len(df), "workers": workers if has_workers else 1}))


def _tree_rss(root: int) -> int:
    """Resident bytes of process ``root`` and all its descendants (Linux /proc)."""
    kids: dict[int, list[int]] = {}
    rss: dict[int, int] = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                st = f.read().rsplit(")", 1)[1].split()
            kids.setdefault(int(st[1]), []).append(int(d))
            rss[int(d)] = int(st[21]) * os.sysconf("SC_PAGE_SIZE")
        except (OSError, IndexError, ValueError):
            continue
    total, stack = 0, [root]
    while stack:
        p = stack.pop()
        total += rss.get(p, 0)
        stack += kids.get(p, [])
    return total


def run_sampled(argv: list[str], env: dict | None = None) -> dict:
    """Run ``argv``; its process tree's peak summed RSS (GB, 0.1 s samples) and wall time."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, env=env)
    peak = 0
    while proc.poll() is None:
        peak = max(peak, _tree_rss(proc.pid))
        time.sleep(0.1)
    if proc.returncode:
        raise SystemExit(f"{' '.join(argv)} exited {proc.returncode}")
    return {"peak_tree_gb": peak / 1e9, "process_wall_s": time.perf_counter() - t0}


def baseline_tree(w: Path, commit: str) -> Path:
    """A package folder whose ``glossrig.core`` is ``core/`` of ``commit`` (git archive), for
    running the code before issue 19 beside this checkout."""
    pkg = w / f"baseline-{commit[:10]}"
    if not (pkg / "glossrig" / "core").is_dir():
        src = w / f"baseline-src-{commit[:10]}"
        src.mkdir(parents=True, exist_ok=True)
        arch = subprocess.run(["git", "-C", str(ROOT), "archive", commit, "core", "cli/toplevel"],
                              check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(src)], input=arch, check=True)
        (pkg / "glossrig").mkdir(parents=True, exist_ok=True)
        for f in (src / "cli" / "toplevel").glob("*.py"):
            (pkg / "glossrig" / f.name).write_bytes(f.read_bytes())
        (pkg / "glossrig" / "core").symlink_to(src / "core")
    return pkg


def differences(a_path: Path, b_path: Path) -> dict:
    """Per float column: the largest relative difference of finite pairs, and the NaN mismatches;
    other columns must be equal."""
    import numpy as np
    import pandas as pd

    a, b = pd.read_parquet(a_path), pd.read_parquet(b_path)
    out: dict = {"same_rows": True, "rows": len(a), "columns": {}}
    if list(a.columns) != list(b.columns):
        return {"same_rows": False, "rows": [len(a), len(b)]}
    if len(a) != len(b):            # compare the rows both have (a sample row is its block, LED and rotation)
        keys = ["u", "v", "led", "rotation"]
        m = a.merge(b, on=keys, suffixes=("", " (b)"))         # a suffix no column name ends with
        out = {"same_rows": False, "rows": [len(a), len(b)], "common_rows": len(m), "columns": {}}
        other = [c for c in a.columns if c not in keys]
        a, b = m[list(a.columns)], m[keys + [f"{c} (b)" for c in other]].set_axis(keys + other, axis=1)[list(a.columns)]
    for c in a.columns:
        x, y = a[c].to_numpy(), b[c].to_numpy()
        if x.dtype.kind != "f":
            out["columns"][c] = {"equal": bool(np.array_equal(x, y))}
            continue
        ok = np.isfinite(x) & np.isfinite(y)
        rel = np.abs(x[ok] - y[ok]) / np.maximum(np.abs(x[ok]), np.finfo(float).tiny)
        out["columns"][c] = {"max_rel": float(rel.max()) if rel.size else 0.0,
                             "over_1e-6": int((rel > 1e-6).sum()),
                             "nan_mismatch": int((np.isnan(x) != np.isnan(y)).sum()),
                             "identical": bool(np.array_equal(x, y, equal_nan=True))}
    return out


def compare(a, w: Path) -> dict:
    """(a)-(d) on the captures in ``w``; results kept in ``w/compare.json``."""
    res: dict = {"workers": a.workers, "leds": a.leds, "repeats": a.repeats, "baseline_commit": a.baseline,
                 "load_average": [os.getloadavg()[0]]}
    files = raw_files(w / "sample", w / "reference")
    me = [sys.executable, "-m", "validation.extract_benchmark", "--work", str(w)]
    res["floor"] = run_sampled(me + ["--decode-floor", str(a.workers), str(w / "floor.json")])
    res["floor"].update(json.loads((w / "floor.json").read_text()))
    res["load_average"].append(os.getloadavg()[0])
    cam = w / "camera.json"
    # the baseline before the one-process run: its differences matter more than that run's time
    runs = {f"workers{a.workers}": (a.workers, None), "baseline": (a.workers, a.baseline), "workers1": (1, None)}
    earlier = json.loads((w / "compare.json").read_text()) if (w / "compare.json").exists() else {}
    partial = w / "compare.partial.json"      # what is measured so far, should the command be stopped
    for name, (n, commit) in runs.items():
        if name == "baseline" and a.reuse_baseline and "baseline" in earlier:
            res[name] = {**earlier["baseline"], "reused_from_earlier_run": True}   # its code does not change
            continue
        env = None
        if commit:
            env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(baseline_tree(w, commit)), str(ROOT)])}
        pq = w / f"{name}.parquet"
        r = run_sampled(me + ["--extract-run", str(w / "sample"), str(w / "reference"), str(cam), str(n), str(pq)], env)
        r.update(json.loads(pq.with_suffix(".json").read_text()))
        res[name] = r
        res["load_average"].append(os.getloadavg()[0])
        partial.write_text(json.dumps(res, indent=1))
    import pickle

    res["diff_vs_workers1"] = differences(w / "workers1.parquet", w / f"workers{a.workers}.parquet")
    res["diff_vs_baseline"] = differences(w / "baseline.parquet", w / f"workers{a.workers}.parquet")
    rep = {k: pickle.loads((w / f"{k}.report.pkl").read_bytes()) for k in ("workers1", f"workers{a.workers}")}
    res["dynamic_range_report_equal_vs_workers1"] = rep["workers1"] == rep[f"workers{a.workers}"]
    if (w / "baseline.report.pkl").exists() and not res["baseline"].get("reused_from_earlier_run"):
        res["dynamic_range_report_equal_vs_baseline"] = (
            pickle.loads((w / "baseline.report.pkl").read_bytes()) == rep[f"workers{a.workers}"])
    res["raw_files"], res["raw_gb"] = len(files), sum(f.stat().st_size for f in files) / 1e9
    res["memory_gb"] = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 1e9
    (w / "compare.json").write_text(json.dumps(res, indent=1))
    return res


def compare_section(res: dict, a) -> str:
    n = res["workers"]
    new, one, old, fl = res[f"workers{n}"], res["workers1"], res["baseline"], res["floor"]

    def worst(d: dict, cols=None) -> str:
        if not d.get("same_rows") and "common_rows" not in d:
            return f"rows differ ({d.get('rows')})"
        rows = ("" if d.get("same_rows") else
                f"rows differ ({d['rows'][0]} against {d['rows'][1]}), on the {d['common_rows']} rows both have: ")
        items = [(c, v) for c, v in d["columns"].items() if "max_rel" in v and (cols is None or c in cols)]
        c, v = max(items, key=lambda cv: cv[1]["max_rel"])
        nan = sum(v2.get("nan_mismatch", 0) for _, v2 in items)
        over = sum(v2.get("over_1e-6", 0) for _, v2 in items)
        neq = [c2 for c2, v2 in d["columns"].items() if v2.get("equal") is False]
        return (f"{rows}largest relative difference {v['max_rel']:.3g} (column {c}); {over} values differ by more than "
                f"1e-6 relative; {nan} NaN mismatches; integer columns "
                + ("all equal" if not neq else f"differ: {', '.join(neq)}"))

    cols = ("r", "g", "b", "weight", "weight_r", "weight_g", "weight_b")
    commit = res["baseline_commit"]
    old_name = f"commit {commit[:10]}" + (" (before issue 19)" if commit.startswith("ef7b09d") else "")
    old_n = old.get("workers", 1)
    n_leds = len(str(a.leds).split(","))
    if n_leds == 8 and a.repeats == 3:
        scope = "**the thesis capture** (all 8 middle-row LEDs)"
    else:
        scope = (f"**a subset of the thesis capture** (8 LEDs x 3 repeats, 866 raw files), {res['raw_files']} raw "
                 "files, because simulating all 8 LEDs at full resolution took the twin longer than that session's "
                 "CPU budget")
    mem = res.get("memory_gb")
    cache = ("" if mem is None else
             f" The raw files ({res['raw_gb']:.1f} GB) are "
             + (f"more than the machine's {mem:.0f} GB of memory: no run can be served from the page cache alone, "
                "each reads most of its files from disk." if res["raw_gb"] > mem else
                f"less than the machine's {mem:.0f} GB of memory: runs may be served from the page cache."))
    rep_old = res.get("dynamic_range_report_equal_vs_baseline")
    lines = [MARK_BEGIN, "## After issue 19: parallel, streamed extraction against the decode floor", "",
             "Command (simulates the captures once, then measures each item in a fresh process):", "",
             f"    nice -n 10 python -m validation.extract_benchmark --work {a.work} --leds {a.leds} "
             f"--repeats {a.repeats} --compare --workers {n} --baseline {a.baseline}", "",
             f"Measured on twin captures at scale 1.0 (6032 x 4032, 48 MB uncompressed DNGs) of `sample_2_6` and the "
             f"`lambert:0.8` reference, LEDs {a.leds} x {a.repeats} repeats x 18 exposures, one rotation: "
             f"{scope}; {res['raw_files']} raw files ({res['raw_gb']:.1f} GB).{cache} "
             f"The machine has {os.cpu_count()} cores and was shared with other "
             f"engineers' work while this ran (1-minute load average at the start and after, in turn, the decode floor, the run with "
             f"{n} workers, the {old_name} run and the one-process run: "
             f"{', '.join(f'{x:.1f}' for x in res['load_average'])}); absolute seconds are inflated by that load, "
             "the ratios below are between runs made one after the other in the same command.", "",
             "| run | wall s | CPU s (all processes) | peak RSS of the process tree | rows |", "|---|---|---|---|---|",
             f"| (a) decode floor: rawpy decodes the same {fl['files']} files, {n} processes | {fl['wall_s']:.1f} | "
             f"{fl['cpu_s']:.1f} | {fl['peak_tree_gb']:.2f} GB | |",
             f"| (b) `extract_samples`, {n} worker processes | {new['wall_s']:.1f} | {new['cpu_s']:.1f} | "
             f"{new['peak_tree_gb']:.2f} GB | {new['rows']} |",
             f"| `extract_samples`, 1 process (`--workers 1`) | {one['wall_s']:.1f} | {one['cpu_s']:.1f} | "
             f"{one['peak_tree_gb']:.2f} GB | {one['rows']} |",
             f"| {old_name}, {old_n} process{'es' if old_n > 1 else ''} | {old['wall_s']:.1f} | {old['cpu_s']:.1f} | "
             f"{old['peak_tree_gb']:.2f} GB | {old['rows']} |", "",
             *(["The 'before' row is from the previous `--compare` run on the same captures (`--reuse-baseline`: "
                "its code does not change); the other rows are from this one.", ""] if old.get("reused_from_earlier_run")
               else []),
             f"**Wall time of the extraction with {n} workers / decode floor with {n} processes: "
             f"{new['wall_s'] / fl['wall_s']:.2f}** (target at most 1.5); against the code of {old_name}: "
             f"its wall time / this code's {old['wall_s'] / new['wall_s']:.2f}, its CPU / this code's "
             f"{old['cpu_s'] / new['cpu_s']:.2f}. "
             f"Peak memory {new['peak_tree_gb']:.2f} GB for the extraction and its workers together (target under 4 GB).",
             "",
             f"Differences (d), values r, g, b and weights: {n} workers against 1: "
             f"{worst(res['diff_vs_workers1'], cols)}; dynamic-range report "
             f"{'identical' if res['dynamic_range_report_equal_vs_workers1'] else 'DIFFERENT'}. "
             f"Against the code of {old_name}: {worst(res['diff_vs_baseline'], cols)}; every column: "
             f"{worst(res['diff_vs_baseline'])}"
             + ("" if rep_old is None else f"; dynamic-range report {'identical' if rep_old else 'DIFFERENT'}")
             + ".", "", MARK_END]
    return "\n".join(lines)


def write_compare(res: dict, a) -> None:
    path = Path(a.out)
    text = path.read_text() if path.exists() else ""
    sec = compare_section(res, a)
    if MARK_BEGIN in text and MARK_END in text:
        text = text[:text.index(MARK_BEGIN)] + sec + text[text.index(MARK_END) + len(MARK_END):]
    else:
        text = sec + "\n\n" + text
    path.write_text(text)
    print(sec)


# ----------------------------------------------------------------- report

LABELS = {
    "poses": "calibration image: read, demosaic, markers, poses (eq. 4.1-4.25)",
    "geometry_rest": "crop, white-patch mask, ray casting (eq. 4.26-4.30)",
    "raw_read": "raw read + crop (sha256 check, rawpy, EXIF checks)",
    "linearise_stack": "linearise + combine repeats (eq. 4.1-4.2, 4.31)",
    "hdr": "neighbour correction + HDR (eq. 4.32-4.44)",
    "patch_blocks": "patch normalisation + Bayer-block values (eq. 4.45-4.50)",
    "angles": "angles (4.3.5)",
    "diffuse_normalise": "diffuse normalisation, KD-tree (4.4)",
    "write_parquet": "write Parquet",
}


def report(runs: dict[int, dict], args) -> str:
    k_max = max(runs)
    r = runs[k_max]
    x0, y0, x1, y1 = r["crops"][0]
    crop = (x1 - x0, y1 - y0)
    frames_per_led = 2 * args.repeats * 18               # sample + reference
    n_frames = {k: k * frames_per_led for k in runs}
    n_cal = 2

    loads = ", ".join(f"{k} LED{'s' if k > 1 else ''} {runs[k]['load_average'][0]:.1f} / "
                      f"{runs[k]['load_average'][1]:.1f}" for k in sorted(runs) if "load_average" in runs[k])

    def stage(run, key, what="cpu_seconds"):
        s = run[what]
        if key == "geometry_rest":
            return s.get("geometry", 0) - s.get("poses", 0)
        return s.get(key, 0.0)

    lines = ["# `glossrig extract` at full resolution (6032 x 4032, 24.3 MP)", "",
             "Command (simulates the captures once, then runs one measuring process per LED count):", "",
             f"    nice -n 5 python -m validation.extract_benchmark --work {args.work} --leds {args.leds} "
             f"--repeats {args.repeats} --counts {args.counts}", "",
             f"Measured: twin captures at scale 1.0 of `sample_2_6` and the `lambert:0.8` reference, LEDs "
             f"{args.leds} x {args.repeats} repeats x 18 exposures each (48 MB DNGs), one rotation; the "
             f"extraction of sample + reference as `glossrig extract` runs it (same function, same Parquet "
             f"output), for the first k LEDs of that list. Each raw file is decoded whole by rawpy and cropped "
             f"to {crop[0]} x {crop[1]} px ({crop[0] * crop[1] / 1e6:.2f} MP: the sample and the holder's "
             f"white patch).", "",
             f"The machine has {os.cpu_count()} cores and was shared with other work while this ran (load "
             f"average at the start / end of each measuring process: {loads}); the {k_max}-LED run's wall "
             f"time was {r['total_s'] / r['total_cpu_s']:.1f}x its CPU time. The CPU seconds (all threads of "
             "the process; `time.process_time`) are the figures to read; rates below are per CPU second. On "
             "an unshared machine the wall time would be about the CPU time plus file reading, less where "
             "numpy/OpenCV use both cores.", "",
             "## Measured, by stage (CPU seconds)", "",
             "| stage | " + " | ".join(f"{k} LED{'s' if k > 1 else ''}" for k in sorted(runs)) +
             f" | rate ({k_max} LEDs) | wall s ({k_max} LEDs) | peak RSS after stage ({k_max} LEDs) |",
             "|---|" + "---|" * len(runs) + "---|---|---|"]
    for key, label in LABELS.items():
        vals = " | ".join(f"{stage(runs[k], key):.1f}" for k in sorted(runs))
        c = stage(r, key)
        if key == "poses":
            rate = f"{n_cal * FRAME_MP / c:.2f} MP/s ({n_cal} calibration images)"
        elif key in ("raw_read", "linearise_stack", "hdr", "patch_blocks"):
            rate = (f"{n_frames[k_max] * FRAME_MP / c:.0f} MP/s of raw frames ({n_frames[k_max]}), "
                    f"{n_frames[k_max] * crop[0] * crop[1] / 1e6 / c:.0f} MP/s of cropped pixels")
        else:
            rate = ""
        pk = r["peak_gb_after"].get("geometry" if key == "geometry_rest" else key)
        lines.append(f"| {label} | {vals} | {rate} | {stage(r, key, 'seconds'):.0f} | "
                     + (f"{pk:.2f} GB |" if pk is not None else "|"))
    other = {k: runs[k]["total_cpu_s"] - sum(stage(runs[k], key) for key in LABELS) for k in runs}
    wall_other = r["total_s"] - sum(stage(r, key, "seconds") for key in LABELS)
    lines.append("| other (manifests, checks, tables) | " + " | ".join(f"{other[k]:.1f}" for k in sorted(runs))
                 + f" | | {wall_other:.0f} | |")
    lines.append("| **total** | " + " | ".join(f"**{runs[k]['total_cpu_s']:.1f}**" for k in sorted(runs)) +
                 f" | {(n_frames[k_max] + n_cal) * FRAME_MP / r['total_cpu_s']:.0f} MP/s of all raw frames | "
                 f"{r['total_s']:.0f} | |")
    lines += ["", "| LEDs | raw files read (sample + reference) | CPU s | wall s | peak RSS GB | rows |",
              "|---|---|---|---|---|---|"]
    for k in sorted(runs):
        lines.append(f"| {k} | {n_frames[k] + n_cal} | {runs[k]['total_cpu_s']:.1f} | {runs[k]['total_s']:.0f} | "
                     f"{runs[k]['peak_gb']:.2f} | {runs[k]['rows']} |")
    ks = sorted(runs)
    if len(ks) >= 2:
        pairs = list(zip(ks[:-1], ks[1:]))
        lines += ["", "## Cost per added LED", "",
                  f"Increments between successive measured runs, per added LED (sample + reference, "
                  f"{frames_per_led} raw files each). A stage whose increment grows from one interval to the next "
                  "grows faster than the number of LEDs.", "",
                  "| stage | " + " | ".join(f"{a} -> {b} LEDs" for a, b in pairs) + " |",
                  "|---|" + "---|" * len(pairs)]
        for key, label in LABELS.items():
            lines.append(f"| {label} | " + " | ".join(
                f"{(stage(runs[b], key) - stage(runs[a], key)) / (b - a):+.1f} CPU s" for a, b in pairs) + " |")
        lines.append("| **total** | " + " | ".join(
            f"**{(runs[b]['total_cpu_s'] - runs[a]['total_cpu_s']) / (b - a):+.1f} CPU s**" for a, b in pairs) + " |")
        lines.append("| peak memory | " + " | ".join(
            f"{(runs[b]['peak_gb'] - runs[a]['peak_gb']) / (b - a):+.2f} GB" for a, b in pairs) + " |")
        lines += ["", f"The raw frames are streamed (one LED's {args.repeats * 18} cropped frames at a time), but the "
                  f"per-block table of every LED is kept until the diffuse normalisation (sample and reference, "
                  f"~{r['rows'] // k_max / 1e3:.0f}k rows per LED and capture), so memory grows with the LEDs and "
                  f"peaks in the KD-tree stage. The Parquet output is {r['parquet_mb'] / k_max:.0f} MB per LED "
                  f"({r['rows'] // k_max} rows)."]
        n8 = 8 * frames_per_led + n_cal
        if 8 in runs:
            r8 = runs[8]
            lines += ["", "## A thesis capture (8 LEDs x 3 repeats x 18 exposures), measured", "",
                      f"Sample + reference, {n8} raw files, {n8 * FRAME_MP:.0f} MP: **{r8['total_cpu_s']:.0f} CPU s "
                      f"({r8['total_cpu_s'] / 60:.1f} min) per rotation, {n8 * FRAME_MP / r8['total_cpu_s']:.0f} MP/s "
                      f"per CPU second, peak memory {r8['peak_gb']:.2f} GB** (of the machine's 24 GB); "
                      f"wall {r8['total_s']:.0f} s on the shared machine."]
        else:
            a, b = pairs[-1]
            per_led = (runs[b]["total_cpu_s"] - runs[a]["total_cpu_s"]) / (b - a)
            dpk = (runs[b]["peak_gb"] - runs[a]["peak_gb"]) / (b - a)
            t8 = runs[b]["total_cpu_s"] + (8 - b) * per_led
            lines += ["", "## Extrapolated to a thesis capture (not measured)", "",
                      f"**Linear extrapolation from the {a}- and {b}-LED runs to 8 LEDs x 3 repeats x 18 exposures** "
                      f"(sample + reference, {n8} raw files, {n8 * FRAME_MP:.0f} MP): **{t8:.0f} CPU s "
                      f"({t8 / 60:.1f} min) per rotation, {n8 * FRAME_MP / t8:.0f} MP/s per CPU second, "
                      f"{runs[b]['peak_gb'] + (8 - b) * dpk:.1f} GB peak** - not measured, and a lower bound where a "
                      "stage grows faster than linearly: simulate all 8 middle-row LEDs to measure it."]
    lines += ["", "At scale 1.0 the twin renders each output pixel from one read of its pinhole canvas "
              "(`twin/render.py`, `LensMap.MAX_CANVAS_MP`); the extraction's cost does not depend on that."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True)
    ap.add_argument("--leds", default="9,10", help="middle-row LEDs to simulate (comma-separated)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--counts", default="1,2,all",
                    help="LED counts to measure (first k of --leds), comma-separated; 'all' = every LED of --leds")
    ap.add_argument("--out", default=None,
                    help="report: with --compare its section of validation/extract_benchmark.md is replaced (default); "
                         "else the stage tables go to validation/extract_benchmark_stages.md (default)")
    ap.add_argument("--compare", action="store_true",
                    help="issue 19: decode floor, workers, memory and differences (module docstring)")
    ap.add_argument("--workers", type=int, default=2, help="with --compare: worker processes")
    ap.add_argument("--baseline", default="ef7b09d",
                    help="with --compare: the commit whose extraction is the 'before' (default: the last one "
                         "before issue 19's extraction work)")
    ap.add_argument("--reuse-baseline", action="store_true",
                    help="with --compare: keep the baseline's figures from the previous --compare run in WORK")
    ap.add_argument("--measure", nargs=4, metavar=("SAMPLE", "REF", "CAMERA", "OUT_JSON"), help=argparse.SUPPRESS)
    ap.add_argument("--decode-floor", nargs=2, metavar=("WORKERS", "OUT_JSON"), help=argparse.SUPPRESS)
    ap.add_argument("--extract-run", nargs=5, metavar=("SAMPLE", "REF", "CAMERA", "WORKERS", "OUT"),
                    help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.out is None:
        a.out = str(ROOT / "validation" / ("extract_benchmark.md" if a.compare else "extract_benchmark_stages.md"))
    if a.measure:
        measure(*map(Path, a.measure))
        return
    w = Path(a.work)
    if a.decode_floor:
        decode_floor(raw_files(w / "sample", w / "reference"), int(a.decode_floor[0]), Path(a.decode_floor[1]))
        return
    if a.extract_run:
        s_, r_, c_, n_, o_ = a.extract_run
        extract_run(Path(s_), Path(r_), Path(c_), int(n_), Path(o_))
        return
    w.mkdir(parents=True, exist_ok=True)
    if a.compare:
        simulate_captures(w, a.leds, a.repeats)
        truth_camera(w / "sample", w / "camera.json")
        write_compare(compare(a, w), a)
        return
    prepare(w, a.leds, a.repeats)
    leds = [int(x) for x in a.leds.split(",")]
    counts = sorted({len(leds) if c == "all" else int(c) for c in a.counts.split(",")})
    if not counts or counts[0] < 1 or counts[-1] > len(leds):
        ap.error(f"--counts {a.counts}: each count must be 1..{len(leds)} (the LEDs of --leds)")
    runs = {}
    for k in counts:
        res = w / f"bench_{k}led.json"
        if not res.exists():
            s = subset(w / "sample", w / f"sample_{k}led", leds[:k])
            r = subset(w / "reference", w / f"reference_{k}led", leds[:k])
            subprocess.run([sys.executable, "-m", "validation.extract_benchmark", "--work", str(w), "--measure", str(s),
                            str(r), str(w / "camera.json"), str(res)], check=True)
        runs[k] = json.loads(res.read_text())
        print(k, "LEDs:", json.dumps(runs[k]))
    text = report(runs, a)
    Path(a.out).write_text(text)
    print(text)


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
