"""The main job: simulate captures on the virtual rig, measure them with ``glossrig
measure``, and report how well the ground truth was recovered.

Steps:
  1. checkerboard views on the twin                 (glossrig simulate --target checkerboard)
  2. a transparency-sheet capture                   (glossrig simulate, thesis 4.3.4)
  3. a lambert:0.8 reference capture and a capture of MATERIAL (middle-row LEDs, the 18
     exposures of Table 4.1, the rig's LED fluctuations and sensor noise, real DNGs)
  4. glossrig measure on them, in OUT itself: calibrate camera and lamps, extract
     (thesis 4.3-4.4), fit (thesis 4.5), exports, renders of the fitted material, the
     recovery table (OUT/recovery.json: the calibrations and the fit against the truth
     the twin recorded) and the report (OUT/report.html, OUT/report.md)
  5. the recovery table printed.

Rerunning with the same --out: each simulation step records in OUT/.steps/STEP.json what
it was run with (its full argv, the sha256 of its input files and the glossrig version)
and the sha256 of what it wrote, and glossrig measure keeps its own step records there
(see glossrig measure --help; the one mechanism is glossrig.cli.steps). With --resume a
finished step is reused only when all of that matches (an output edited since is
redone), so another --material re-simulates the sample and redoes extract, fit, exports,
renders and report but keeps the checkerboard, camera, specular, lamps and reference
steps, and another --scale redoes everything. A simulation that was interrupted with the
same inputs is continued with simulate's own --resume; otherwise whatever it left is
removed and it is redone. --force starts over (every step redone). With neither option
an existing non-empty --out is refused, naming both.
"""
from __future__ import annotations

import argparse
import logging

from glossrig.cli.outputs import add_force_option, prepare_output

_log = logging.getLogger(__name__)

HELP = "simulate captures on the virtual rig, measure them (glossrig measure); report ground-truth recovery"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="demo_out", help="working folder for the demo's captures and results")
    p.add_argument("--material", default="sample_2_6", help="the sample (see glossrig simulate --help)")
    p.add_argument("--scale", type=float, default=0.25)
    p.add_argument("--rotations", default="0")
    p.add_argument("--seed", type=int, default=1)
    add_force_option(p, "every earlier result in --out: redo all steps instead of reusing the finished ones")
    p.add_argument("--resume", action="store_true",
                   help="continue the demo in --out: reuse the finished steps whose recorded inputs match, "
                        "complete an interrupted one, redo the rest")


def _accepts_resume(words: list[str]) -> bool:
    """True when ``glossrig WORDS...`` has a --resume option."""
    from glossrig.cli.main import build_parser

    p = build_parser()
    for w in words:
        sub = next((a for a in p._actions if isinstance(a, argparse._SubParsersAction)), None)
        if sub is None or w not in sub.choices:
            return False
        p = sub.choices[w]
    return "--resume" in p._option_string_actions


def _dispatch(argv: list[str]) -> int:
    """Run one step as ``glossrig ARGV`` (a seam the tests replace)."""
    from glossrig.cli.main import main

    return main(argv)


def _material_file(spec: str):
    """The file a --material spec reads, when it reads one (its content is a step input)."""
    from pathlib import Path

    from glossrig.core.models.materials import MATERIALS_DIR

    if spec.startswith("measured:"):
        p = Path(spec[len("measured:"):])
        return p if p.is_file() else None
    if ":" in spec:
        return None
    p = MATERIALS_DIR / f"{spec}.toml"
    return p if p.is_file() else None


def _sim_step(steps, out, rig, name: str, argv: list, files: dict, chatter: list) -> None:
    """``glossrig simulate ARGV`` as step ``name`` writing the capture ``OUT/name``."""
    from pathlib import Path

    from glossrig.core.errors import GlossrigError

    def shown(a) -> str:
        """An argument as recorded: paths inside --out relative to it, the rig by name (its content is hashed)."""
        if isinstance(a, Path):
            if a == rig:
                return "RIG"
            try:
                return "OUT/" + a.relative_to(out).as_posix()
            except ValueError:
                return str(a)
        return str(a)

    line = " ".join(shown(a) for a in argv)

    def compute(resume: bool) -> None:
        flag = "--resume" if resume else "--force"
        _log.info(f"glossrig {line} {flag}")
        rc = _dispatch([str(a) for a in [*argv, flag, *chatter]])
        if rc == 130:               # the step was interrupted (Ctrl-C): so is the demo; --resume continues
            raise KeyboardInterrupt
        if rc != 0:
            raise GlossrigError(f"demo step failed: glossrig {line}")

    words = [a for a in argv[:2] if not str(a).startswith("-") and not isinstance(a, Path)]
    steps.run(name, out / name, compute, files=files, options={"argv": [shown(a) for a in argv]},
              resumable=_accepts_resume(words))


def run(args) -> int:
    from glossrig.cli.steps import StepRunner
    from glossrig.core.errors import GlossrigError, InputError
    from glossrig.core.report.recovery import format_recovery, read_recovery
    from glossrig.core.rig import default_rig_path

    if args.force and args.resume:
        raise InputError("--resume continues the demo in --out, --force starts it over: give one of them")
    out = prepare_output(args.out, args.force, kind="folder", resume=args.resume,
                         hint="use --resume to continue it (finished steps whose inputs match are reused) "
                              "or --force to start over")
    out.mkdir(parents=True, exist_ok=True)
    rig = default_rig_path()
    chatter = ["-q"] if args.quiet else ["-v"] if args.verbose else []
    steps = StepRunner(out, resume=args.resume, total=5, log=_log)

    def capture(name, material, seed):
        _sim_step(steps, out, rig, name,
                  ["simulate", "--rig", rig, "--material", material, "--leds", "middle",
                   f"--rotations={args.rotations}", "--repeats", 1, "--scale", args.scale, "--seed", seed,
                   "--out", out / name], {"rig": rig, "material": _material_file(material)}, chatter)
        return out / name

    _sim_step(steps, out, rig, "checker", ["simulate", "--rig", rig, "--target", "checkerboard", "--views", 12,
                                           "--scale", args.scale, "--seed", args.seed, "--out", out / "checker"],
              {"rig": rig}, chatter)
    spec = capture("specular", "transparency_sheet", args.seed + 1)
    ref = capture("reference", "lambert:0.8", args.seed + 2)
    sample = capture("sample", args.material, args.seed + 3)
    # glossrig measure keeps its own step records in OUT/.steps: --resume reuses what still matches
    _log.info("step 5/5 measure: glossrig measure OUT/sample --reference OUT/reference --checkerboard OUT/checker "
              "--specular OUT/specular --out OUT")
    rc = _dispatch([str(a) for a in ["measure", sample, "--reference", ref, "--checkerboard", out / "checker",
                                     "--specular", spec, "--out", out, "--force" if args.force else "--resume",
                                     *chatter]])
    if rc == 130:
        raise KeyboardInterrupt
    if rc != 0:
        raise GlossrigError("demo step failed: glossrig measure")

    rec = out / "recovery.json"
    if not rec.is_file():
        raise GlossrigError(f"glossrig measure wrote no recovery table ({rec}): is {sample} a twin capture?")
    for line in format_recovery(read_recovery(rec)):
        print(line)
    print(f"  results in {out}: report.html, report.md, recovery.json, fit.json, samples.parquet, exports/, plots/")
    return 0
