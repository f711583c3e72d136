"""``glossrig design exposures``: per-LED exposures for one material, as a capture plan.

Chooses, per LED, the exposures of the rig's table that keep every pixel's HDR
estimate within a noise target at the least capture time
(:mod:`glossrig.core.radiometry.exposure_plan`), and writes a capture plan in the format of
``scenes/plans/*.toml`` (:data:`glossrig.hardware.plan.PLAN_FORMAT`) with the
per-LED exposures in its ``[led_exposures_s]`` table. The written plan is read back
with the hardware layer's loader, which prints its time against the thesis's full
plan (table 4.1, three sequences per LED).

    glossrig design exposures --rig scenes/thesis_rig.toml --material sample_2_6 \\
        --leds middle --rotations 0 --out plan.toml
"""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path

from glossrig.cli.outputs import add_force_option, prepare_output
from glossrig.core.errors import InputError

_log = logging.getLogger(__name__)

HELP = "per-LED exposures keeping the HDR noise within a target at least capture time; writes a capture plan"


def add_arguments(p) -> None:
    p.add_argument("--rig", required=True, help="rig file (scenes/*.toml)")
    p.add_argument("--material", required=True,
                   help="extended-Ward or Lambertian material: a scenes/materials name, ward:... (lobe_rotation "
                        "in radians, or 140deg / 2.44rad), lambert:ALBEDO")
    p.add_argument("--out", required=True, help="capture plan to write (.toml)")
    p.add_argument("--leds", default="middle", help="LEDs: middle (default, the thesis's), all, a row or ids")
    p.add_argument("--rotations", default=None, help="sample rotations, degrees (default: the rig's)")
    p.add_argument("--noise", type=float, default=0.03,
                   help="target relative standard deviation of every pixel's HDR estimate from sensor noise "
                        "(default 0.03)")
    p.add_argument("--margin", type=float, default=1.1,
                   help="brightness margin: saturation judged at margin x, noise at 1/margin x the predicted "
                        "signal, so the plan holds for the material's class (default 1.1)")
    p.add_argument("--jitter", type=float, default=None,
                   help="LED frame-to-frame jitter, relative RMS, for the gain requirement (default 0.005, thesis "
                        "4.3.3; 0 leaves the requirement out)")
    p.add_argument("--gain-noise", type=float, default=None,
                   help="target of the gain error common to a frame's pixels after neighbour correction "
                        "(default 0.001; where the whole table misses half of it, twice the whole table's)")
    p.add_argument("--scale", type=float, default=0.25, help="image scale the pixels are predicted at (default 0.25)")
    p.add_argument("--capture-scale", type=float, default=1.0,
                   help="image scale the capture is made at, for neighbour correction's pixel counts (default 1, "
                        "the camera; a twin capture's --scale otherwise)")
    p.add_argument("--overhead", type=float, default=None,
                   help="seconds per shot beyond the exposure (default: the rig's [capture] figure, else the "
                        "thesis's measured 9.94 s)")
    p.add_argument("--sample", default=None, help="material label for the plan (default: the material)")
    p.add_argument("--seed", type=int, default=1,
                   help="noise seed of the twin when the plan is captured with --lights twin --camera twin "
                        "(written to the plan's [twin] table with the material and --capture-scale; default 1)")
    p.add_argument("--report", default=None, help="also write the per-LED figures as JSON here")
    add_force_option(p, "existing --out and --report files")


def plan_text(plan, rig_path: str, sample: str, leds, overhead_s: float, twin: dict | None = None) -> str:
    """The capture plan TOML of an :class:`~glossrig.core.radiometry.exposure_plan.ExposurePlan`, with
    a ``[twin]`` table (``twin``: material, scale, seed) so that the plan captured with the
    twin backends renders the material it was designed for, at the planned scale."""
    def num(x):
        return repr(float(x))

    per = plan.exposures()
    lines = [
        f"# Exposure plan for {plan.material.label} (glossrig design exposures): per LED the exposures of the",
        f"# rig's table that keep every pixel's HDR noise within {100 * plan.noise_target:g} % (sensor noise; where",
        "# the whole table misses half of that, within twice the whole table's), brightness margin "
        f"{plan.margin:g}, one sequence per LED; LED jitter {100 * plan.jitter:g} % per frame: frame-gain error "
        f"after neighbour correction within {100 * plan.gain_target:g} % (or twice the whole table's), capture "
        f"scale {plan.capture_scale:g}.",
        f"# {plan.shots_per_rotation()} shots per rotation, {plan.exposure_s_per_rotation():.1f} s of exposure, "
        f"{plan.time_s_per_rotation() / 60:.1f} min with {overhead_s:.2f} s per shot.",
        "",
        f"rig = {json.dumps(str(rig_path))}",
        f"sample = {json.dumps(sample)}",
        "rotations = [" + ", ".join(f"{r:g}" for r in plan.rotations) + "]",
        "leds = [" + ", ".join(str(i) for i in leds) + "]",
        "repeats = 1",
        "exposures_s = \"rig\"               # LEDs not listed below (none)",
        "calibration = true",
        f"overhead_s_per_shot = {overhead_s:.4f}",
        "",
        "[led_exposures_s]",
    ]
    lines += [f"{led} = [" + ", ".join(num(t) for t in per[led]) + "]" for led in leds]
    if twin:
        lines += ["", "[twin]                             # read by the twin backends (--lights twin --camera twin)"]
        lines += [f"{k} = {json.dumps(v)}" for k, v in twin.items()]
    return "\n".join(lines) + "\n"


def run(args) -> int:
    from glossrig.core.radiometry.exposure_plan import GAIN_TARGET, THESIS_JITTER, plan_exposures, white_patch_warnings
    from glossrig.core.models.materials import parse_material
    from glossrig.core.resources import packaged_reference
    from glossrig.core.rig import load_rig
    from glossrig.hardware.plan import THESIS_OVERHEAD_S, THESIS_SEQUENCE_S, format_duration, load_plan

    from .design import _floats

    out = prepare_output(args.out, args.force)
    if args.report:
        prepare_output(args.report, args.force)
    rig = load_rig(args.rig)
    material = parse_material(args.material)
    leds = rig.select_leds(args.leds)
    rots = _floats(args.rotations, "--rotations") if args.rotations else list(rig.sample_rotations)
    overhead = args.overhead
    if overhead is None:
        overhead = rig.capture.overhead_s_per_shot
        if overhead is None:
            overhead = THESIS_OVERHEAD_S
    if not (math.isfinite(overhead) and overhead >= 0):
        raise InputError(f"--overhead must be >= 0 s, got {overhead}")
    plan = plan_exposures(rig, material, leds, rots, noise_target=args.noise, margin=args.margin, scale=args.scale,
                          overhead_s=overhead, jitter=THESIS_JITTER if args.jitter is None else args.jitter,
                          gain_target=GAIN_TARGET if args.gain_noise is None else args.gain_noise,
                          capture_scale=args.capture_scale)
    # A packaged rig as scenes/NAME (the plan loader finds it from anywhere, installed or
    # not); any other rig by its absolute path.
    rig_ref = packaged_reference(rig.path) or Path(rig.path).resolve()
    twin = {"material": args.material.strip(), "scale": float(args.capture_scale), "seed": int(args.seed)}
    out.write_text(plan_text(plan, str(rig_ref), args.sample or material.label, leds, overhead, twin=twin))
    loaded = load_plan(out)            # the hardware layer must accept what it is given
    for msg in white_patch_warnings(rig, plan.exposures(), where=str(out)):
        _log.warning(msg)
    est = loaded.estimate()
    n_rot = len(rots)
    full_floor = len(leds) * 3 * sum(THESIS_SEQUENCE_S)
    full_time = len(leds) * 3 * (sum(THESIS_SEQUENCE_S) + len(THESIS_SEQUENCE_S) * overhead)
    print(f"wrote {out}: {plan.shots_per_rotation()} shots per rotation over {len(leds)} LEDs")
    for e in plan.leds:
        print(f"  LED {e.led:2d}: " + ", ".join(f"{t:g}" for t in e.exposures_s) + " s   worst noise "
              f"{100 * e.worst_noise:.2f} % on {100 * e.target_fraction:.0f} % of {e.lit_pixels} pixels"
              + (f", frame-gain error {100 * e.gain_noise_worst:.3f} % (whole table {100 * e.gain_noise_worst_full:.3f}"
                 f" %), {e.unlinked_frames} frame(s) left uncorrected" if plan.jitter > 0 else ""))
    print(f"time per rotation {format_duration(plan.time_s_per_rotation())} "
          f"(exposures {format_duration(plan.exposure_s_per_rotation())}); the whole plan ({n_rot} rotation(s), "
          f"with calibration images) {format_duration(est.estimate_s)}")
    print(f"thesis plan per rotation ({len(leds)} LEDs x 3 sequences x 18 exposures): {format_duration(full_time)} "
          f"at {overhead:.2f} s per shot, exposures alone {format_duration(full_floor)} "
          "(thesis 4.2.3 states 120 min)")
    if args.report:
        doc = plan.to_json()
        doc.update({"plan": str(out), "time_s_per_rotation": plan.time_s_per_rotation(),
                    "plan_estimate_s": est.estimate_s, "thesis_plan_s_per_rotation": full_time,
                    "thesis_floor_s_per_rotation": full_floor})
        Path(args.report).write_text(json.dumps(doc, indent=1) + "\n")
    return 0
