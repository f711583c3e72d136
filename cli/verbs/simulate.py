"""Simulate a capture on the virtual rig (Mitsuba twin) and write it as DNG files.

Writes OUT/capture.json (the manifest the pipeline reads), one DNG per image,
OUT/rig.toml (the rig it was made with) and OUT/truth.json (what was simulated;
the pipeline never reads it) - the same folder, with the same file names, as
`glossrig capture --lights twin --camera twin` writes.

An interrupted run (Ctrl-C, a crash) leaves capture.json with "complete": false;
rerun the same command with --resume to finish it: recorded images are checked
against their sha256, missing or damaged ones are re-made, and the capture ends
byte-identical to one made without interruption (every image has its own random
stream and its own time on the capture's schedule). A resume with other options
is refused - the material's file counts by its content (its sha256 is recorded),
so an edited .bsdf or .xml at the same path is another material.

MATERIAL is one of
  ward:rho_d=..,rho_s=..,alpha_x=..,alpha_y=..,lobe_rotation=..   (extended Ward, thesis eq. 4.79;
                       lobe_rotation in radians, or with a unit: 140deg, 2.44rad; rho_d in [0, 1],
                       rho_s >= 0, rho_d + rho_s <= 1, alpha in (0, 0.5] as in thesis Table 4.2)
  lambert:ALBEDO
  measured:PATH        an RGL .bsdf file, e.g. ../shared/data/rgl/paper_white_rgb.bsdf
  mitsuba:FILE.xml     any stock Mitsuba 3 BSDF, one <bsdf type="..."> element, e.g. an anisotropic
                       roughconductor (alpha_u around the cylinder at rotation 0, alpha_v along its
                       axis; the sample rotation turns it): scenes/materials/aniso_roughconductor_ggx.xml,
                       aniso_roughconductor_beckmann.xml, aniso_principled.xml, roughplastic_beckmann.xml
                       (a bare name finds these); truth.json records the XML text and its sha256
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
import logging
from pathlib import Path

from glossrig.cli.outputs import add_force_option, prepare_output

log = logging.getLogger(__name__)

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
    p.add_argument("--target", choices=["sample", "checkerboard"], default="sample",
                   help="what is photographed: the sample under its LEDs, or checkerboard views for calibrate camera")
    p.add_argument("--views", type=int, default=12, help="checkerboard views (with --target checkerboard)")
    p.add_argument("--spp", type=int, default=None,
                   help="samples per pixel of each render (anti-aliasing; default: the twin's DEFAULT_SPP, "
                        "glossrig.twin.render)")
    p.add_argument("--keep-exr", action="store_true", help="also write each LED's linear render as OpenEXR")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--out", required=True, help="capture folder to create (must not exist or be empty)")
    p.add_argument("--resume", action="store_true",
                   help="complete an interrupted capture in --out, made with the same options: recorded images "
                        "are checked against their sha256, missing or damaged ones re-made; the result is "
                        "byte-identical to an uninterrupted run")
    add_force_option(p, "a capture this command made earlier in --out: its images, capture.json, truth.json "
                        "and linear/*.exr are removed first; a folder holding anything else is still refused")


def parse_rotations(text: str) -> list[float]:
    """``--rotations``: the comma-separated sample rotations (degrees), at least one."""
    from glossrig.core.errors import InputError

    try:
        rotations = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise InputError(f"--rotations: expected comma-separated degrees, got {text!r}") from None
    if not rotations:
        raise InputError("--rotations: empty")
    return rotations


def spp_of(args) -> int:
    """``--spp``, or the twin's :data:`glossrig.twin.render.DEFAULT_SPP` where it is not given (the
    parser is built without importing the twin)."""
    from glossrig.twin.render import DEFAULT_SPP

    return DEFAULT_SPP if args.spp is None else int(args.spp)


def run(args) -> int:
    from glossrig.core.errors import InputError
    from glossrig.twin.simulate import simulate

    rotations = parse_rotations(args.rotations)
    resume = getattr(args, "resume", False)
    if resume and args.force:
        raise InputError("--resume completes the capture in --out, --force replaces it: give one of them")
    prepare_output(args.out, args.force, kind="folder", resume=resume)
    if args.force and not resume:
        # the cheap inputs first: a typo must not cost the earlier capture
        from glossrig.core.rig import load_rig
        from glossrig.twin.simulate import parse_twin_material

        rig = load_rig(args.rig)
        parse_twin_material(args.material)
        if args.target == "sample":
            rig.select_leds(args.leds)
        if args.repeats < 1 or not (0.01 <= args.scale <= 1.0):
            raise InputError(f"--repeats must be >= 1 and --scale in [0.01, 1], got {args.repeats} and {args.scale}")
        _clear_own_capture(Path(args.out))
    out = simulate(args.rig, args.material, args.leds, rotations, args.repeats, args.scale, args.seed,
                   args.effects, args.out, target=args.target, ideal=args.ideal, spp=spp_of(args),
                   keep_exr=args.keep_exr, views=args.views, progress=not args.no_progress, resume=resume)
    print(f"capture written to {out}")
    return 0


def _clear_own_capture(out: Path) -> None:
    """For ``--force``: empty ``out`` if it holds only a capture ``glossrig simulate`` made.

    Removes the images its manifest lists, capture.json, truth.json, linear/*.exr and
    unfinished ``.*.part`` files; refuses (removing nothing) when the folder holds
    anything else or a manifest from another source (a real capture is never deleted).
    """
    from glossrig.core.capture import MANIFEST, TRUTH, load_manifest
    from glossrig.core.errors import InputError

    if not out.is_dir() or not any(out.iterdir()):
        return
    try:
        man = load_manifest(out)
    except InputError:
        man = None
    if man is None or man.meta.get("source") != "glossrig twin":
        raise InputError("is not empty and holds no capture made by glossrig simulate; --force only replaces "
                         "simulate's own captures (remove the folder yourself or choose another --out)", path=out)
    own = {MANIFEST, TRUTH, "rig.toml"} | {im.file for im in man.images}
    doomed, foreign = [], []
    for p in sorted(out.iterdir()):
        if p.is_file() and (p.name in own or (p.name.startswith(".") and p.name.endswith(".part"))):
            doomed.append(p)
        elif p.is_dir() and p.name == "linear" and all(q.is_file() and q.suffix == ".exr" for q in p.iterdir()):
            doomed += sorted(p.iterdir())
            doomed.append(p)
        else:
            foreign.append(p.name)
    if foreign:
        raise InputError(f"holds files glossrig simulate did not write ({', '.join(foreign[:5])}); nothing removed, "
                         "remove them yourself or choose another --out", path=out)
    for p in doomed:
        p.rmdir() if p.is_dir() else p.unlink()
    log.info(f"--force: removed the earlier capture in {out} ({len(doomed)} entries)")
