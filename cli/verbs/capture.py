# ``glossrig capture``: run a capture plan (thesis 4.2.3); the help text below is the module docstring.
from __future__ import annotations

import argparse
import logging
from pathlib import Path

from glossrig.cli.logs import LogStream
from glossrig.cli.outputs import prepare_output
from glossrig.hardware.plan import PLAN_FORMAT

_log = logging.getLogger(__name__)

HELP = "run a capture plan on the twin or the real rig (LEDs, camera); resumable, LEDs always end off"

__doc__ = f"""\
Run a capture plan (thesis 4.2.3): per sample rotation the calibration image with all
LEDs on, then for each LED the LDR exposure sequences, on any combination of devices.
Writes the capture folder DIR (capture.json + raw files + a copy of the rig file):
every raw file is written under a temporary name, renamed once complete, and its
sha256 recorded in the manifest at once.

The plan file (TOML):

{PLAN_FORMAT}
Devices:
  --lights twin          the twin's LEDs (with --camera twin)
  --lights gpio          16-channel active-low relay module on Raspberry Pi GPIO (pins
                         from the rig file's leds.table gpio)
  --lights serial-relay  USB/serial relay board, Numato Lab ASCII protocol
                         ("relay writeall"/"relay readall"), on --relay-port
  --camera twin          the twin's camera (it also rotates the virtual sample)
  --camera gphoto2       a tethered camera through python-gphoto2
                         (pip install 'glossrig[camera]')
  --lights fake / --camera fake
                         TEST ONLY: the real GPIO / gphoto2 drivers on simulated
                         devices (faults: GLOSSRIG_FAKE_LIGHTS, GLOSSRIG_FAKE_CAMERA)

Resume: after a crash, a power cut, a camera that dropped off USB or Ctrl-C, rerun the
same command with --resume: recorded files are checked against their checksums,
damaged ones moved to DIR/set_aside/, and only what is missing is retaken; no good file
is ever overwritten; there is no --force, a capture is never replaced (remove it
yourself or choose another DIR). With a real camera the operator is asked to rotate the sample
(--sample-ready: it is already at the first rotation still needed).

--dry-run prints the plan, the sum of its exposure times (the physical floor) and the
estimate with the measured per-shot overhead (thesis 4.2.3: ~4 min per 18-exposure
sequence), and with an existing DIR what is left to take; no device is touched.

Exit status: 0 complete, 2 error (the message says what is safe and how to resume),
130 interrupted.
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--plan", required=True, type=Path, metavar="PLAN.toml", help="capture plan (format above)")
    p.add_argument("--lights", required=True, choices=("twin", "gpio", "serial-relay", "fake"),
                   help="LED backend (fake: test only)")
    p.add_argument("--camera", required=True, choices=("twin", "gphoto2", "fake"),
                   help="camera backend (fake: test only)")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="capture folder to write")
    p.add_argument("--resume", action="store_true", help="complete an interrupted capture in DIR")
    p.add_argument("--dry-run", action="store_true", help="print the plan and its time; touch no device")
    p.add_argument("--relay-port", metavar="PORT", help="serial port of the relay board (--lights serial-relay)")
    p.add_argument("--relay-channels", type=int, default=16, choices=(8, 16, 32, 64),
                   help="channels of the serial relay board (default 16)")
    p.add_argument("--sample-ready", action="store_true",
                   help="the sample is already mounted at the first rotation needed: do not ask")
    p.add_argument("--min-free-mb", type=float, default=256.0,
                   help="stop before a shot if less disk space is free (default 256 MiB)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _dry_run(args) -> int:
    from glossrig.core.capture import MANIFEST, load_manifest
    from glossrig.hardware.plan import describe, load_plan

    plan = load_plan(args.plan)
    remaining = None
    if (args.out / MANIFEST).is_file():
        m = load_manifest(args.out)
        done = {im.key() for im in m.images}
        remaining = [s for s in plan.shots() if s.key not in done]
    print(describe(plan, remaining))
    if remaining is not None:
        print("          (checksums of the recorded files are verified when --resume runs)")
    return 0


def run(args) -> int:
    if args.dry_run:
        return _dry_run(args)
    from glossrig.hardware.backends import make_backends
    from glossrig.hardware.orchestrator import run_capture
    from glossrig.hardware.plan import format_duration, load_plan

    # Before any device is opened: an existing capture needs --resume, and DIR must be writable.
    from glossrig.core.capture import MANIFEST
    from glossrig.core.errors import InputError

    has_capture = (args.out / MANIFEST).is_file()
    if has_capture and not args.resume:
        raise InputError("already holds a capture; rerun with --resume to complete it, or choose another "
                         "--out (nothing was changed)", path=args.out)
    prepare_output(args.out, kind="folder", resume=has_capture,
                   hint="holds no capture manifest (capture.json); choose another --out (nothing was changed)")
    plan = load_plan(args.plan)
    est = plan.estimate()
    _log.info(f"capture of {plan.sample!r}: {est.shots} images planned, about {format_duration(est.estimate_s)} "
              f"(exposures alone {format_duration(est.exposure_s)})")
    dev = make_backends(plan, args.lights, args.camera, relay_port=args.relay_port,
                        relay_channels=args.relay_channels, sample_ready=args.sample_ready)
    try:
        report = run_capture(plan, args.out, lights=dev.lights, camera=dev.camera, operator=dev.operator,
                             backends=dev.names, resume=args.resume, show_progress=not args.no_progress,
                             min_free_bytes=int(args.min_free_mb * 2 ** 20), log=LogStream(_log))
    finally:
        try:
            dev.close()
        except Exception as e:   # noqa: BLE001 - never hide the capture's own outcome
            _log.warning(f"closing the devices failed: {e}")
    taken = f"{report.taken} taken" + (f", {report.kept} kept from before" if args.resume else "")
    aside = f"; {len(report.set_aside)} file(s) moved to {args.out / 'set_aside'}" if report.set_aside else ""
    print(f"capture complete: {report.planned} images in {args.out} ({taken}{aside})")
    return 0
