"""Benchmark of the virtual rig (issues 2 and 19): scene set-up, single-LED render and the
18-exposure sequence derived from one render, with the sensor model's NumPy reference path
(the code of the "before" table) and its Dr.Jit path measured in the same run on the same
render.

    python -m validation.twin.benchmark [--repeats 3] [--scales 0.25,1.0] [--out validation/twin/benchmark.md]

Per scale: scene set-up (``VirtualRig(...)``, then a second one for the same rig in the
same process), the first render (Dr.Jit/Mitsuba JIT compilation included) and a second
render of LED 9, then from it, per repeat, the 18 exposures of Table 4.1 five ways: sensor model
only (``expose_reference`` - the figure the "before" table measured -, the Dr.Jit kernel as
committed in :data:`PREVIOUS` (the first round of issue 19, loaded from git), and ``expose`` of
the radiance prepared once per sequence, its preparation included, as ``VirtualRig.shoot``
does), and whole shots (``VirtualRig.shoot``: LED gain, sensor, DNG written and checksummed)
with the reference and the current sensor path. Times are medians over ``--repeats`` (whole shots: ``--shot-repeats``);
the ratios are of medians taken in this one run. The load average of the machine is recorded with the figures (the machine is
shared: the figures are wall-clock seconds of this process, not of an idle machine).
"""
from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

from validation.paths import RIG, ROOT

AFTER = "## After (issue 19)"
#: The commit whose Dr.Jit sensor kernel (twin/sensor_drjit.py) is measured as "previous".
PREVIOUS = "506e81b"


def _previous_kernel():
    """twin/sensor_drjit.py as of :data:`PREVIOUS`, imported as a sibling module of the current
    one (its relative imports resolve), or None where git or the commit is missing."""
    import importlib.util
    import subprocess
    import sys

    try:
        src = subprocess.run(["git", "show", f"{PREVIOUS}:twin/sensor_drjit.py"], cwd=ROOT, check=True,
                             capture_output=True, text=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    name = f"glossrig.twin._sensor_drjit_{PREVIOUS}"
    spec = importlib.util.spec_from_loader(name, loader=None)
    assert spec is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    exec(compile(src, f"{PREVIOUS}:twin/sensor_drjit.py", "exec"), mod.__dict__)
    return mod


def _expose_previous(kernel, sensor, rate, t, iso, aperture, rng):
    """``SensorModel.expose`` of a prepared radiance (no gain, no effects) with ``kernel``'s noise step."""
    import numpy as np

    seed = int(rng.integers(0, 2 ** 64, dtype=np.uint64))
    e = kernel.noise_dn(rate, seed=seed, dark_e=sensor.dark_current_e_s * t, full_well_e=sensor.full_well_e,
                        read_e=sensor.read_noise_e, inv_k=1.0 / sensor.conversion_gain(iso),
                        black_2x2=sensor.black_2x2(), white=sensor.white_level, scale=(11.0 / aperture) ** 2 * t)
    return e.astype(np.uint16)


class _ReferenceSensor:
    """A sensor model whose ``expose`` is its NumPy reference path (for whole shots)."""

    def __init__(self, model):
        self._model = model

    def expose(self, *args, **kw):
        return self._model.expose_reference(*args, **kw)

    def __getattr__(self, name):
        return getattr(self._model, name)


def _shots(vr, folder: Path, rig, tag: str) -> float:
    vr.switch([9])
    t0 = time.perf_counter()
    for i, t in enumerate(rig.exposure_times_s):
        vr.shoot(folder / f"{tag}_{i:02d}.dng", t, rig.sequence_iso, rig.sequence_aperture)
    return time.perf_counter() - t0


def bench_scale(scale: float, repeats: int, shot_repeats: int) -> dict:
    from glossrig.core.models.materials import parse_material
    from glossrig.core.rig import load_rig
    from glossrig.twin.sensor import frame_rng
    from glossrig.twin.virtual_rig import VirtualRig

    rig = load_rig(RIG)
    material = parse_material("sample_2_6")
    t0 = time.perf_counter()
    vr = VirtualRig(rig, material, scale=scale, seed=0)
    setup = time.perf_counter() - t0
    t0 = time.perf_counter()
    VirtualRig(rig, material, scale=scale, seed=1)
    setup_again = time.perf_counter() - t0
    t0 = time.perf_counter()
    vr.led_radiance(9)
    first = time.perf_counter() - t0
    sensor = vr.sensor
    previous = _previous_kernel()
    keys = ("ref", "prev", "fast") if previous is not None else ("ref", "fast")
    times: dict[str, list[float]] = {k: [] for k in ("render", *keys, "shots_ref", "shots_fast")}
    cpu: dict[str, list[float]] = {k: [] for k in keys}
    vr._cache.clear()
    t0 = time.perf_counter()
    rad = vr.led_radiance(9)
    times["render"].append(time.perf_counter() - t0)
    with tempfile.TemporaryDirectory(prefix="glossrig-twin-bench-") as d:
        for k in range(repeats):
            for key in keys:
                t0, c0 = time.perf_counter(), time.process_time()
                if key == "ref":
                    src, expose = rad, sensor.expose_reference
                elif key == "prev":
                    src = previous.Rate(sensor.expected_electrons(rad, 1.0, 11.0))

                    def expose(rate, t, iso, aperture, rng):
                        return _expose_previous(previous, sensor, rate, t, iso, aperture, rng)
                else:                               # as VirtualRig.shoot does: prepared once per sequence
                    src, expose = sensor.prepare(rad), sensor.expose
                for i, t in enumerate(rig.exposure_times_s):
                    expose(src, t, rig.sequence_iso, rig.sequence_aperture, frame_rng(k, i))
                times[key].append(time.perf_counter() - t0)
                cpu[key].append(time.process_time() - c0)
            if k < shot_repeats:
                for key, model in (("shots_ref", _ReferenceSensor(sensor)), ("shots_fast", sensor)):
                    vr.sensor = model
                    vr._prepared = None
                    times[key].append(_shots(vr, Path(d), rig, f"{key}{k}"))
                    for f in Path(d).glob("*.dng"):
                        f.unlink()
                vr.sensor = sensor
    import drjit as dr

    w, h = vr.lens.size
    med = {k: statistics.median(v) for k, v in times.items()}
    return {"scale": scale, "size": f"{w}x{h}", "threads": dr.thread_count(), "setup_s": setup, "setup_again_s": setup_again,
            "first_render_s": first, **{f"{k}_s": v for k, v in med.items()},
            **{f"{k}_cpu_s": statistics.median(v) for k, v in cpu.items()},
            "runs": {k: [round(x, 2) for x in v] for k, v in times.items()},
            "cpu_runs": {k: [round(x, 2) for x in v] for k, v in cpu.items()}}


def report(rows: list[dict], repeats: int, shot_repeats: int, variant: str, load: tuple[float, float]) -> str:
    lines = [AFTER, "",
             f"Command: `python -m validation.twin.benchmark --repeats {repeats} --shot-repeats {shot_repeats} --scales "
             f"{','.join(str(r['scale']) for r in rows)}`; Mitsuba variant `{variant}`, 4 spp, one LED (9), material "
             f"sample_2_6, ISO 320, the 18 exposures of Table 4.1. Medians of {repeats} runs in one process (whole "
             f"shots: of {shot_repeats}); "
             f"machine load average {load[0]:.2f} before, {load[1]:.2f} after (a shared 2-core machine: wall-clock "
             "seconds, compare ratios, not absolute figures).", "",
             "| scale | image | scene set-up (s) | again, same process (s) | first render incl. JIT (s) | "
             "render, one LED (s) |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scale']} | {r['size']} | {r['setup_s']:.2f} | {r['setup_again_s']:.2f} | "
                     f"{r['first_render_s']:.2f} | {r['render_s']:.2f} |")
    prev = all("prev_s" in r for r in rows)
    lines += ["", f"18-exposure sequence from one render: wall-clock seconds (CPU seconds of the process, all "
              f"threads, in brackets; Dr.Jit ran {rows[0]['threads']} threads on {os.cpu_count()} cores):", "",
              "| scale | sensor model, NumPy reference (before) | "
              + (f"sensor model, Dr.Jit as of {PREVIOUS} | " if prev else "")
              + "sensor model, Dr.Jit | ratio to reference, wall (CPU) | "
              + ("ratio to " + PREVIOUS + ", wall (CPU) | " if prev else "")
              + "whole shots incl. DNG, reference sensor | whole shots incl. DNG, Dr.Jit sensor | ratio |",
              "|---|---|---|---|---|---|---|" + ("---|---|" if prev else "")]

    def ratio(r, a, b):
        return f"{r[a + '_s'] / r[b + '_s']:.1f}x ({r[a + '_cpu_s'] / r[b + '_cpu_s']:.1f}x)"

    for r in rows:
        lines.append(f"| {r['scale']} | {r['ref_s']:.2f} ({r['ref_cpu_s']:.2f}) | "
                     + (f"{r['prev_s']:.2f} ({r['prev_cpu_s']:.2f}) | " if prev else "")
                     + f"{r['fast_s']:.2f} ({r['fast_cpu_s']:.2f}) | {ratio(r, 'ref', 'fast')} | "
                     + (f"{ratio(r, 'prev', 'fast')} | " if prev else "")
                     + f"{r['shots_ref_s']:.2f} | {r['shots_fast_s']:.2f} | {r['shots_ref_s'] / r['shots_fast_s']:.1f}x |")
    lines += ["", "Single runs (s): " + "; ".join(f"scale {r['scale']}: {r['runs']}, CPU {r['cpu_runs']}" for r in rows),
              ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scales", default="0.25,1.0")
    ap.add_argument("--shot-repeats", type=int, default=1, help="repeats of the whole-shot sequences (DNGs written)")
    ap.add_argument("--out", default=str(ROOT / "validation/twin/benchmark.md"))
    a = ap.parse_args()
    from glossrig.twin.mitsuba_env import choose_variant

    variant = choose_variant()
    load0 = os.getloadavg()[0]
    rows = [bench_scale(float(s), a.repeats, a.shot_repeats) for s in a.scales.split(",")]
    text = report(rows, a.repeats, a.shot_repeats, variant, (load0, os.getloadavg()[0]))
    out = Path(a.out)
    old = out.read_text() if out.exists() else "# Virtual rig benchmark\n\n"
    keep = old.split(AFTER)[0].rstrip() + "\n\n"          # the "before" section stays as it was
    out.write_text(keep + text)
    print(text)


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
