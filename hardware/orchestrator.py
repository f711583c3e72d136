"""Capture orchestration: run a plan against any lights / camera / operator, writing the
capture folder of design.md as it goes, resumable after anything.

Thesis 4.2.3 is the procedure (calibration image with all LEDs, then per LED the LDR
sequences of table 4.1); :mod:`glossrig.hardware.plan` turns a plan file into the
list of shots. What this module adds is what an overnight run needs and the
thesis's script did not have (it overwrote one temporary file per shot and could not
resume):

* **Every raw file is durable before it is recorded.** The camera writes to a
  temporary name in the capture folder (``.NAME.part``); the file is fsynced, its
  sha256 computed, then it is published under its final name by a hard link (or a
  rename after an existence check on file systems without links;
  :func:`glossrig.core.atomic.publish`), which never replaces an existing file; the
  folder is fsynced and only then the manifest (``capture.json``, written atomically
  by :mod:`glossrig.core.atomic`) gains the
  entry with that checksum. A crash at any point leaves either a stale ``.part``
  (deleted on resume), a published file not yet in the manifest (set aside on
  resume, then retaken) or a recorded, checksummed file.
* **Resume** (``resume=True``) verifies every recorded file against its checksum,
  moves damaged ones to ``set_aside/`` (never deleting what was captured), and
  retakes only what is missing. It refuses to continue a capture with another plan,
  another rig file, another sample or other backends.
* **The LEDs always end off**: on success, on any error, on Ctrl-C, SIGTERM or SIGHUP
  (a closed ssh session). After a SIGKILL or a power cut nothing can run, so every
  run starts by switching all LEDs off.
* Before each shot the free space is checked (at least ``min_free_bytes`` and three
  times the largest raw file so far); a full disk during a write is caught too. Each
  stop says how many images are safe and to rerun with ``--resume``.
* ``complete`` is set in the manifest only when every planned image is on disk.
"""
from __future__ import annotations

import errno
import os
import shutil
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from glossrig.core.atomic import atomic_write_bytes, fsync_dir, fsync_file, publish
from glossrig.core.capture import (MANIFEST, RIG_COPY, ImageEntry, Manifest, check_rig_copy, load_manifest, now_iso,
                                   sha256_file)
from glossrig.core.errors import GlossrigError, InputError

from .camera import Camera
from .errors import CameraDisconnected, CaptureError, DeviceError, LightsError
from .lights import Lights
from .operator import Operator
from .plan import CapturePlan, Shot
from .progress import Progress

SET_ASIDE = "set_aside"
DEFAULT_MIN_FREE_BYTES = 256 * 1024 * 1024


class CaptureTerminated(KeyboardInterrupt):
    """SIGTERM / SIGHUP during a capture: handled like Ctrl-C (LEDs off, resumable)."""


@dataclass
class CaptureReport:
    folder: Path
    planned: int
    taken: int = 0
    kept: int = 0                     # good images found on resume
    set_aside: list[str] = field(default_factory=list)
    complete: bool = False


def _set_aside(folder: Path, name: str, why: str) -> str:
    """Move ``folder/name`` into ``folder/set_aside/`` under a name that exists nowhere yet."""
    dest_dir = folder / SET_ASIDE
    dest_dir.mkdir(exist_ok=True)
    stamp = time.strftime("%Y%m%dT%H%M%S")
    n = 0
    while True:
        dest = dest_dir / f"{name}.{why}-{stamp}" if n == 0 else dest_dir / f"{name}.{why}-{stamp}-{n}"
        if not dest.exists():
            break
        n += 1
    os.replace(folder / name, dest)
    return str(dest.relative_to(folder))


def _software() -> str:
    try:
        from importlib.metadata import version
        return f"glossrig {version('glossrig')}"
    except Exception:   # noqa: BLE001 - not installed as a distribution
        return "glossrig"


class CaptureRun:
    """One execution of a plan into one folder (see the module docstring)."""

    def __init__(self, plan: CapturePlan, out: str | Path, *, lights: Lights, camera: Camera, operator: Operator,
                 backends: dict, resume: bool = False, show_progress: bool = True,
                 min_free_bytes: int = DEFAULT_MIN_FREE_BYTES, disk_usage=shutil.disk_usage,
                 log=None, sleep=time.sleep, meta: dict | None = None):
        self.plan = plan
        self.extra_meta = dict(meta or {})
        self.out = Path(out)
        self.lights, self.camera, self.operator = lights, camera, operator
        self.backends = {k: str(v) for k, v in backends.items()}
        self.resume = resume
        self.show_progress = show_progress
        self.min_free_bytes = int(min_free_bytes)
        self._disk_usage = disk_usage
        self._log_stream = log if log is not None else sys.stderr
        self._sleep = sleep
        self.shots = plan.shots()
        # Each shot's time on the plan's schedule (exposures plus the measured overhead of
        # every shot before it): a function of its place in the plan, not of when this
        # process took it, so a simulated shot is the same after a resume.
        self.schedule_s: list[float] = []
        t = 0.0
        for s in self.shots:
            self.schedule_s.append(t)
            t += plan.shot_cost_s(s)
        self.report = CaptureReport(folder=self.out, planned=len(self.shots))
        self.manifest: Manifest | None = None
        self.progress: Progress | None = None
        self._largest = 0

    # ------------------------------------------------------------ messages
    def log(self, msg: str) -> None:
        if self.progress is not None:
            self.progress.write(msg)
        else:
            print(msg, file=self._log_stream, flush=True)

    # ------------------------------------------------------------ folder
    def _camera_provenance(self) -> dict | None:
        """The camera backend's own record of what makes its images (``provenance()``, where it has one:
        the twin's renderer and sensor path), or None."""
        f = getattr(self.camera, "provenance", None)
        return dict(f()) if callable(f) else None

    def _rig_bytes(self) -> bytes:
        try:
            return self.plan.rig_path.read_bytes()
        except OSError as e:
            raise InputError(f"cannot read the rig file: {e}", path=self.plan.rig_path) from None

    def open_folder(self) -> None:
        """Create the capture folder or, with ``resume``, check and clean it up."""
        out = self.out
        has_manifest = (out / MANIFEST).is_file()
        if out.exists() and not out.is_dir():
            raise InputError("--out exists and is not a folder", path=out)
        if has_manifest and not self.resume:
            raise InputError("already holds a capture; rerun with --resume to complete it, or choose another "
                             "--out (nothing was changed)", path=out)
        if not has_manifest and out.is_dir() and any(out.iterdir()):
            raise InputError("folder is not empty and holds no capture manifest (capture.json); refusing to "
                             "write into it", path=out)
        if not has_manifest:
            self._new_manifest()
            return
        self._resume_manifest()

    def _new_manifest(self) -> None:
        self.out.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(self.out / RIG_COPY, self._rig_bytes())
        meta = {"rig_name": self.plan.rig.name, "rig_source": str(self.plan.rig_path), "sample": self.plan.sample,
                "plan": self.plan.meta(), "backends": self.backends, "software": _software(), "started": now_iso()}
        if self.plan.twin and self.backends.get("camera") == "twin":
            meta["twin"] = dict(self.plan.twin)
        prov = self._camera_provenance()
        if prov is not None:
            meta["camera_provenance"] = prov
        meta.update(self.extra_meta)
        self.manifest = Manifest(folder=self.out, rig=RIG_COPY, material=self.plan.sample, images=[],
                                 complete=False, meta=meta)
        self.manifest.save()
        fsync_dir(self.out)

    def _resume_manifest(self) -> None:
        out = self.out
        m = load_manifest(out)
        where = out / MANIFEST
        plan_meta = m.meta.get("plan", {})
        if m.material != self.plan.sample:
            raise InputError(f"this capture is of sample {m.material!r}, the plan says {self.plan.sample!r}; "
                             "refusing to mix samples", path=where)
        if plan_meta.get("sha256") != self.plan.text_sha256:
            raise InputError(f"the capture was started with another plan ({plan_meta.get('path', '?')}, sha256 "
                             f"{str(plan_meta.get('sha256'))[:12]}...), this one is {self.plan.path} (sha256 "
                             f"{self.plan.text_sha256[:12]}...); resume with the original plan or start a new "
                             "capture folder", path=where)
        check_rig_copy(out, self._rig_bytes(), copy=m.rig, where=where,
                       then="refusing to mix rigs in one capture")
        old = m.meta.get("backends", {})
        for k, v in self.backends.items():
            if k in old and old[k] != v:
                raise InputError(f"the capture was started with {k} backend {old[k]!r}, not {v!r}; refusing to mix "
                                 "them in one capture", path=where)
        planned = {s.key for s in self.shots}
        good: list[ImageEntry] = []
        seen: set = set()
        self.log(f"resume: checking {len(m.images)} recorded image(s) in {out}")
        for im in m.images:
            f = out / im.file
            if not f.is_file():
                self.log(f"resume: {im.file} is missing; it will be retaken")
                continue
            if sha256_file(f) != im.sha256:
                dest = _set_aside(out, im.file, "damaged")
                self.report.set_aside.append(dest)
                self.log(f"resume: {im.file} does not match its checksum; moved to {dest}, it will be retaken")
                continue
            if im.key() in seen:
                self.log(f"resume: {im.file} duplicates an earlier entry; keeping both files, using the first")
            seen.add(im.key())
            good.append(im)
            self._largest = max(self._largest, f.stat().st_size)
        recorded = {im.file for im in good}
        ext = self.camera.extension.lower()
        stems = {s.stem for s in self.shots}
        for p in sorted(out.iterdir()):
            name = p.name
            if name.startswith(".") and name.endswith(".part"):
                p.unlink()       # an unfinished write: incomplete by construction
                continue
            if p.is_file() and name not in recorded and Path(name).stem in stems and name.lower().endswith(ext):
                dest = _set_aside(out, name, "unrecorded")
                self.report.set_aside.append(dest)
                self.log(f"resume: {name} was written but never recorded (crash between the two); moved to "
                         f"{dest}, it will be retaken")
        self.report.kept = sum(1 for im in good if im.key() in planned)
        prov = self._camera_provenance()
        if prov is not None and m.meta.get("camera_provenance") not in (None, prov):
            # allowed (the same physics and statistics), but said and recorded: the finished capture is not
            # the bytes an uninterrupted run of either camera would have written
            self.log(f"resume: warning: the capture was started by a camera made otherwise "
                     f"({m.meta['camera_provenance']}); the remaining images are made by {prov}: the same "
                     "statistics, but not the bytes an uninterrupted run would have written")
            m.meta.setdefault("resumed_camera_provenance", []).append(prov)
        m.images = good
        m.complete = False
        m.meta.setdefault("resumed", []).append(now_iso())
        self.manifest = m
        m.save()
        fsync_dir(out)

    def remaining(self) -> list[Shot]:
        done = {im.key() for im in self.manifest.images} if self.manifest else set()
        return [s for s in self.shots if s.key not in done]

    # ------------------------------------------------------------ shooting
    def _check_space(self) -> None:
        need = max(self.min_free_bytes, 3 * self._largest)
        try:
            free = self._disk_usage(self.out).free
        except OSError:
            return
        if free < need:
            raise CaptureError(f"disk nearly full: {free / 2**20:.0f} MiB free in {self.out}, the next raw file "
                               f"needs at least {need / 2**20:.0f} MiB")

    def _take(self, shot: Shot) -> ImageEntry:
        name = shot.stem + self.camera.extension
        final = self.out / name
        if final.exists():
            raise CaptureError(f"{final} exists but is not in the manifest; refusing to overwrite it")
        tmp = self.out / f".{name}.part"
        if tmp.exists():
            tmp.unlink()
        started = now_iso()
        announce = getattr(self.camera, "next_shot", None)
        if announce is not None:     # optional: a simulated camera keys its shot by it (Camera protocol)
            announce(shot, self.schedule_s[shot.index])
        try:
            info = self.camera.capture(tmp)
            fsync_file(tmp)
            digest = sha256_file(tmp)
            try:
                publish(tmp, final, overwrite=False)      # fsyncs the folder too
            except FileExistsError:
                raise CaptureError(f"{final} appeared while shooting; refusing to overwrite it") from None
        except BaseException:
            try:
                tmp.unlink()
            except FileNotFoundError:
                pass
            raise
        self._largest = max(self._largest, final.stat().st_size)
        extra = {"index": shot.index, "exposure_s_file": info.exposure_s, "iso_file": info.iso,
                 "aperture_file": info.aperture}
        if info.camera:
            extra["camera"] = info.camera
        if shot.view is not None:
            extra["view"] = shot.view
        return ImageEntry(file=name, role=shot.role, leds=list(shot.leds), rotation=shot.rotation,
                          repeat=shot.repeat, exposure_s=shot.exposure_s, iso=shot.iso, aperture=shot.aperture,
                          time=info.time or started, sha256=digest, extra=extra)

    def _operator(self, fn, *args) -> None:
        self.lights.all_off()
        if self.progress is not None:
            self.progress.clear()
        fn(*args)
        if self.progress is not None:
            self.progress.refresh()

    def _loop(self, todo: list[Shot]) -> None:
        rotation = None
        leds = None
        settings = None
        m = self.manifest
        for shot in todo:
            if shot.role == "checkerboard":
                self._operator(self.operator.place_checkerboard, shot.view, self.plan.checkerboard_views)
                leds = None
            elif shot.rotation != rotation:
                self._operator(self.operator.rotate_to, shot.rotation)
                rotation = shot.rotation
                leds = None
            if self.progress is not None:
                self.progress.start(shot)
            if shot.leds != leds:
                self.lights.switch(shot.leds)
                leds = shot.leds
                if self.plan.settle_s:
                    self._sleep(self.plan.settle_s)
            if shot.settings() != settings:
                self.camera.configure(exposure_s=shot.exposure_s, iso=shot.iso, aperture=shot.aperture)
                settings = shot.settings()
            self._check_space()
            entry = self._take(shot)
            m.images.append(entry)
            try:
                m.save()
            except OSError as e:
                m.images.pop()
                raise CaptureError(f"could not record {entry.file} in the manifest ({e}); the manifest on disk "
                                   "still lists every earlier image") from e
            self.report.taken += 1
            if self.progress is not None:
                self.progress.finish(shot, self.plan.shot_cost_s(shot))
            if shot.role == "checkerboard":
                # The board has to be moved for the next view, and the sample may need mounting next.
                rotation = None

    def _lights_off(self) -> str | None:
        try:
            self.lights.all_off()
            return None
        except Exception as e:   # noqa: BLE001 - reported to the operator, never swallowed
            try:
                self.lights.all_off()     # one more try: a serial timeout is often transient
                return None
            except Exception:   # noqa: BLE001
                return f"{e}"

    def _explain(self, e: BaseException) -> str:
        n = len(self.manifest.images) if self.manifest else 0
        total = len(self.shots)
        kept = f"{n} of {total} images are safe in {self.out}"
        text = str(e).rstrip()
        end = "" if text.endswith((".", "?", "!")) else "."
        if isinstance(e, CameraDisconnected):
            return f"camera lost: {text}{end} {kept}; reconnect the camera and rerun with --resume."
        if isinstance(e, LightsError):
            return f"LED switching failed: {text}{end} {kept}; check the relay board and rerun with --resume."
        if isinstance(e, DeviceError):
            return f"{text}{end} {kept}; fix the cause and rerun with --resume."
        if isinstance(e, OSError) and e.errno == errno.ENOSPC:
            return f"disk full ({e}). {kept}; free some space and rerun with --resume."
        if isinstance(e, OSError):
            return f"file system error ({e}). {kept}; rerun with --resume once it is fixed."
        return f"{text}{end} {kept}; rerun with --resume to continue."

    def run(self) -> CaptureReport:
        self.open_folder()
        todo = self.remaining()
        handlers = self._install_signals()
        try:
            self.lights.all_off()     # a previous run may have been killed with LEDs on
            if todo:
                work = sum(self.plan.shot_cost_s(s) for s in todo)
                self.progress = Progress(work, len(self.shots), done_shots=len(self.shots) - len(todo),
                                         disable=not self.show_progress)
                self._loop(todo)
        except BaseException as e:
            off = self._lights_off()
            self._close_progress()
            self._restore_signals(handlers)
            off_msg = (f" WARNING: the LEDs could not be switched off ({off}); switch the relay board off by hand."
                       if off else " The LEDs are off.")
            if isinstance(e, KeyboardInterrupt):
                n = len(self.manifest.images) if self.manifest else 0
                print(f"capture interrupted: {n} of {len(self.shots)} images are safe in {self.out}; rerun with "
                      f"--resume to continue.{off_msg}", file=self._log_stream, flush=True)
                raise
            if isinstance(e, InputError):
                raise
            if isinstance(e, (GlossrigError, OSError)):
                raise CaptureError(self._explain(e) + off_msg) from e
            raise
        off = self._lights_off()
        self._close_progress()
        self._restore_signals(handlers)
        if off:
            raise CaptureError(f"all images were taken, but the LEDs could not be switched off ({off}); switch the "
                               "relay board off by hand")
        missing = self.remaining()
        if not missing:
            # plan order, whatever order a resume retook images in: a resumed capture's
            # manifest lists its images exactly as an uninterrupted one's does
            order = {s.key: s.index for s in self.shots}
            self.manifest.images.sort(key=lambda im: order.get(im.key(), len(order)))
            self.manifest.complete = True
            self.manifest.meta["finished"] = now_iso()
            self.manifest.save()
            fsync_dir(self.out)
        self.report.complete = not missing
        return self.report

    def _close_progress(self) -> None:
        if self.progress is not None:
            self.progress.close()
            self.progress = None

    # ------------------------------------------------------------ signals
    def _install_signals(self):
        if threading.current_thread() is not threading.main_thread():
            return None

        def handler(signum, frame):
            raise CaptureTerminated(f"signal {signal.Signals(signum).name}")

        old = {}
        for sig in (signal.SIGTERM, getattr(signal, "SIGHUP", None)):
            if sig is not None:
                old[sig] = signal.signal(sig, handler)
        return old

    def _restore_signals(self, old) -> None:
        if old:
            for sig, h in old.items():
                signal.signal(sig, h)


def run_capture(plan: CapturePlan, out: str | Path, *, lights: Lights, camera: Camera, operator: Operator,
                backends: dict, resume: bool = False, show_progress: bool = True, **kw) -> CaptureReport:
    """Execute ``plan`` into the capture folder ``out`` (module docstring)."""
    return CaptureRun(plan, out, lights=lights, camera=camera, operator=operator, backends=backends, resume=resume,
                      show_progress=show_progress, **kw).run()
