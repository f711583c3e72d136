"""From a capture folder to BRDF samples (thesis 4.3-4.4): the pipeline's main stage.

Per sample rotation (one calibration image each):
1. linearise and demosaic the calibration image, find the markers, solve the holder
   and cylinder poses (:mod:`glossrig.core.calibration.poses`, eq. 4.6-4.25);
2. cast rays through the centres of the 2x2 Bayer blocks that see the sample and
   intersect the cylinder (:mod:`glossrig.core.extraction.cylinder`, eq. 4.26-4.30, corrected);
3. per LED: read only an even-aligned crop holding the sample and the holder
   marker's white patch from every raw file (streaming: one LED's frames at a
   time), combine repeats, correct jitter, estimate HDR (:mod:`glossrig.core.radiometry.hdr`,
   eq. 4.31-4.44) and divide by the white patch (eq. 4.45-4.50);
4. each Bayer block becomes one sample with its R, G (mean of two) and B values
   at the block centre. The thesis keeps single CFA pixels; one sample per block
   gives all three channels at one geometry at half the linear resolution.

Units of work: each (rotation, LED) of a capture is measured independently
(:func:`measure_unit`), in worker processes (:mod:`glossrig.core.workers`, one per usable
core by default); :func:`extract_samples` streams them, dividing each sample unit by the
reference's as soon as both are measured, so memory does not grow with the number of
LEDs beyond the output table. A plainly stored DNG is cropped before decoding (only the
crop's rows are read, :func:`glossrig.core.calibration.raw.read_raw`).

Diffuse normalisation (thesis 4.4, eq. 4.73-4.78) divides the sample's values by
the reference capture's at the nearest geometry, found with a KD-tree per (LED,
rotation). Departure from eq. 4.76: the distance is the Euclidean distance of the
two unit directions (wi, wo) in the local frame rather than a sum of squared
angle differences, which wraps phi correctly and has no pole singularity.
"""
from __future__ import annotations

import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import pandas as pd

from glossrig.core.radiometry import hdr as hdrmod
from glossrig.core.models.angles import ANGLE_COLUMNS, local_direction
from glossrig.core.capture import Manifest, load_manifest
from glossrig.core.extraction.cylinder import SurfaceSamples, sample_angles, surface_samples
from glossrig.core.errors import InputError
from glossrig.core.calibration.intrinsics import CameraCalibration
from glossrig.core.radiometry.patch import normalise_by_patch
from glossrig.core.progress import progress_enabled
from glossrig.core.calibration.markers import holder_marker_corners
from glossrig.core.calibration.raw import even_crop
from glossrig.core.rig import Rig, load_rig
from glossrig.core.samples import CHANNEL_WEIGHT_COLUMNS, COLUMNS
from glossrig.core.workers import ordered_results, process_pool, release_memory, resolve_workers

PATCH_SHRINK = 0.2        # keep the inner 60 % of the white patch (away from the red frame)
#: a Bayer block is a sample only when the rays through its footprint's corners, centre
#: +- this many pixels, meet the sample (the whole 2x2 block; cylinder.surface_samples)
BLOCK_FOOTPRINT_HALF_PX = 1.0


@dataclass
class RotationGeometry:
    rotation: float
    calibration_file: str
    R_hold: np.ndarray            # holder -> camera
    t_hold: np.ndarray
    R_cyl: np.ndarray             # cylinder -> holder
    t_cyl: np.ndarray
    surface: SurfaceSamples       # block centres seeing the sample (holder frame)
    crop: tuple[int, int, int, int]
    patch_mask: np.ndarray        # bool, crop-sized: white patch pixels
    block_index: tuple[np.ndarray, np.ndarray] | None = field(repr=False, default=None)  # (row, col) in crop blocks
    #: calibrate_capture's result these poses come from (corners, corner PnP, edge-fit std): what
    #: the calibration draws start from (calibrate lamps: calibration_uncertainty.load_inputs(solved=))
    poses: dict | None = field(repr=False, default=None)


def camera_arrays(cam: CameraCalibration):
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    return K, np.asarray(cam.distortion, np.float64)


def rotation_geometry(man: Manifest, rig: Rig, cam: CameraCalibration, rotation: float) -> RotationGeometry:
    """Poses, sample blocks and white-patch mask of one rotation's calibration image."""
    from glossrig.core.calibration.poses import calibrate_capture

    if not cam.path:
        raise InputError("the camera calibration must come from a file (glossrig calibrate camera)")
    poses = calibrate_capture(man.folder, cam.path, rotation=rotation)
    w, h = poses["image_size"]
    K, dist = camera_arrays(cam)
    R_hold, t_hold = poses["holder"]["R"], poses["holder"]["t_mm"]
    R_cyl, t_cyl = poses["cylinder_in_holder"]["R"], poses["cylinder_in_holder"]["t_mm"]
    path = man.folder / poses["file"]
    # Blocks: first find the sample's pixel bounding box at full resolution (coarse grid).
    gu, gv = np.meshgrid(np.arange(0, w, 4.0), np.arange(0, h, 4.0))
    coarse = surface_samples(K, dist, (w, h), R_hold, t_hold, R_cyl, t_cyl, rig.cylinder_radius,
                             rig.sample_height, pixels=(gu, gv))
    if len(coarse.u) == 0:
        raise InputError("no pixel sees the sample with the calibrated poses", path=path)
    sx0, sx1 = int(coarse.u.min()) - 8, int(coarse.u.max()) + 8
    sy0, sy1 = int(coarse.v.min()) - 8, int(coarse.v.max()) + 8
    # White patch polygon (shrunk towards its centre) projected with the holder pose.
    inner = holder_marker_corners(rig, inner=True)
    centre = inner.mean(axis=0)
    shrunk = centre + (inner - centre) * (1 - 2 * PATCH_SHRINK)
    poly, _ = cv2.projectPoints(shrunk, cv2.Rodrigues(R_hold)[0], t_hold, K, dist)
    poly = poly.reshape(-1, 2)[[0, 1, 3, 2]]          # UL, UR, LR, LL
    px0, py0 = np.floor(poly.min(axis=0)).astype(int)
    px1, py1 = np.ceil(poly.max(axis=0)).astype(int) + 1
    crop = even_crop((max(0, min(sx0, px0)), max(0, min(sy0, py0)), min(w, max(sx1, px1)), min(h, max(sy1, py1))), (w, h))
    x0, y0, x1, y1 = crop
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillConvexPoly(mask, np.round(poly - [x0, y0]).astype(np.int32), 1)
    # Bayer blocks inside the crop, cast through their centres.
    bj, bi = np.meshgrid(np.arange((x1 - x0) // 2), np.arange((y1 - y0) // 2))
    u = x0 + 2 * bj.ravel() + 0.5
    v = y0 + 2 * bi.ravel() + 0.5
    surf = surface_samples(K, dist, (w, h), R_hold, t_hold, R_cyl, t_cyl, rig.cylinder_radius, rig.sample_height,
                           pixels=(u, v), footprint_half_px=BLOCK_FOOTPRINT_HALF_PX)
    geom = RotationGeometry(rotation, poses["file"], R_hold, t_hold, R_cyl, t_cyl, surf, crop, mask.astype(bool),
                            poses=poses)
    geom.block_index = (((surf.v - 0.5 - y0) / 2).astype(int), ((surf.u - 0.5 - x0) / 2).astype(int))
    return geom


class LedValues(NamedTuple):
    """One LED's blocks (N, 3 channels): patch-normalised HDR ``values`` and their
    ``variance`` (NaN where the channel has no valid value), the channel's ``status``
    (a :data:`glossrig.core.radiometry.hdr.STATUS_REASONS` key; see :func:`block_status`)
    and ``exposure_to_fix`` (s; :func:`glossrig.core.radiometry.hdr.exposure_to_fix`,
    NaN where valid or unknown)."""

    values: np.ndarray
    variance: np.ndarray
    status: np.ndarray
    exposure_to_fix: np.ndarray


def led_rate(man: Manifest, rig: Rig, seq: list, crop: tuple[int, int, int, int], estimator: str = "ml"):
    """One LED's exposure sequence ``seq`` (manifest entries) over ``crop`` (x0, y0, x1, y1) combined
    into an HDR rate mosaic (thesis eq. 4.31-4.44, :mod:`glossrig.core.radiometry.hdr`): (rate, variance,
    status, cfa, ends) - ``ends`` what :func:`glossrig.core.radiometry.hdr.exposure_to_fix` reads."""
    # one exposure's frames at a time, read (checksums checked) as they are combined
    stack = hdrmod.stream_stack(lambda i: man.read_raw(seq[i], crop=crop), [im.exposure_s for im in seq],
                                [str(man.folder / im.file) for im in seq], [im.repeat for im in seq])
    cfa = stack.cfa
    release_memory()          # the frames' pages, freed, back to the system before the HDR step
    if estimator == "ml":
        ends = stack.ends()   # exposure_to_fix reads the uncorrected ends; the stack is corrected in place
        res = hdrmod.hdr_from_stack(stack, hdrmod.NoiseModel.from_rig(rig, iso=seq[0].iso), overwrite=True)
        rate, var, status = res.rate, res.variance, res.status
    elif estimator == "thesis":
        images, _ = hdrmod.neighbour_correct(stack.images, stack.exposure_s, clipped=stack.clipped, method="thesis")
        rate = hdrmod.hdr_thesis(images, stack.exposure_s)
        rate = np.where(rate > 0, rate, np.nan).astype(np.float32)
        noise = hdrmod.NoiseModel.from_rig(rig, iso=seq[0].iso)
        var = noise.variance(rate, stack.repeats).astype(np.float32)   # nominal, for weights only
        # eq. 4.44 has no reason for its 0: saturated at the shortest exposure, else too dark
        status = np.where(np.isfinite(rate), hdrmod.VALID,
                          np.where(stack.clipped[0] | (stack.images[0] >= hdrmod.HI), hdrmod.TOO_BRIGHT,
                                   hdrmod.TOO_DARK)).astype(np.uint8)
        ends = stack
    else:
        raise InputError(f"HDR estimator must be 'ml' or 'thesis', got {estimator!r}")
    del stack
    return rate, var, status, cfa, ends


def led_values(man: Manifest, rig: Rig, geom: RotationGeometry, led: int,
               estimator: str = "ml") -> LedValues:
    """Patch-normalised HDR values (N_blocks, 3), their variances and per-channel
    validity for one LED (thesis eq. 4.31-4.50 through :mod:`glossrig.core.radiometry.hdr`
    and :mod:`glossrig.core.radiometry.patch`)."""
    seq = led_sequence(man, geom.rotation, led)
    if not seq:
        raise InputError(f"no sequence for LED {led} at rotation {geom.rotation:g} deg", path=man.path)
    rate, var, status, cfa, ends = led_rate(man, rig, seq, geom.crop, estimator)
    tfix = hdrmod.exposure_to_fix(ends, status)
    norm = normalise_by_patch(rate, geom.patch_mask, cfa, variance=var, name=str(man.folder / seq[0].file))
    assert norm.variance is not None        # a variance went in
    vals, vvar = block_values(norm.image, norm.variance, cfa, geom.block_index)
    st, fix = block_status(status, tfix, cfa, geom.block_index)
    st[~np.isfinite(vals) & (st == hdrmod.VALID)] = hdrmod.TOO_FEW      # no valid pixel reason: say "too few"
    return LedValues(vals, vvar, st, fix)


def led_sequence(man: Manifest, rotation: float, led: int) -> list:
    """The manifest entries of one LED's sequence images at one rotation (every repeat and
    exposure, in manifest order)."""
    return man.select("sequence", rotation=rotation, leds=[led])


def block_values(rate: np.ndarray, var: np.ndarray, cfa, block_index) -> tuple[np.ndarray, np.ndarray]:
    """R, G, B values (and variances) at the centres of 2x2 Bayer blocks.

    Each CFA position (di, dj) forms a half-resolution plane whose pixels sit
    (0.5 - di, 0.5 - dj) pixels away from the block centre; reading every plane
    there by bilinear interpolation puts all three channels at the block centre's
    geometry. Taking the raw R and B pixels instead would misregister them by
    half a pixel, which inside a narrow lobe costs several per cent (measured:
    4.6 % / 6.7 % median error for R / B against 1.4 % for G at quarter scale).
    """
    from scipy.ndimage import map_coordinates

    cid = np.asarray(cfa)
    bi, bj = block_index
    vals = np.zeros((len(bi), 3))
    vvar = np.zeros((len(bi), 3))
    cnt = np.zeros(3)
    for di in range(2):
        for dj in range(2):
            c = int(cid[di, dj])
            plane = rate[di::2, dj::2]
            vplane = var[di::2, dj::2]
            coords = np.stack([bi + (0.5 - di) / 2, bj + (0.5 - dj) / 2])
            vals[:, c] += map_coordinates(plane, coords, order=1, mode="nearest")
            # bilinear weights at offsets of a quarter plane pixel: sum of squares 0.390625
            vvar[:, c] += map_coordinates(vplane, coords, order=1, mode="nearest") * 0.390625
            cnt[c] += 1
    return vals / cnt, vvar / cnt ** 2


def block_status(status: np.ndarray, exposure_to_fix: np.ndarray, cfa, block_index) -> tuple[np.ndarray, np.ndarray]:
    """Per block and channel (N, 3): why the channel has no value, and the exposure that
    would have given it one, from the pixels :func:`block_values` reads.

    A block's channel is read by bilinear interpolation from the 2 x 2 pixels of each of
    its CFA planes nearest the block centre, so it is missing when one of them is: its
    status is TOO_BRIGHT if one of them is saturated, else TOO_DARK if one is too dark,
    else TOO_FEW (:data:`glossrig.core.radiometry.hdr.STATUS_REASONS`; VALID when all
    are valid). Its exposure to fix is the one for the mean rate of those pixels of that
    status (the harmonic mean of their exposures to fix; a single pixel's is noisy;
    NaN when none is known)."""
    cid = np.asarray(cfa)
    bi, bj = block_index
    n = len(bi)
    bright = np.zeros((n, 3), bool)
    dark = np.zeros((n, 3), bool)
    few = np.zeros((n, 3), bool)
    inv = {code: np.zeros((n, 3)) for code in (hdrmod.TOO_DARK, hdrmod.TOO_BRIGHT)}    # sum of 1 / t_fix
    cnt = {code: np.zeros((n, 3)) for code in (hdrmod.TOO_DARK, hdrmod.TOO_BRIGHT)}
    for di in range(2):
        for dj in range(2):
            c = int(cid[di, dj])
            plane = np.ascontiguousarray(status[di::2, dj::2]).ravel()
            tplane = exposure_to_fix[di::2, dj::2]
            h, w = tplane.shape
            # per pixel of the plane, once: 1 / t_fix where the pixel has that status and a known t_fix
            per_code = {}
            for code in (hdrmod.TOO_DARK, hdrmod.TOO_BRIGHT):
                known = (status[di::2, dj::2] == code) & ~np.isnan(tplane)
                with np.errstate(divide="ignore"):
                    per_code[code] = (np.where(known, 1.0 / np.where(known, tplane, 1.0), 0.0).ravel(), known.ravel())
            for oi in (0, 1):          # the bilinear stencil of the offset (0.5 - di) / 2 (block_values)
                rows = np.clip(bi - di + oi, 0, h - 1) * w
                for oj in (0, 1):
                    at = rows + np.clip(bj - dj + oj, 0, w - 1)
                    sv = plane[at]
                    bright[:, c] |= sv == hdrmod.TOO_BRIGHT
                    dark[:, c] |= sv == hdrmod.TOO_DARK
                    few[:, c] |= sv == hdrmod.TOO_FEW
                    for code, (inv_t, known) in per_code.items():
                        inv[code][:, c] += inv_t[at]
                        cnt[code][:, c] += known[at]
    st = np.where(bright, hdrmod.TOO_BRIGHT, np.where(dark, hdrmod.TOO_DARK,
                                                      np.where(few, hdrmod.TOO_FEW, hdrmod.VALID))).astype(np.uint8)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_dark = np.where(cnt[hdrmod.TOO_DARK] > 0, cnt[hdrmod.TOO_DARK] / inv[hdrmod.TOO_DARK], np.nan)
        t_bright = np.where(cnt[hdrmod.TOO_BRIGHT] > 0, cnt[hdrmod.TOO_BRIGHT] / inv[hdrmod.TOO_BRIGHT], np.nan)
    fix = np.where(st == hdrmod.TOO_BRIGHT, t_bright, np.where(st == hdrmod.TOO_DARK, t_dark, np.nan))
    return st, fix


@dataclass
class Measured:
    """One capture measured: ``table`` has a row per (block, LED, rotation) with pixel,
    surface point and normal (holder frame), angles (when lamps were given) and
    patch-normalised HDR values ``r, g, b`` with variances ``var_r, var_g, var_b``
    (NaN where that channel has no valid value), each channel's ``status_<c>`` and
    ``fix_s_<c>`` (:class:`LedValues`)."""

    table: pd.DataFrame
    rig_path: str
    geometry: dict           # rotation -> RotationGeometry


def measure_unit(man: Manifest, rig: Rig, g: RotationGeometry, rot: float, led: int,
                 lamps: dict[int, np.ndarray] | None, estimator: str = "ml") -> pd.DataFrame:
    """One (rotation, LED) unit of :func:`measure_capture`: that LED's exposure sequences
    read and combined into HDR values per Bayer block (:func:`led_values`), with each
    block's pixel, surface point, normal and (when ``lamps`` are given) angles. Depends
    only on its arguments, so units can be measured in any order or process."""
    lv = led_values(man, rig, g, led, estimator)
    s = g.surface
    df = pd.DataFrame({"u": np.floor(s.u).astype(np.int32), "v": np.floor(s.v).astype(np.int32)})
    df["led"], df["rotation"] = np.int32(led), float(rot)
    for k, c in enumerate("rgb"):
        df[c] = lv.values[:, k]
        df[f"var_{c}"] = lv.variance[:, k]
        df[f"status_{c}"] = lv.status[:, k]
        df[f"fix_s_{c}"] = lv.exposure_to_fix[:, k]
    df["x"], df["y"], df["z"] = s.points[:, 0], s.points[:, 1], s.points[:, 2]
    df["nx"], df["ny"], df["nz"] = s.normals[:, 0], s.normals[:, 1], s.normals[:, 2]
    if lamps is not None:
        if led not in lamps:
            raise InputError(f"lamp positions have no LED {led}")
        ang = sample_angles(s, lamps[led], rot)
        for col in ANGLE_COLUMNS:
            df[col] = ang[col]
        df["cos_in"], df["cos_out"] = ang["cos_in"], ang["cos_out"]
    return df


@dataclass
class _Source:
    """One capture to measure: its manifest, rig and the prefix of its unit names in a work store."""

    man: Manifest
    rig: Rig
    prefix: str = ""

    def units(self) -> list[tuple[float, int]]:
        """Its (rotation, LED) units in plan order (:func:`capture_units`)."""
        return capture_units(self.man)

    def unit_name(self, rot: float, led: int) -> str:
        return unit_name(self.prefix, rot, led)

    def sequence_files(self, rot: float, led: int) -> list[Path]:
        """The raw files of a unit's sequences (:func:`led_sequence`)."""
        return [self.man.folder / im.file for im in led_sequence(self.man, rot, led)]


def capture_units(man: Manifest) -> list[tuple[float, int]]:
    """The (rotation, LED) units of a capture's sequence images, in plan order (rotations,
    then LEDs ascending): the order :func:`measure_capture` measures them in and
    :mod:`glossrig.core.extraction.follow` hands them on in."""
    return [(rot, led) for rot in man.rotations()
            for led in sorted({im.leds[0] for im in man.select("sequence", rotation=rot)})]


def unit_name(prefix: str, rotation: float, led: int) -> str:
    """A (rotation, LED) unit's name in a :class:`glossrig.core.checkpoint.WorkStore`
    (``sample-rot0-led6``): the one spelling, shared by extract's resume and
    :mod:`glossrig.core.extraction.follow`, so units measured by either are reused by both."""
    return f"{prefix}rot{rotation:g}-led{led}"


def _manifest(capture) -> Manifest:
    """A capture given as its folder or as its already loaded :class:`Manifest` (callers that
    need it several times load it once and pass it on)."""
    return capture if isinstance(capture, Manifest) else load_manifest(capture)


def _open_source(capture, name: str, what: str, prefix: str) -> _Source:
    man = _manifest(capture)
    man.require_sequences(what, name)
    if not man.complete:
        raise InputError("capture is not complete (interrupted?): resume it before extracting", path=man.path)
    return _Source(man, load_rig(man.rig_path()), prefix)


def _measured_units(pool, sources: list[_Source], order, cam: CameraCalibration, lamps, estimator: str, store,
                    geoms: dict, bar, solve=()):
    """The table of every (source index, rotation, LED) of ``order`` (:func:`measure_unit`), yielded
    in that order: from ``store`` when it holds the unit, else measured in ``pool`` (None: in this
    process) and saved to ``store``.

    The geometries (:func:`rotation_geometry`) the measured units need, and those of ``solve``
    (further (source index, rotation) keys a caller wants), that ``geoms`` lacks are solved and
    added to it, in the order the units first need them: in this process first, or in ``pool``
    one at a time (a full-resolution calibration image takes ~2 GB), each next one started as
    soon as the one before is solved, so that it runs beside the units that need only the
    geometries already solved (its wall time overlaps theirs instead of idling the other
    workers). While a geometry is solved the files of the next units are read ahead
    (:func:`_read_ahead`: the disk would otherwise idle)."""
    def stored(i, rot, led) -> bool:
        return store is not None and store.has(sources[i].unit_name(rot, led))

    order = list(order)
    todo = [job for job in order if not stored(*job)]
    need = [k for k in dict.fromkeys([(i, rot) for i, rot, _ in todo] + list(solve)) if k not in geoms]

    def geometry_job(key) -> tuple:
        i, rot = key
        return sources[i].man, sources[i].rig, cam, rot

    if pool is None:
        for key in need:
            geoms[key] = rotation_geometry(*geometry_job(key))
        need = []

    def jobs() -> Iterator[tuple]:
        solving: list = []            # [(key, future)]: the one geometry being solved in the pool

        def start_next() -> None:
            if need and not solving:
                key = need.pop(0)
                solving.append((key, pool.submit(_geometry_in_worker, *geometry_job(key))))

        def wait_one(ahead: list) -> None:
            key, fut = solving.pop()
            if ahead:
                _read_ahead([p for i, rot, led in ahead for p in sources[i].sequence_files(rot, led)])
            geoms[key] = fut.result()
            start_next()

        start_next()
        for n, (i, rot, led) in enumerate(todo):
            while (i, rot) not in geoms:
                wait_one(todo[n:n + max(1, pool.workers)])
            yield sources[i].man, sources[i].rig, geoms[(i, rot)], rot, led, lamps, estimator
        while solving:                # the geometries of ``solve`` no unit needed
            wait_one([])

    computed = ordered_results(pool, measure_unit if pool is None else _unit_in_worker, jobs())
    todo_set = set(todo)
    for i, rot, led in order:
        name = sources[i].unit_name(rot, led)
        if (i, rot, led) in todo_set:
            df = next(computed)
            if store is not None:
                store.save(name, df)
        else:
            df = store.load(name)
        bar.update(1)
        yield df
    for _ in computed:                # nothing is left but the geometries of ``solve``: solve them
        pass


def _read_ahead(paths: list[Path]) -> None:
    """Ask the kernel, from a daemon thread, to read ``paths`` into the page cache
    (``posix_fadvise`` WILLNEED; nothing where the system lacks it): the files a unit will read
    are on their way from disk while this process waits for a geometry. The pages are read
    once; the unit then finds them in memory."""
    import threading

    advise = getattr(os, "posix_fadvise", None)
    if advise is None or not paths:
        return

    def run() -> None:
        for p in paths:
            try:
                fd = os.open(p, os.O_RDONLY)
            except OSError:
                continue                # the unit's own read names the file
            try:
                advise(fd, 0, 0, os.POSIX_FADV_WILLNEED)
            except OSError:
                pass
            finally:
                os.close(fd)

    threading.Thread(target=run, name="read-ahead", daemon=True).start()


def _unit_in_worker(*args) -> pd.DataFrame:
    """:func:`measure_unit` as a worker process runs it (named, so a job pickles as a reference to
    it whatever this process has put in ``measure_unit``'s place), its memory given back after."""
    try:
        return measure_unit(*args)
    finally:
        release_memory()


def _geometry_in_worker(*args) -> RotationGeometry:
    """:func:`rotation_geometry` in a worker process, its memory given back after."""
    try:
        return rotation_geometry(*args)
    finally:
        release_memory()


def _pool(workers: int | None, jobs: int):
    """A process pool of ``workers`` (None: every usable core) for ``jobs`` units of work, or
    a null context (None: work in this process) when one process is asked for or enough."""
    from contextlib import nullcontext

    n = min(resolve_workers(workers), max(jobs, 1))
    return process_pool(n) if n > 1 else nullcontext()


def measure_capture(folder, cam: CameraCalibration, lamps: dict[int, np.ndarray] | None, estimator: str = "ml",
                    progress: bool = False, name: str = "SAMPLE_DIR", what: str = "extract",
                    store=None, unit_prefix: str = "", workers: int | None = None) -> Measured:
    """Measure every (block, LED, rotation) of a capture (see :class:`Measured`).
    ``name`` and ``what`` (the argument and the verb) word the error for a capture
    with no exposure sequences (a checkerboard capture, say), which stops here.

    ``store`` (a :class:`glossrig.core.checkpoint.WorkStore` fingerprinted with this
    capture, camera, lamps and estimator) keeps each finished (rotation, LED) unit as
    ``unit_prefix`` + ``rot<deg>-led<id>`` and reuses the ones it already holds, so an
    interrupted measurement resumes where it stopped with the same table (units are
    concatenated in plan order). The geometry of every rotation is always solved:
    callers use :attr:`Measured.geometry`.

    ``workers``: processes measuring units at once (:mod:`glossrig.core.workers`; None:
    every usable core; 1: all in this process). Units are independent and concatenated in
    plan order, so the table is the same for any number; the store is read and written
    here, in the calling process."""
    src = _open_source(folder, name, what, unit_prefix)
    order = [(0, rot, led) for rot, led in src.units()]
    return _measure([src], order, cam, lamps, estimator, store, workers, progress, f"extract {Path(folder).name}",
                    solve=[(0, rot) for rot in src.man.rotations()])[0]


def measure_pair(sample_dir, reference_dir, cam: CameraCalibration, lamps: dict[int, np.ndarray] | None,
                 estimator: str = "ml", progress: bool = False, what: str = "extract", store=None,
                 workers: int | None = None) -> tuple[Measured, Measured]:
    """A sample and its diffuse reference measured as :func:`measure_capture` measures each, in one
    pool: the reference only in the sample's (rotation, LED) units - the ones eq. 4.78 divides by
    (:func:`diffuse_normalize`); a reference unit of another rotation or LED is not read - and each
    reference unit :data:`REFERENCE_LAG` sample units after its own (:func:`_paired_order`), so the
    reference's geometry is solved beside the sample's units instead of after them (two
    :func:`measure_capture` calls idle a worker through each geometry, and measured the reference's
    other rotations for nothing: on a scale-0.25, 8-LED capture of one rotation against a reference of
    two, diagnose's measurement took 25-32 s instead of 43-48 s, validation/diagnose/speed_benchmark.md).
    The tables are those two calls would give, the reference's restricted to the sample's units;
    the units are kept in ``store`` under the names ``sample-...`` and ``reference-...``
    (:func:`unit_name`). Captures :func:`check_compatible` refuses (a reference of another rig, or one
    that lacks a unit of the sample) stop here, before anything is measured."""
    ms, mr = _manifest(sample_dir), _manifest(reference_dir)
    check_compatible(ms, mr, what)
    sources = [_open_source(ms, "SAMPLE_DIR", what, "sample-"), _open_source(mr, "REF_DIR", what, "reference-")]
    order = _paired_order(sources[0].units(), REFERENCE_LAG)
    a, b = _measure(sources, order, cam, lamps, estimator, store, workers, progress,
                    f"extract {ms.folder.name} + {mr.folder.name}", solve=[(0, rot) for rot in ms.rotations()])
    return a, b


def _measure(sources: list[_Source], order, cam: CameraCalibration, lamps, estimator: str, store,
             workers: int | None, progress: bool, desc: str, solve) -> list[Measured]:
    """The units ``order`` of ``sources`` measured in one pool (:func:`_measured_units`): one
    :class:`Measured` per source, its units concatenated in its plan order (:func:`capture_units`)
    whatever the order they were measured in, its geometries those solved for it."""
    from tqdm import tqdm

    bar = tqdm(total=len(order), desc=desc, unit="LED", disable=not progress_enabled(progress))
    geoms: dict = {}
    with _pool(workers, len(order)) as pool:
        tables = list(_measured_units(pool, sources, order, cam, lamps, estimator, store, geoms, bar, solve=solve))
    bar.close()
    got = {job: df for job, df in zip(order, tables)}
    return [Measured(pd.concat([got[(i, rot, led)] for rot, led in src.units() if (i, rot, led) in got],
                               ignore_index=True),
                     str(src.man.rig_path()), {rot: g for (j, rot), g in geoms.items() if j == i})
            for i, src in enumerate(sources)]


def _dirs(df: pd.DataFrame) -> np.ndarray:
    return np.concatenate([local_direction(df.theta_in.to_numpy(), df.phi_in.to_numpy()),
                           local_direction(df.theta_out.to_numpy(), df.phi_out.to_numpy())], axis=1)


def diffuse_normalize(sample: pd.DataFrame, reference: pd.DataFrame, albedo: float = 0.8,
                      max_distance: float = 0.02) -> pd.DataFrame:
    """BRDF values by division with the reference (thesis eq. 4.78):
    f = (albedo / pi) * S / R at the reference's nearest geometry in the same
    (LED, rotation). Rows whose nearest reference sample is farther than
    ``max_distance`` (chord length of the unit directions, ~1 degree) are dropped.

    Per-channel validity (:mod:`glossrig.core.samples`): a channel is NaN where the
    sample's or the reference's value is missing (or the reference's is not positive);
    a row is kept while it has one channel. ``weight_<c>`` is the inverse variance of
    channel c's BRDF value (NaN where missing) and ``weight`` their mean over the row's
    valid channels, all divided by the mean of ``weight``. The reference's
    ``status_<c>`` / ``fix_s_<c>`` come along as ``ref_status_<c>`` / ``ref_fix_s_<c>``
    where the reference table has them (:mod:`glossrig.core.extraction.dynamic_range`).
    Each (LED, rotation) is :func:`normalize_unit`; :func:`extract_samples` streams them."""
    _check_albedo(albedo)
    out = []
    for (led, rot), s in sample.groupby(["led", "rotation"], sort=True):
        r = reference[(reference.led == led) & (reference.rotation == rot)]
        if r.empty:
            raise InputError(f"the reference capture has no LED {led} at rotation {rot:g} deg")
        out.append(normalize_unit(s, r, albedo, max_distance))
    res = pd.concat(out, ignore_index=True)
    return scale_weights(kept_rows(res))


def _check_albedo(albedo: float) -> None:
    if not (0 < albedo <= 1):
        raise InputError(f"reference albedo must lie in (0, 1], got {albedo}")


def normalize_unit(s: pd.DataFrame, r: pd.DataFrame, albedo: float = 0.8, max_distance: float = 0.02) -> pd.DataFrame:
    """:func:`diffuse_normalize` of one (LED, rotation): the sample's rows ``s`` divided by
    the reference's ``r`` at the nearest geometry (KD-tree), before :func:`kept_rows` and
    :func:`scale_weights`. Rows are independent, so both can follow per unit or on the
    concatenation alike."""
    from scipy.spatial import cKDTree

    tree = cKDTree(_dirs(r))
    d, idx = tree.query(_dirs(s))
    keep = d <= max_distance
    s = s[keep].copy()
    rr = r.iloc[idx[keep]]
    w = np.zeros(len(s))
    nw = np.zeros(len(s))
    for c in "rgb":
        R = rr[c].to_numpy()
        S = s[c].to_numpy()
        ok = R > 0          # False for a NaN reference value too
        with np.errstate(invalid="ignore"):
            f = np.where(ok, albedo / np.pi * S / np.where(ok, R, 1.0), np.nan)
            # relative variance of a ratio: var(S)/S^2 + var(R)/R^2
            rel = (s[f"var_{c}"].to_numpy() / np.maximum(S, 1e-12) ** 2
                   + rr[f"var_{c}"].to_numpy() / np.maximum(R, 1e-12) ** 2)
            wc = 1.0 / np.maximum(rel * f ** 2, 1e-30)
        s[c] = f
        s[f"weight_{c}"] = wc                       # NaN where the channel is missing
        valid = np.isfinite(f) & np.isfinite(wc)
        w += np.where(valid, wc, 0.0)
        nw += valid
        for k in (f"status_{c}", f"fix_s_{c}"):
            if k in rr:
                s[f"ref_{k}"] = rr[k].to_numpy()
    with np.errstate(invalid="ignore", divide="ignore"):
        s["weight"] = w / nw
    return s


def kept_rows(res: pd.DataFrame) -> pd.DataFrame:
    """The rows of :func:`normalize_unit` output that are samples: one valid channel at
    least (not all three), both directions above the surface."""
    res = res[np.isfinite(res[["r", "g", "b"]]).any(axis=1)]       # a row needs one channel, not all three
    good = (res.theta_in < np.pi / 2) & (res.theta_out < np.pi / 2)
    return res[good].copy()


def scale_weights(res: pd.DataFrame) -> pd.DataFrame:
    """Divide ``weight`` and ``weight_<c>`` by the mean ``weight`` of all rows (in place; returned)."""
    scale = res["weight"].mean()
    for k in ("weight", "weight_r", "weight_g", "weight_b"):
        res[k] = res[k] / scale
    return res


def check_compatible(sample_dir, reference_dir, what: str = "extract") -> None:
    """Both captures must hold exposure sequences (not a checkerboard capture given by
    mistake: stopped here, before any image is read); a reference must come from the
    same rig and hold every (LED, rotation) of the sample. ``what``: the verb, for the
    error message. Each capture: its folder or its loaded :class:`Manifest`."""
    s, r = _manifest(sample_dir), _manifest(reference_dir)
    s.require_sequences(what, "SAMPLE_DIR")
    r.require_sequences(what, "REF_DIR")
    rs, rr = load_rig(s.rig_path()), load_rig(r.rig_path())
    if rs.name != rr.name or rs.raw != rr.raw:
        raise InputError(f"reference was captured with another rig ({rr.name!r} at {rr.path}) than the sample "
                         f"({rs.name!r} at {rs.path})", path=r.path)
    def pairs(m):
        return {(im.leds[0], im.rotation) for im in m.select("sequence")}
    missing = pairs(s) - pairs(r)
    if missing:
        miss = ", ".join(f"LED {l} at {rot:g} deg" for l, rot in sorted(missing))
        raise InputError(f"reference lacks sequences the sample has: {miss} (another rotation or LED set?)",
                         path=r.path)


def measurement_fingerprint(sample_dir, reference_dir, cam: CameraCalibration, lamps: dict[int, np.ndarray] | None,
                            files: dict | None = None, **options) -> dict:
    """What measuring a sample and a reference capture depends on
    (:func:`glossrig.core.checkpoint.fingerprint`): both manifests, the rig files they
    name, the camera calibration file, the lamp positions, ``options`` and any further
    input ``files`` (name -> path) of the caller's run. Each capture: its folder or its
    loaded :class:`Manifest`."""
    from glossrig.core.checkpoint import fingerprint

    ms, mr = _manifest(sample_dir), _manifest(reference_dir)
    lp = None if lamps is None else {str(k): np.asarray(v, float).tolist() for k, v in sorted(lamps.items())}
    return fingerprint(files={"camera": cam.path or None, "sample_rig": ms.rig_path(), "reference_rig": mr.rig_path(),
                              **(files or {})},
                       captures={"sample": ms.folder, "reference": mr.folder},
                       options={**options, "lamps_mm": lp, "block_footprint_half_px": BLOCK_FOOTPRINT_HALF_PX})


#: the samples table's columns (:mod:`glossrig.core.samples`), in order
SAMPLE_COLUMNS = list(COLUMNS) + list(CHANNEL_WEIGHT_COLUMNS)
_PLOT_COLUMNS = ["u", "v", "rotation", "led", "r", "g", "b"]      # what extract_plots reads of the measured sample


def extract_samples(sample_dir, reference_dir, cam: CameraCalibration, lamps: dict[int, np.ndarray],
                    albedo: float = 0.8, estimator: str = "ml", progress: bool = False, plots=None,
                    store=None, workers: int | None = None) -> pd.DataFrame:
    """The full extraction: sample and reference measured alike, then divided (eq. 4.78).
    ``sample_dir``, ``reference_dir``: the captures' folders or their loaded manifests.

    ``store``: a :class:`glossrig.core.checkpoint.WorkStore` fingerprinted with
    :func:`measurement_fingerprint` (and the estimator); every finished LED of either
    capture is kept there and reused, so an interrupted extraction resumes.

    ``workers``: processes measuring (rotation, LED) units at once (None: every usable
    core, :func:`glossrig.core.workers.usable_cores`; 1: all in this process). Streamed:
    each unit of the sample is measured next to the reference's (:data:`REFERENCE_LAG`
    units ahead of it), the pair is divided as soon as both are measured
    (:func:`normalize_unit`), its dynamic-range report made and only the samples' columns
    kept, so memory holds the output table plus a few units at a time whatever the number
    of LEDs, not both captures' full tables. The table (rows sorted by LED, then rotation,
    as :func:`diffuse_normalize` sorts them) is the same for any number of workers."""
    from tqdm import tqdm

    from glossrig.core.extraction.dynamic_range import dynamic_range_report, log_dynamic_range, merge_reports

    _check_albedo(albedo)
    ms, mr = _manifest(sample_dir), _manifest(reference_dir)        # each read once, here
    check_compatible(ms, mr)
    sources = [_open_source(ms, "SAMPLE_DIR", "extract", "sample-"),
               _open_source(mr, "REF_DIR", "extract", "reference-")]
    s_units = sources[0].units()
    extra = [u for u in sources[1].units() if u not in set(s_units)]
    order = _paired_order(s_units, REFERENCE_LAG) + [(1, rot, led) for rot, led in extra]
    exposures = {"sample": _exposures(ms), "reference": _exposures(mr)}
    bar = tqdm(total=len(order), desc=f"extract {ms.folder.name} + {mr.folder.name}", unit="LED",
               disable=not progress_enabled(progress))
    chunks: dict = {}         # (led, rotation) -> that unit's samples
    parts: dict = {}          # (capture, rotation, led) -> its dynamic-range report
    plotted = []
    held: dict = {}
    geoms: dict = {}          # (capture, rotation) -> RotationGeometry, as _measured_units solves them
    with _pool(workers, len(order)) as pool:
        # the sample's geometries are solved even where a resumed extraction's store holds every unit of a
        # rotation: the table records their poses (recorded_geometry), as an uninterrupted run's does
        units = _measured_units(pool, sources, order, cam, lamps, estimator, store, geoms, bar,
                                solve=[(0, rot) for rot in dict.fromkeys(rot for rot, _ in s_units)])
        for (i, rot, led), df in zip(order, units):
            if i == 0:
                held[(rot, led)] = df
                if plots is not None:
                    plotted.append(df[_PLOT_COLUMNS])
                continue
            s = held.pop((rot, led), None)
            if s is None:                # a reference unit the sample lacks: reported, not divided
                parts[("reference", rot, led)] = dynamic_range_report(None, df, df.iloc[:0], exposures)
                continue
            out = kept_rows(normalize_unit(s, df, albedo))
            parts[("sample", rot, led)] = dynamic_range_report(s, None, out, exposures)
            parts[("reference", rot, led)] = dynamic_range_report(None, df, out.iloc[:0], exposures)
            chunks[(led, rot)] = out[SAMPLE_COLUMNS]
            del s, df, out
            release_memory()
    bar.close()
    res = scale_weights(pd.concat([chunks[k] for k in sorted(chunks)], ignore_index=True))
    # which channels ran out of dynamic range, where, and what exposure would have fixed it
    report = merge_reports([parts[k] for k in sorted(parts, key=lambda k: (k[0] != "sample", k[1], k[2]))])
    log_dynamic_range(report)
    res.attrs["dynamic_range"] = report
    # the sample's poses, for the fit's calibration draws (calibration_uncertainty.recorded_poses)
    res.attrs["poses"] = recorded_geometry(ms, cam, {rot: g.poses for (i, rot), g in geoms.items() if i == 0})
    if plots is not None:
        from glossrig.core.extraction.dynamic_range import write_dynamic_range
        from glossrig.core.extraction.extract_plots import write_plots

        write_plots(Path(plots), pd.concat(plotted, ignore_index=True), res)
        write_dynamic_range(Path(plots), report, res)
    return res


def recorded_geometry(man: Manifest, cam: CameraCalibration, poses: dict) -> dict | None:
    """The sample capture's solved poses (:func:`glossrig.core.calibration.poses.calibrate_capture`'s
    result per rotation, JSON-ready) with what they were solved from: the sha256 of the camera.json
    and of the capture's rig file (the marker corners the draws pair with the image corners come
    from it; the calibration images' own sha256 are in each result). ``glossrig extract`` stores it
    in the samples table (:func:`glossrig.core.samples.write_samples`) so that ``glossrig fit``'s
    calibration draws start from the poses the table was measured with instead of solving them
    again from the capture (:func:`glossrig.core.fitting.calibration_uncertainty.recorded_poses`;
    the solve was more than half of the calibration component's CPU time,
    validation/uncertainty_coverage.md, section 4). :func:`extract_samples` (also under
    ``--follow``) always solves the sample's geometries, also when a resumed extraction's store
    holds every unit, so that a resumed table records what an uninterrupted one does."""
    from glossrig.core.capture import sha256_file
    from glossrig.core.calibration.poses import geometry_to_json

    have = {float(r): p for r, p in poses.items() if p is not None}
    if not have or not cam.path:
        return None
    return {"camera_sha256": sha256_file(cam.path), "rig_sha256": sha256_file(man.rig_path()),
            "per_rotation": {repr(r): finite_json(geometry_to_json(p)) for r, p in sorted(have.items())}}


def finite_json(obj):
    """``obj`` (JSON-ready) with every non-finite float as None: strict JSON (a pose's edge-fit
    std is NaN where the fit could not state one; :func:`calibration_uncertainty.rotation_poses`
    reads None back as NaN)."""
    if isinstance(obj, dict):
        return {k: finite_json(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [finite_json(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


#: how many sample units are measured beyond a unit before its reference unit
#: (:func:`_paired_order`). With 1 the jobs run s1 s2 r1 s3 r2 ...: the reference's geometry,
#: solved once the sample's is, runs beside s1 and s2 (a full-resolution geometry takes about
#: two units' time) instead of beside a worker idling until r1 may start (issue 19)
REFERENCE_LAG = 1


def _paired_order(units: list[tuple[float, int]], lag: int) -> list[tuple[int, float, int]]:
    """(capture, rotation, LED) jobs of a sample (capture 0) and reference (capture 1) with the
    same ``units``: each sample unit, and each reference unit ``lag`` sample units after its
    own sample unit (always after it: :func:`extract_samples` divides a pair as its reference
    arrives)."""
    order = []
    for k, (rot, led) in enumerate(units):
        order.append((0, rot, led))
        if k >= lag:
            order.append((1, *units[k - lag]))
    order += [(1, rot, led) for rot, led in units[max(0, len(units) - lag):]]
    return order


def _exposures(man: Manifest) -> list[float]:
    """The exposure times (s) of a capture's sequences, shortest first."""
    return sorted({float(im.exposure_s) for im in man.select("sequence")})
