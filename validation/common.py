"""The studies' small library: run the ``glossrig`` command line, and the calibrated-twin
chain the studies script (simulate -> calibrate camera -> calibrate lamps -> extract ->
fit), each step a real ``glossrig`` command, so a study runs what a user runs.

* :func:`glossrig` runs one command in a child process (``python -m glossrig.cli.main``
  with this interpreter); a failure raises :class:`GlossrigFailed`, whose message names
  the verb, the exit status, the command and - where the output was captured - the
  last lines of its error output.
* :func:`simulate` / :func:`capture` / :func:`checkerboard`: twin captures with the
  studies' reuse rule (a complete capture is reused - only when it was made by the same
  command, :func:`check_reuse`; a partial one is removed and made again, or finished with
  ``--resume``, or every capture is made anew; or, for :func:`capture`, a capture of the
  first LEDs of a list is extended to the whole list, :func:`extend_leds`);
* :func:`camera` and :func:`calibrate`: the camera and lamp calibration of the nominal
  rig on the twin, resumable in a folder;
* :func:`extract` and :func:`fit`: one step each, skipped when its output exists;
* :func:`truth_camera` and :func:`truth_lamps`: the twin's true intrinsics and lamp
  positions in the pipeline's own file formats (to isolate what a study compares from
  the calibration's own error).

Every helper passes ``stdout``/``stderr``/``echo``/``cwd`` on to :func:`glossrig`.
:func:`run_main` runs a study's ``main`` as the command line does: bad input (an
InputError) is one line on stderr and exit status 2, not a traceback.
"""
from __future__ import annotations

import shlex
import shutil
import subprocess
import sys
from pathlib import Path

from glossrig.core.atomic import atomic_write_json
from glossrig.core.capture import capture_complete, check_rig_copy, load_manifest, read_truth
from glossrig.core.errors import InputError
from validation.paths import RIG

GLOSSRIG = (sys.executable, "-m", "glossrig.cli.main")
TAIL_LINES = 20           # error-output lines a failure's message repeats


class GlossrigFailed(subprocess.CalledProcessError):
    """A ``glossrig`` command exited with a non-zero status (a CalledProcessError: ``cmd``,
    ``returncode``, and ``stdout``/``stderr`` where they were captured)."""

    @property
    def verb(self) -> str:
        return self.cmd[len(GLOSSRIG)] if len(self.cmd) > len(GLOSSRIG) else ""

    @property
    def last_line(self) -> str:
        """The last non-blank line of the captured error output ('' where none was captured)."""
        lines = [x for x in (self.stderr or "").strip().splitlines() if x.strip()]
        return lines[-1] if lines else ""

    @property
    def summary(self) -> str:
        return f"glossrig {self.verb} failed (exit {self.returncode}): {self.last_line}"

    def __str__(self) -> str:
        command = f"\n  command: {shlex.join(self.cmd)}"
        if self.stderr is None:         # shown as it ran, not captured
            return f"glossrig {self.verb} failed (exit {self.returncode}){command}\n  (its error output is above)"
        text = self.stderr if self.stderr.strip() else (self.stdout or "")
        lines = text.rstrip().splitlines()[-TAIL_LINES:]
        which = "stderr" if self.stderr.strip() else "stdout"
        return (f"{self.summary}{command}\n  {which} (last {len(lines)} lines):\n"
                + "\n".join("  | " + x for x in lines))


def glossrig(*args, stdout: bool = True, stderr: bool = True, echo: str | None = None,
             cwd: str | Path | None = None) -> subprocess.CompletedProcess:
    """Run ``glossrig ARGS`` (each argument through ``str``). ``stdout``/``stderr`` False:
    that stream is captured (returned, and repeated in a failure's message) instead of
    shown. ``echo``: print ``ECHO glossrig ARGS`` first (e.g. ``"+"``). Raises
    :class:`GlossrigFailed` when the command fails."""
    argv = [str(a) for a in args]
    cmd = [*GLOSSRIG, *argv]
    if echo:
        print(f"{echo} glossrig " + " ".join(argv), flush=True)
    r = subprocess.run(cmd, cwd=cwd, text=True, errors="replace",
                       stdout=None if stdout else subprocess.PIPE, stderr=None if stderr else subprocess.PIPE)
    if r.returncode:
        raise GlossrigFailed(r.returncode, cmd, r.stdout, r.stderr)
    return r


def run_main(main, *args) -> int:
    """``main(*args)`` of a study, as the command line runs a verb (glossrig.cli.main): bad input
    (a :class:`~glossrig.core.errors.GlossrigError`, e.g. a work folder holding a capture made
    with other options) is one line on stderr, ``error: MESSAGE``, and exit status 2; a failed
    ``glossrig`` child is its :class:`GlossrigFailed` message (the verb, the command, the end of
    its error output) and the child's own exit status, not a traceback. ``main``'s own return
    value is the status otherwise (None: 0). Use: ``raise SystemExit(run_main(main))``."""
    from glossrig.core.errors import GlossrigError

    try:
        return int(main(*args) or 0)
    except GlossrigError as e:
        print(f"error: {e}", file=sys.stderr, flush=True)
        return 2
    except GlossrigFailed as e:
        print(f"error: {e}", file=sys.stderr, flush=True)
        return int(e.returncode) or 1


# ------------------------------------------------------------------ twin captures

def needs_capture(out: Path) -> bool:
    """False when OUT holds a complete capture; else True, after removing what OUT holds."""
    if capture_complete(out):
        return False
    if out.exists():
        shutil.rmtree(out)
    return True


def simulate(out: Path, *args, rig: Path = RIG, extra=(), mode: str = "reuse", **run) -> Path:
    """``glossrig simulate --rig RIG ARGS --no-progress --out OUT EXTRA``. ``mode``:
    ``reuse`` (a complete capture in OUT is kept, a partial one removed and made again),
    ``resume`` (kept; a partial one finished with ``--resume``) or ``fresh`` (always made
    anew). With ``echo`` a reused capture is said."""
    out = Path(out)
    if mode not in ("reuse", "resume", "fresh"):
        raise ValueError(f"mode {mode!r}: reuse, resume or fresh")
    resume = []
    if mode == "fresh":
        if out.exists():
            shutil.rmtree(out)
    elif capture_complete(out):
        check_reuse(out, *args, rig=rig, extra=extra)
        if run.get("echo"):
            print(f"reusing the complete capture {out}", flush=True)
        return out
    elif mode == "resume":
        resume = ["--resume"] if out.exists() and any(out.iterdir()) else []
    elif out.exists():          # reuse: a partial capture is made again
        shutil.rmtree(out)
    glossrig("simulate", "--rig", rig, *args, "--no-progress", "--out", out, *extra, *resume, **run)
    return out


def check_reuse(out: Path, *args, rig: Path = RIG, extra=()) -> None:
    """A complete capture in OUT may stand for ``glossrig simulate --rig RIG ARGS EXTRA`` only
    when that command made it: the simulate options its manifest records equal the command's
    (:func:`simulate_options`: the material's file content by its sha256, the LEDs, rotations,
    scale, seed, effects, ...) and its copy of the rig description (``rig.toml``) is the rig
    file's bytes. Otherwise an InputError names OUT and every difference, and nothing is
    removed: a study run again into one WORK with other arguments stops instead of measuring
    the old capture as if it were the new one.

    An option the capture does not record (``material_sha256``, recorded since 2026-12-04)
    cannot be compared: the capture is reused with a warning on stderr naming the option, so
    work folders made before stay usable and say what was not checked."""
    from glossrig.twin.simulate import OPTIONS_KEY, describe_differences, differing_options

    out = Path(out)
    options = simulate_options(*args, rig=rig, extra=extra)
    recorded = load_manifest(out).meta.get(OPTIONS_KEY)
    where = out / "capture.json"
    if not isinstance(recorded, dict):
        raise InputError("the complete capture here was not made by glossrig simulate (its manifest records no "
                         "simulate options), so it cannot stand for the study's capture; remove it or choose "
                         "another work folder (nothing was changed)", path=where)
    diff = differing_options(recorded, options)
    unrecorded = [k for k in diff if k not in recorded]
    refused = [k for k in diff if k in recorded]
    if refused:
        raise InputError(f"the complete capture here was made with other options "
                         f"({describe_differences(recorded, options, refused)}); remove it or choose another work "
                         "folder (nothing was changed)", path=where)
    from glossrig.core.rig import load_rig

    check_rig_copy(out, Path(load_rig(rig).path).read_bytes(), where=where,
                   then=f"it was made with another rig description than {rig}: remove it or choose another work "
                        "folder (nothing was changed)")
    if unrecorded:
        print(f"warning: {where}: reused without checking {describe_differences(recorded, options, unrecorded)}",
              file=sys.stderr, flush=True)


def extend_leds(out: Path, leds: list[int], *, options: dict | None = None) -> bool:
    """Turn the twin capture in OUT, made by ``glossrig simulate`` with LEDs that are the
    first ones of LEDS and otherwise the same options, into an unfinished capture of all
    of LEDS that ``glossrig simulate --resume`` completes: the images already made are
    kept, only the added LEDs' sequences are simulated. Returns whether the manifest was
    changed (False: OUT holds no simulated capture, or one of LEDS already).

    This gives the capture a fresh simulation of LEDS would give, byte for byte: a twin
    image draws its noise and LED fluctuations from its own random stream, keyed by what
    the image is (``glossrig.twin.sensor.image_rng``), at its time on the plan's
    schedule, and the plan takes the calibration image and then the LEDs in their given
    order (``CapturePlan.shots``), so the first LEDs' images stand at the same times in
    both plans. The manifest gets the options and plan record (its sha256,
    ``glossrig.twin.simulate.plan_sha256``; LED list; number of planned images) the longer
    simulation writes; its recorded images are checked against their sha256 by the resume.

    ``options``: the simulate options of the command that is to complete the capture
    (``glossrig.twin.simulate.sample_options``, :func:`simulate_options`); they must be the
    capture's with LEDS as its LEDs, or the resume would refuse them. Everything is checked
    before the manifest is written (atomically, last): a refused call (InputError: other
    options; LEDs that do not begin with the capture's own, in another order or fewer; a
    plan this cannot extend) leaves the capture as it was."""
    from glossrig.twin.simulate import OPTIONS_KEY, describe_differences, differing_options, plan_sha256

    out = Path(out)
    if not (out / "capture.json").is_file():
        return False
    m = load_manifest(out)
    where = out / "capture.json"
    opts, plan = m.meta.get(OPTIONS_KEY), m.meta.get("plan")
    if not opts or not plan:
        return False
    old = [int(x) for x in opts["leds"]]
    leds = [int(x) for x in leds]
    new = {**opts, "leds": leds}
    if options is not None:
        diff = differing_options(new, options)
        if diff:
            what = describe_differences(new, options, diff, recorded_as="extended capture", given_as="command")
            raise InputError(f"cannot extend the capture to LEDs {leds}: the simulate command that would complete "
                             f"it has other options ({what}); nothing was changed", path=where)
    if leds == old:
        return False
    if leds[:len(old)] != old:
        raise InputError(f"cannot extend the capture of LEDs {old} to LEDs {leds}: its LEDs must be the first "
                         "ones of the new list, in the same order (their images' times on the schedule)", path=where)
    if plan.get("led_exposures_s") or plan.get("checkerboard_views"):
        raise InputError("cannot extend a capture with per-LED exposures or checkerboard views", path=where)
    if plan_sha256(opts) != plan.get("sha256"):
        raise InputError("the manifest's plan sha256 is not that of its simulate options (made by another version "
                         "of glossrig simulate?); simulate the capture anew", path=where)
    per_led = len(plan["exposures_s"]) * int(plan["repeats"]) * len(plan["rotations"])
    m.meta[OPTIONS_KEY] = new
    m.meta["plan"] = {**plan, "sha256": plan_sha256(new), "leds": leds,
                      "planned_images": int(plan["planned_images"]) + per_led * (len(leds) - len(old))}
    m.meta.pop("finished", None)
    m.complete = False
    m.save()
    return True


def simulate_options(*args, rig: Path = RIG, extra=()) -> dict:
    """The options ``glossrig simulate --rig RIG ARGS EXTRA`` records in its capture's manifest
    (``glossrig.twin.simulate.sample_options`` or, with ``--target checkerboard``,
    ``checkerboard_options``), its command line read by the verb's own parser; a bad argument
    is an InputError."""
    import argparse

    from glossrig.cli.verbs.simulate import add_arguments, parse_rotations, spp_of
    from glossrig.core.rig import load_rig
    from glossrig.twin.simulate import checkerboard_options, sample_options, twin_effects

    class Parser(argparse.ArgumentParser):
        def error(self, message):
            raise InputError(f"glossrig simulate {' '.join(argv)}: {message}")

    argv = [str(a) for a in ("--rig", rig, *args, "--out", "-", *extra)]
    p = Parser(prog="glossrig simulate")
    add_arguments(p)
    a = p.parse_args(argv)
    if a.target == "checkerboard":
        return checkerboard_options(load_rig(a.rig), a.scale, a.seed, a.views, spp_of(a))
    rig_ = load_rig(a.rig)
    return sample_options(rig_, a.material, a.leds, parse_rotations(a.rotations), a.repeats, a.scale, a.seed,
                          twin_effects(rig_, a.effects, a.ideal), spp_of(a))


def capture_argv(material: str, scale: float, seed: int, rotations: str = "0", repeats: int = 1,
                 leds: str = "middle") -> tuple:
    """The ``glossrig simulate`` arguments of :func:`capture` (but ``--rig``, ``--out`` and EXTRA)."""
    return ("--material", material, "--leds", leds, f"--rotations={rotations}", "--repeats", repeats,
            "--scale", scale, "--seed", seed)


def check_capture(out: Path, material: str, scale: float, seed: int, rotations: str = "0", repeats: int = 1, *,
                  leds: str = "middle", extra=(), rig: Path = RIG) -> None:
    """:func:`check_reuse` of the complete capture in OUT for the one :func:`capture` makes with
    these arguments (a study that reuses a capture it kept itself, outside :func:`capture`)."""
    check_reuse(out, *capture_argv(material, scale, seed, rotations, repeats, leds), rig=rig, extra=extra)


def capture(out: Path, material: str, scale: float, seed: int, rotations: str = "0", repeats: int = 1, *,
            leds: str = "middle", extra=(), rig: Path = RIG, mode: str = "reuse", **run) -> Path:
    """A capture of MATERIAL: :func:`simulate` with ``--material --leds --rotations
    --repeats --scale --seed``. ``mode`` as :func:`simulate`'s, or ``extend``: a capture
    in OUT of the first of LEDS (all other options equal: checked, with the LEDs, before
    anything is changed) is extended to LEDS (:func:`extend_leds`) and completed;
    otherwise as ``resume``."""
    args = capture_argv(material, scale, seed, rotations, repeats, leds)
    if mode == "extend":
        options = simulate_options(*args, rig=rig, extra=extra)
        extend_leds(Path(out), options["leds"], options=options)
        mode = "resume"
    return simulate(out, *args, rig=rig, extra=extra, mode=mode, **run)


def checkerboard(out: Path, views: int, scale: float, seed: int, *, rig: Path = RIG, **run) -> Path:
    """Checkerboard views for the camera calibration: :func:`simulate` ``--target checkerboard``."""
    return simulate(out, "--target", "checkerboard", "--views", views, "--scale", scale, "--seed", seed, rig=rig,
                    **run)


# ------------------------------------------------------------------ the calibrated twin

def camera(out: Path, checker: Path, views: int, scale: float, seed: int, *, rig: Path = RIG, **run) -> Path:
    """VIEWS checkerboard views in CHECKER (seed) -> ``glossrig calibrate camera`` -> OUT;
    an OUT that exists is kept."""
    if not out.exists():
        checkerboard(checker, views, scale, seed, rig=rig, **run)
        glossrig("calibrate", "camera", checker, "--out", out, **run)
    return out


def calibrate(out: Path, scale: float, seed: int, lamp_rotations: str = "0", repeats: int = 1,
              leds: str = "middle", extra=()) -> tuple[Path, Path]:
    """Camera and lamp calibration of the nominal rig on the twin, resumable in OUT: 12
    checkerboard views (seed) -> `glossrig calibrate camera` -> OUT/camera.json; a
    transparency-sheet capture of LEDS (seed + 1; EXTRA passed to its simulate) ->
    `glossrig calibrate lamps` (thesis 4.3.4) -> OUT/lamps.json. A camera.json or
    lamps.json already in OUT is kept."""
    cam = camera(out / "camera.json", out / "checker", 12, scale, seed)
    lamps = out / "lamps.json"
    if not lamps.exists():
        spec = capture(out / "specular", "transparency_sheet", scale, seed + 1, lamp_rotations, repeats, leds=leds,
                       extra=extra)
        glossrig("calibrate", "lamps", spec, "--camera", cam, "--out", lamps)
    return cam, lamps


def extract(capture_dir: Path, reference: Path, camera_json: Path, lamps_json: Path, out: Path, *extra,
            **run) -> Path:
    """``glossrig extract`` of a capture against a reference into OUT (Parquet); an OUT
    that exists is kept."""
    if not Path(out).exists():
        glossrig("extract", capture_dir, "--reference", reference, "--camera", camera_json, "--lamps", lamps_json,
                 "--out", out, "--no-progress", *extra, **run)
    return out


def fit(samples: Path, out: Path, *extra, **run) -> Path:
    """``glossrig fit SAMPLES --out OUT EXTRA``; an OUT that exists is kept."""
    if not Path(out).exists():
        glossrig("fit", samples, "--out", out, *extra, **run)
    return out


def truth_camera(capture_dir: Path, out: Path) -> Path:
    """The twin's true intrinsics (the capture's truth.json) as a camera.json at OUT (replaced)."""
    import numpy as np

    from glossrig.core.calibration.intrinsics import CameraCalibration, save_camera

    t = read_truth(capture_dir)
    K = np.array(t["camera_matrix"])
    cal = CameraCalibration(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], distortion=tuple(t["distortion"]),
                            image_size=tuple(t["image_size"]), rms_px=0.0)
    return save_camera(cal, {"source": "twin truth.json"}, out, overwrite=True)


def truth_lamps(capture_dir: Path, out: Path) -> Path:
    """The twin's true lamp positions (the capture's truth.json) as a lamps.json at OUT (replaced)."""
    t = read_truth(capture_dir)
    out = Path(out)
    atomic_write_json(out, {"kind": "glossrig.lamps", "lamps_mm": t["led_positions_mm"], "source": "twin truth.json"})
    return out
