"""Extraction that follows a capture while it is being taken (issue 19: samples ready
within a minute of the last exposure).

Thesis 4.2.3 takes a rotation's images LED by LED (the calibration image first, then each
LED's LDR sequences), and each (rotation, LED) unit of the extraction (thesis 4.3-4.4 per
LED: HDR of that LED's sequences, eq. 4.31-4.50) depends only on that rotation's
calibration image and that LED's sequence files
(:func:`glossrig.core.extraction.extract.measure_unit`). The capture orchestrator
(:mod:`glossrig.hardware.orchestrator`; ``glossrig simulate`` runs through it too) records
each raw file in ``capture.json`` only once the file is durable, rewrites the manifest
atomically after every image and records the plan (rotations, LEDs, repeats, exposures)
in ``meta["plan"]`` before the first shot. So a unit can be measured as soon as the
manifest lists its calibration image and every planned (repeat, exposure) of its LED.

:func:`follow_extract`:

1. checks that the reference capture is complete (it is taken beforehand: only the sample
   is followed);
2. polls the sample's ``capture.json`` (every ``poll_s``; a poll that finds the file
   unchanged costs one ``stat``) and measures each unit as soon as its files are listed,
   and the reference's units while the sample has none ready;
3. once the capture is marked complete, hands the finished units to the work store of a
   plain extraction and runs :func:`glossrig.core.extraction.extract.extract_samples`
   with it, which reuses them, measures whatever is left and normalises (eq. 4.78). The
   table is therefore the one ``glossrig extract`` makes of the finished capture.

Units are kept while following in their own work store (``OUT.follow/``), whose
fingerprint is that of the extraction without the sample manifest (which changes with
every image); instead each unit records the manifest entries it was made from (file,
settings, time, sha256 of the calibration image and of its sequence images). A unit is
handed on only when those entries are the finished capture's, so an image retaken on a
resume (a damaged file set aside) redoes exactly the units that read it.

An interrupted capture: following waits; after ``idle_timeout_s`` without a new image it
stops with a message saying to resume the capture and rerun with ``--resume``, which
reuses the finished units (``resume=True``).
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd

from glossrig.core.calibration.intrinsics import CameraCalibration
from glossrig.core.capture import MANIFEST, Manifest, load_manifest
from glossrig.core.checkpoint import WorkStore, work_folder_for
from glossrig.core.errors import InputError
from glossrig.core.extraction import extract as ex
from glossrig.core.extraction.extract import capture_units, unit_name
from glossrig.core.rig import Rig, load_rig

_log = logging.getLogger(__name__)

#: the work folder of a followed extraction: ``OUT.follow`` beside the output
FOLLOW_SUFFIX = ".follow"
#: default time without a new image after which following stops (s): a rotation of the
#: sample on a real rig, with the operator's time, fits well within it
IDLE_TIMEOUT_S = 900.0

Unit = tuple[float, int]          # (rotation in degrees, LED id)


def follow_folder_for(output) -> Path:
    """The work folder of a followed extraction writing ``output``: ``OUTPUT.follow``."""
    p = Path(output)
    return p.with_name(p.name + FOLLOW_SUFFIX)


def planned_units(man: Manifest) -> dict[Unit, set[tuple[int, float]]] | None:
    """The (repeat, exposure) pairs planned for each (rotation, LED) unit, from the plan the
    capture orchestrator records in the manifest (:meth:`glossrig.hardware.plan.CapturePlan.meta`);
    None for a capture without one (its units are then measured once it is complete)."""
    plan = man.meta.get("plan")
    if not isinstance(plan, dict):
        return None
    try:
        own = {int(k): [float(t) for t in v] for k, v in (plan.get("led_exposures_s") or {}).items()}
        default = [float(t) for t in plan["exposures_s"]]
        reps = int(plan["repeats"])
        return {(float(rot), int(led)): {(r, t) for r in range(reps) for t in own.get(int(led), default)}
                for rot in plan["rotations"] for led in plan["leds"]}
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"the recorded plan (meta 'plan') is malformed: {e}", path=man.path) from None


def unit_record(man: Manifest, rotation: float, led: int) -> list[dict]:
    """The manifest entries a unit is measured from, in manifest order: the rotation's
    calibration images (:func:`glossrig.core.calibration.poses.calibrate_capture` reads them)
    and the LED's sequence images (:func:`glossrig.core.extraction.extract.led_values`)."""
    return ([im.to_json() for im in man.select("calibration", rotation=rotation)]
            + [im.to_json() for im in ex.led_sequence(man, rotation, led)])


def unit_ready(man: Manifest, rotation: float, led: int, planned: set[tuple[int, float]]) -> bool:
    """Whether the manifest lists the rotation's calibration image and every planned
    (repeat, exposure) of the LED's sequences."""
    if not man.select("calibration", rotation=rotation):
        return False
    have = {(im.repeat, float(im.exposure_s)) for im in ex.led_sequence(man, rotation, led)}
    return planned <= have


def _manifest_state(folder: Path) -> tuple[int, int] | None:
    """(mtime in ns, size) of the manifest, None while there is none: it changes whenever
    the orchestrator records an image (atomic rename of a new file)."""
    try:
        st = (folder / MANIFEST).stat()
    except FileNotFoundError:
        return None
    return (st.st_mtime_ns, st.st_size)


class _Units:
    """The follow work store with each unit's record beside it (``NAME-inputs``), and the
    records of the units known to be current (measured or checked in this run), so that a
    manifest change re-examines only the units whose entries changed."""

    def __init__(self, store: WorkStore, cam: CameraCalibration, lamps: dict[int, np.ndarray] | None,
                 estimator: str):
        self.store, self.cam, self.lamps, self.estimator = store, cam, lamps, estimator
        self._geoms: dict[tuple[str, float], tuple[str, ex.RotationGeometry]] = {}
        self._known: dict[str, list[dict]] = {}          # unit name -> the record its stored version has
        self._rigs: dict[Path, Rig] = {}

    def current(self, name: str, record: list[dict]) -> bool:
        """Whether the store holds the unit made from ``record``'s entries."""
        if name not in self._known and self.store.has(name) and self.store.has(name + "-inputs"):
            self._known[name] = self.store.load(name + "-inputs")
        return self._known.get(name) == record

    def measure(self, man: Manifest, prefix: str, rotation: float, led: int) -> bool:
        """Measure one unit unless its stored version was made from the same entries;
        True when it was measured now."""
        name = unit_name(prefix, rotation, led)
        record = unit_record(man, rotation, led)
        if self.current(name, record):
            return False
        cal = record[0]["sha256"]
        key = (prefix, rotation)
        rig_path = man.rig_path()
        if rig_path not in self._rigs:
            self._rigs[rig_path] = load_rig(rig_path)
        rig = self._rigs[rig_path]
        if key not in self._geoms or self._geoms[key][0] != cal:
            self._geoms[key] = (cal, ex.rotation_geometry(man, rig, self.cam, rotation))
        df = ex.measure_unit(man, rig, self._geoms[key][1], rotation, led, self.lamps, self.estimator)
        self.store.save(name, df)
        self.store.save(name + "-inputs", record)
        self._known[name] = record
        return True


def follow_extract(sample_dir, reference_dir, cam: CameraCalibration, lamps: dict[int, np.ndarray], out, *,
                   albedo: float = 0.8, estimator: str = "ml", resume: bool = False,
                   idle_timeout_s: float = IDLE_TIMEOUT_S, poll_s: float = 1.0, progress: bool = False, plots=None,
                   workers: int | None = None, clock: Callable[[], float] = time.monotonic,
                   sleep: Callable[[float], None] = time.sleep) -> Followed:
    """Extract the BRDF samples of a capture being taken (module docstring): the table of
    :func:`glossrig.core.extraction.extract.extract_samples` for the finished capture, the
    work stores (the follow store and the extraction's, both beside ``out``) for the
    caller to remove once the table is written, and both captures' manifests as the table
    was made from them (for its provenance; not read again). ``resume`` reuses the units of an earlier
    follow (or extraction) of the same inputs. ``workers``: processes of the final extraction
    (:func:`glossrig.core.extraction.extract.extract_samples`); while following, units are
    measured here as they become ready."""
    if not idle_timeout_s > 0 or not poll_s > 0:
        raise InputError(f"the idle timeout and the poll interval must be > 0 s, got {idle_timeout_s}, {poll_s}")
    sample_dir, reference_dir = Path(sample_dir), Path(reference_dir)
    ref = load_manifest(reference_dir)
    ref.require_sequences("extract", "REF_DIR")
    if not ref.complete:
        raise InputError("the reference capture is not complete: --follow follows the sample capture only, so "
                         "take (or resume) the reference first", path=ref.path)
    waited = 0.0
    while _manifest_state(sample_dir) is None:          # the capture may not have started yet
        if waited > idle_timeout_s:
            raise InputError(f"no capture.json appeared in {idle_timeout_s:g} s: is the capture running?",
                             path=sample_dir)
        sleep(poll_s)
        waited += poll_s
    # the sample manifest grows with every image: each unit records its own entries instead
    fp = ex.measurement_fingerprint(sample_dir, reference_dir, cam, lamps, estimator=estimator)
    del fp["captures"]["sample"]
    units = _Units(WorkStore(follow_folder_for(out), fp, resume=resume), cam, lamps, estimator)
    ref_todo = capture_units(ref)       # measured while the sample has nothing ready (the sample first)
    _log.info(f"follow: following {sample_dir}")

    seen, idle_since, measured = None, clock(), 0
    while True:
        state = _manifest_state(sample_dir)
        if state != seen:
            seen = state
            man = load_manifest(sample_dir)
            plan = planned_units(man)
            if man.select("sequence"):
                ex.check_compatible(man, ref)
            for (rot, led), want in (plan or {}).items():
                if unit_ready(man, rot, led, want) and units.measure(man, "sample-", rot, led):
                    measured += 1
                    _log.info(f"follow: rotation {rot:g} LED {led} measured ({measured} of {len(plan or {})} units)")
            if man.complete:
                break
            idle_since = clock()
        elif ref_todo:
            rot, led = ref_todo.pop(0)
            units.measure(ref, "reference-", rot, led)
            continue                    # look at the sample again before waiting
        elif clock() - idle_since > idle_timeout_s:
            n = sum(1 for u in units.store.units() if u.startswith("sample-") and not u.endswith("-inputs"))
            raise InputError(f"no new image for {idle_timeout_s:g} s and the capture is not complete (interrupted?); "
                             f"{n} finished unit(s) are kept in {units.store.folder}: resume the capture "
                             "(glossrig capture/simulate --resume) and rerun this command with --resume",
                             path=sample_dir / MANIFEST)
        sleep(poll_s)
    return _finish(man, ref, cam, lamps, out, units, albedo=albedo, estimator=estimator,
                   resume=resume, progress=progress, plots=plots, workers=workers)


class Followed(NamedTuple):
    """What :func:`follow_extract` made: the samples ``table``, the work ``stores`` to remove
    once it is written, and the finished ``sample`` and ``reference`` manifests it was made from."""

    table: pd.DataFrame
    stores: list[WorkStore]
    sample: Manifest
    reference: Manifest


def _finish(ms: Manifest, mr: Manifest, cam, lamps, out, units: _Units, *, albedo: float, estimator: str,
            resume: bool, progress: bool, plots, workers: int | None) -> Followed:
    """The finished capture (``ms``: its manifest as the last poll read it, marked complete, so
    final; ``mr``: the reference's, complete from the start): hand every unit whose record is
    the finished manifests' to the extraction's work store, then extract with it (the remaining
    units measured there)."""
    fp = ex.measurement_fingerprint(ms, mr, cam, lamps, estimator=estimator)
    store = WorkStore(work_folder_for(out), fp, resume=resume)
    handed, total = 0, 0
    for prefix, man in (("sample-", ms), ("reference-", mr)):
        for rot, led in capture_units(man):
            name = unit_name(prefix, rot, led)
            total += 1
            if not store.has(name) and units.current(name, unit_record(man, rot, led)):
                store.save(name, units.store.load(name))
                handed += 1
    _log.info(f"follow: capture complete; {handed} of {total} units were measured while it ran")
    df = ex.extract_samples(ms, mr, cam, lamps, albedo=albedo, estimator=estimator,
                            progress=progress, plots=plots, store=store, workers=workers)
    return Followed(df, [store, units.store], ms, mr)
