"""Simulate a capture on the virtual rig (Mitsuba twin) and write it as DNG files.

Writes OUT/capture.json (the manifest the pipeline reads), one DNG per image,
and OUT/truth.json (what was simulated; the pipeline never reads it).

MATERIAL is one of
  ward:rho_d=..,rho_s=..,alpha_x=..,alpha_y=..,lobe_rotation=..   (extended Ward, thesis eq. 4.79)
  lambert:ALBEDO
  measured:PATH        an RGL .bsdf file, e.g. ../shared/data/rgl/paper_white_rgb.bsdf
  NAME                 a file of scenes/materials (e.g. transparency_sheet, sample_2_6)
LEDS is 'middle', 'all', a row name or comma-separated LED ids (1-16).
EFFECTS is name=value,... from the twin's catalogue (see below). Unless --ideal,
the rig's own LED fluctuations (led_jitter=0.005, led_drift=0.01) are on.

Example (thesis capture at quarter resolution, one repeat):
  glossrig simulate --rig scenes/thesis_rig.toml --material sample_2_6 --leds middle \\
      --rotations 0 --repeats 1 --scale 0.25 --seed 1 --out cap_sample
"""
from __future__ import annotations

import argparse

HELP = "simulate a capture on the virtual rig (Mitsuba twin)"


def _effects_epilog() -> str:
    from glossrig.twin.effects import CATALOGUE

    lines = ["effects (name: unit, typical value):"]
    for e in CATALOGUE.values():
        lines.append(f"  {e.name}: {e.unit}, e.g. {e.typical:g}. {e.doc}")
    return "\n".join(lines)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.epilog = _effects_epilog()
    p.add_argument("--rig", default="scenes/thesis_rig.toml", help="rig description (TOML)")
    p.add_argument("--material", default="sample_2_6", help="sample material (see above)")
    p.add_argument("--leds", default="middle", help="LEDs to take sequences with")
    p.add_argument("--rotations", default="0", help="comma-separated sample rotations in degrees")
    p.add_argument("--repeats", type=int, default=1, help="exposure sequences per LED (thesis: 3)")
    p.add_argument("--scale", type=float, default=0.25, help="resolution against the 6032x4032 sensor")
    p.add_argument("--seed", type=int, default=0, help="seed of every random draw")
    p.add_argument("--effects", default=None, help="non-idealities, name=value,...")
    p.add_argument("--ideal", action="store_true", help="switch off the rig's baseline LED fluctuations")
    p.add_argument("--target", choices=["sample", "checkerboard"], default="sample")
    p.add_argument("--views", type=int, default=12, help="checkerboard views (with --target checkerboard)")
    p.add_argument("--spp", type=int, default=4, help="samples per pixel of each render (anti-aliasing)")
    p.add_argument("--keep-exr", action="store_true", help="also write each LED's linear render as OpenEXR")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--out", required=True, help="capture folder to create (must not exist or be empty)")


def run(args) -> int:
    from glossrig.core.errors import InputError
    from glossrig.twin.simulate import simulate

    try:
        rotations = [float(x) for x in args.rotations.split(",") if x.strip()]
    except ValueError:
        raise InputError(f"--rotations: expected comma-separated degrees, got {args.rotations!r}") from None
    if not rotations:
        raise InputError("--rotations: empty")
    out = simulate(args.rig, args.material, args.leds, rotations, args.repeats, args.scale, args.seed,
                   args.effects, args.out, target=args.target, ideal=args.ideal, spp=args.spp,
                   keep_exr=args.keep_exr, views=args.views, progress=not args.no_progress)
    print(f"capture written to {out}")
    return 0
