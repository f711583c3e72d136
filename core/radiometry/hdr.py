"""Radiometric calibration of one exposure sequence (thesis 4.3.3, eq. 4.31-4.44).

The extraction stage calls this once per (sample rotation, LED) on cropped,
linearised CFA mosaics (thesis eq. 4.1-4.2, :func:`glossrig.core.calibration.raw.linearize`).
Nothing is demosaiced: every pixel keeps its own CFA colour (thesis 4.3.2,
"We do not need to demosaic the sequence images"), and every function here is
pixel-wise, so the CFA layout only matters for patch normalisation
(:mod:`glossrig.core.radiometry.patch`).

Steps, with the thesis equation each implements and where it departs:

1. :func:`combine_repeats` - eq. 4.31, the mean of the m repeats of each
   exposure. Also records which (exposure, pixel) had a saturated repeat;
   the mean of partly clipped repeats lies below 1 and would otherwise pass
   for a valid value. :func:`stack_frames` builds the stack from
   :class:`~glossrig.core.calibration.raw.RawFrame` objects and refuses sequences whose
   repeats disagree.
2. :func:`neighbour_correct` - eq. 4.32-4.38, removal of the LED's
   frame-to-frame intensity jitter by forcing neighbouring exposures to the
   ratio of their exposure times, from the centre of the sequence outwards.
   The printed correction factor (eq. 4.36) has the wrong sign of the
   exponent: see the function's docstring for the algebra.
3. :func:`hdr_thesis` - eq. 4.39-4.44 as printed: unweighted straight-line fit
   of value against exposure time over the unclipped exposures, sampled at
   1 s, 0 when fewer than 4 exposures are valid.
   :func:`hdr_ml` - the estimator this project uses: the (quasi-)maximum
   likelihood rate of a linear sensor with shot and read noise, i.e. an
   inverse-variance weighted fit through the origin, which for pure shot
   noise is ``sum(y) / sum(t)``; the valid exposures are chosen from the
   estimated expected value, not from the noisy samples.

Units: linearised values are fractions of the white-black range (0..1); HDR
rates are that fraction per second of exposure (the thesis's "sample at
exposure 1 s"), variances their squares.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from glossrig.core.errors import InputError

__all__ = [
    "NoiseModel", "ExposureStack", "NeighbourReport", "HdrResult",
    "combine_repeats", "stack_frames", "stream_stack", "neighbour_correct", "hdr_thesis", "hdr_ml", "hdr_from_stack",
    "VALID", "TOO_DARK", "TOO_BRIGHT", "TOO_FEW", "STATUS_REASONS", "LO", "HI", "exposure_to_fix",
]

#: Status codes of :class:`HdrResult` (``status`` array); NaN rate for all but VALID.
VALID, TOO_DARK, TOO_BRIGHT, TOO_FEW = 0, 1, 2, 3
STATUS_REASONS = {
    VALID: "valid",
    TOO_DARK: "too dark: even at the longest exposure the expected value is below the lower limit "
              "(shot and read noise dominate, and linearisation clips negative values at 0)",
    TOO_BRIGHT: "too bright: saturated, or expected above the upper limit, even at the shortest exposure",
    TOO_FEW: "fewer valid exposures than min_valid",
}

#: :func:`hdr_ml`'s default validity window of an exposure's expected value (fractions of
#: the white-black range): the noise floor ``LO`` and the top ``HI`` (see hdr_ml).
LO, HI = 0.002, 0.95

#: Pixels per block in :func:`hdr_thesis` (bounds the (n, block) float64 temporaries).
_BLOCK = 1 << 17
#: Pixels per block in :func:`hdr_ml`: its (n, block) float32 temporaries (1.2 MB for 18
#: exposures) stay in the processor's cache through the iterations.
_ML_BLOCK = 1 << 14


# ------------------------------------------------------------------ noise model

@dataclass(frozen=True)
class NoiseModel:
    """Temporal noise of one linearised frame, in units of the white-black range.

    A photon-transfer model (EMVA 1288 release 4.0, eq. 7; Janesick, "Photon
    Transfer", 2007): a frame of expected value ``y`` (0..1) has variance
    ``y / electrons_full_scale + read_sigma**2``; ``electrons_full_scale`` is
    the number of photo-electrons that fill the white-black range (the
    inverse of the shot-noise slope) and ``read_sigma`` is read plus
    quantisation noise. The mean of m repeats has 1/m of that variance.
    The thesis has no noise model; it is what makes :func:`hdr_ml` weight
    the exposures correctly.
    """

    electrons_full_scale: float
    read_sigma: float

    def __post_init__(self):
        if not (math.isfinite(self.electrons_full_scale) and self.electrons_full_scale > 0):
            raise InputError(f"NoiseModel: electrons_full_scale must be > 0, got {self.electrons_full_scale!r}")
        if not (math.isfinite(self.read_sigma) and self.read_sigma >= 0):
            raise InputError(f"NoiseModel: read_sigma must be >= 0, got {self.read_sigma!r}")

    @classmethod
    def from_sensor(cls, *, white: float, black, iso: float, electrons_per_dn_iso100: float,
                    read_noise_e: float) -> NoiseModel:
        """From sensor figures: conversion gain K = electrons_per_dn_iso100 *
        100 / ISO (e-/DN), range R = white - mean(black) DN; then
        electrons_full_scale = R K and read_sigma = sqrt((read_noise_e/K)^2 +
        1/12) / R (the 1/12 DN^2 is the rounding to integer DN)."""
        black = float(np.mean(np.asarray(black, float)))
        rng = float(white) - black
        if not rng > 0:
            raise InputError(f"NoiseModel: white level {white} must exceed the black level {black}")
        if not (iso > 0 and electrons_per_dn_iso100 > 0 and read_noise_e >= 0):
            raise InputError(f"NoiseModel: need ISO > 0, electrons_per_dn_iso100 > 0, read_noise_e >= 0; got "
                             f"{iso}, {electrons_per_dn_iso100}, {read_noise_e}")
        k = electrons_per_dn_iso100 * 100.0 / float(iso)
        return cls(electrons_full_scale=rng * k, read_sigma=math.sqrt((read_noise_e / k) ** 2 + 1.0 / 12.0) / rng)

    @classmethod
    def from_rig(cls, rig, iso: float | None = None) -> NoiseModel:
        """From a :class:`glossrig.core.rig.Rig`: its ``[camera]`` levels and
        ``[sensor]`` figures, at ``iso`` (default: the rig's sequence ISO)."""
        return cls.from_sensor(white=rig.camera.white_level, black=rig.camera.black_level,
                               iso=rig.sequence_iso if iso is None else iso,
                               electrons_per_dn_iso100=rig.sensor.electrons_per_dn_iso100,
                               read_noise_e=rig.sensor.read_noise_e)

    def variance(self, value, repeats: int = 1):
        """Variance of the mean of ``repeats`` frames of expected ``value``."""
        v = np.maximum(np.asarray(value, float), 0.0)
        return (v / self.electrons_full_scale + self.read_sigma ** 2) / repeats


# ------------------------------------------------------------ eq. 4.31

@dataclass
class ExposureStack:
    """One combined exposure sequence (thesis SI^comb, eq. 4.31).

    ``images`` float32 (n, H, W): per exposure, the mean of the repeats of
    the linearised mosaic; ``exposure_s`` float64 (n,), strictly increasing;
    ``clipped`` bool (n, H, W): some repeat was saturated there; ``repeats``
    m; ``cfa`` the 2x2 colour indices of ``images[:, 0:2, 0:2]`` (None when
    unknown); ``files[k]`` the raw files of exposure k (for messages).
    """

    images: np.ndarray
    exposure_s: np.ndarray
    clipped: np.ndarray
    repeats: int
    cfa: np.ndarray | None = None
    files: list[list[str]] = field(default_factory=list)

    def ends(self) -> ExposureStack:
        """A copy of the exposures :func:`exposure_to_fix` reads (the shortest and the two
        longest) as a stack of its own: what it needs of a stack that
        :func:`hdr_from_stack` is about to correct in place (``overwrite``)."""
        n = self.exposure_s.size
        k = sorted({0, max(0, n - 2), n - 1})
        return ExposureStack(images=self.images[k], exposure_s=self.exposure_s[k], clipped=self.clipped[k],
                             repeats=self.repeats, cfa=self.cfa, files=[self.files[i] for i in k] if self.files else [])


def _check_finite(a: np.ndarray, what: str) -> None:
    # one (H, W) image at a time: no mask the size of a whole stack
    for k in range(a.shape[0] if a.ndim > 2 else 1):
        part = a[k] if a.ndim > 2 else a
        if part.size and not np.isfinite(part).all():
            bad = np.argwhere(~np.isfinite(a))[0]
            raise InputError(f"{what} holds NaN or infinite values (first at index {tuple(int(i) for i in bad)})")


def combine_repeats(linear, *, saturation: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Thesis eq. 4.31: SI^comb_n = (1/m) sum_i SI^lin_{i,n} - the mean of
    the m repeats of every exposure.

    ``linear``: the m repeats, each (n, H, W) linearised mosaics (exposure, row,
    column), values in units of the white-black range: an (m, n, H, W) array, or any
    iterable of (n, H, W) arrays (a generator that linearises each repeat only when it is
    asked for). Returns ``(combined, clipped)``: float32 (n, H, W) means, and bool
    (n, H, W) marking where at least one repeat reached ``saturation`` (1.0 after
    :func:`~glossrig.core.calibration.raw.linearize`, which maps every value at or above
    the white level to exactly 1). Addition to the thesis: the thesis tests
    saturation on the mean (eq. 4.39, ``< 1``), which lets a mean of partly
    clipped repeats through as if it were a true value.

    The repeats are taken one at a time (issue 19: a worker's memory), so memory is one
    repeat and the accumulators: a float64 running sum, added in repeat order, divided by
    m and rounded once to float32 (numpy's float64 mean over axis 0 of a C-ordered
    (m, n, H, W) stack adds in the same order, so the values are the same bit for bit),
    and the saturation mask. No (m, n, H, W) array or mask is made.
    """
    whole = isinstance(linear, np.ndarray)
    if whole and linear.ndim != 4:
        raise InputError(f"combine_repeats expects (repeats, exposures, H, W) linear mosaics, got shape {linear.shape}")
    if whole and min(linear.shape) < 1:
        raise InputError(f"combine_repeats: empty input of shape {linear.shape}")
    total, clipped = np.zeros(0), np.zeros(0, bool)        # sized by the first repeat
    m = 0
    for rep in linear:              # not enumerate: its reused result tuple would hold the last repeat
        r = np.asarray(rep)
        del rep
        if m == 0:
            if r.ndim != 3:
                raise InputError(f"combine_repeats expects repeats of (exposures, H, W) linear mosaics, got shape "
                                 f"{r.shape}")
            if min(r.shape) < 1:
                raise InputError(f"combine_repeats: empty repeat of shape {r.shape}")
            total, clipped = np.zeros(r.shape, np.float64), np.zeros(r.shape, bool)
        elif r.shape != total.shape:
            raise InputError(f"combine_repeats: repeat {m} has shape {r.shape}, repeat 0 {total.shape}; all "
                             f"repeats must have one shape")
        if not np.issubdtype(r.dtype, np.floating):
            raise InputError(f"combine_repeats expects linearised float values, got {r.dtype} (linearize the raw "
                             f"mosaics first, glossrig.core.calibration.raw.linearize)")
        _check_finite(r, f"linear images (repeat {m})")
        total += r
        clipped |= r >= saturation
        m += 1
        del r                       # one repeat in memory while the next one is made
    if m == 0:
        raise InputError("combine_repeats: no repeats given")
    total /= m
    return total.astype(np.float32), clipped


def _same(x, y) -> bool:
    if x is None or y is None:
        return x is y
    return bool(np.array_equal(np.asarray(x), np.asarray(y)))


def _check_alike(f, f0, shape0: tuple[int, ...]) -> None:
    """Frame ``f`` must share crop (``shape0``: the mosaic shape of ``f0``, whose pixels may have
    been released), CFA, levels, ISO and f-number with the sequence's first ``f0``."""
    for name, x, y in (("crop size", f.mosaic.shape, shape0), ("crop origin", f.origin, f0.origin),
                       ("CFA pattern", f.cfa, f0.cfa), ("black levels", f.black, f0.black),
                       ("white level", f.white, f0.white), ("ISO", f.iso, f0.iso),
                       ("f-number", f.aperture, f0.aperture)):
        if not _same(x, y):
            raise InputError(f"{name} {np.asarray(x).tolist() if x is not None else None} differs from "
                             f"{np.asarray(y).tolist() if y is not None else None} of {f0.path}; all frames "
                             f"of a sequence must share it", path=f.path)


def _match(t: float, table: np.ndarray, rel_tol: float) -> int:
    """Index of the exposure of ``table`` that ``t`` matches within ``rel_tol``, else -1."""
    k = int(np.argmin(np.abs(table - t)))
    return k if abs(table[k] - t) <= rel_tol * max(t, table[k]) else -1


def _exposure_slots(exposures: Sequence[float], paths: Sequence[str], repeats: Sequence[int],
                    exposures_s: Sequence[float] | None, rel_tol: float
                    ) -> tuple[np.ndarray, str, list[int], dict[int, list[int]]]:
    """The exposure table of a sequence and, per repeat, the item (index) of each of its
    exposures (:func:`stack_frames`' checks): ``(table, where the table comes from, repeats,
    slots)``. Item i has exposure ``exposures[i]``, file ``paths[i]`` and repeat ``repeats[i]``."""
    by_rep: dict[int, list[int]] = {}
    for i, r in enumerate(repeats):
        by_rep.setdefault(r, []).append(i)
    reps = sorted(by_rep)
    if exposures_s is not None:
        table = np.asarray(exposures_s, float)
        if table.ndim != 1 or table.size == 0 or not np.all(table > 0) or np.any(np.diff(table) <= 0):
            raise InputError(f"exposure table must be positive and strictly increasing, got {table.tolist()}")
        table_src = "the exposure table"
    else:
        table = np.array(sorted(exposures[i] for i in by_rep[reps[0]]), float)
        table_src = f"repeat {reps[0]}"
    n = table.size
    slots: dict[int, list] = {}
    for r in reps:
        slot: list = [None] * n
        for i in by_rep[r]:
            k = _match(exposures[i], table, rel_tol)
            if k < 0:
                near = table[int(np.argmin(np.abs(table - exposures[i])))]
                raise InputError(f"exposure {exposures[i]:g} s (repeat {r}) matches no exposure of {table_src} "
                                 f"(nearest {near:g} s); the repeats of a sequence disagree", path=paths[i])
            if slot[k] is not None:
                raise InputError(f"repeat {r} has exposure {table[k]:g} s twice (also {paths[slot[k]]})",
                                 path=paths[i])
            slot[k] = i
        slots[r] = slot
    for r in reps:
        missing = [k for k in range(n) if slots[r][k] is None]
        if missing:
            k = missing[0]
            other = next((slots[q][k] for q in reps if slots[q][k] is not None), None)
            where = paths[other] if other is not None else paths[by_rep[r][0]]
            note = (" (this file is that exposure in another repeat)" if other is not None else
                    " (no repeat has it; this is the repeat's first file)")
            raise InputError(f"repeat {r} lacks exposure(s) {', '.join(f'{table[j]:g} s' for j in missing)} of "
                             f"{table_src}{note}; the sequence is incomplete", path=where)
    return table, table_src, reps, slots


def stack_frames(frames: Sequence, repeats: Sequence[int], *, exposures_s: Sequence[float] | None = None,
                 rel_tol: float = 1e-3) -> ExposureStack:
    """Combine the raw frames of one (rotation, LED) sequence (thesis eq. 4.31).

    ``frames``: :class:`~glossrig.core.calibration.raw.RawFrame` objects (cropped alike),
    in any order; ``repeats[i]`` the repeat index of ``frames[i]`` (from the
    capture manifest). Every repeat must hold the same exposures (matched
    within ``rel_tol``), each once; when ``exposures_s`` (the rig's exposure
    table) is given, those exactly. All frames must share crop, CFA, black
    and white levels, ISO and f-number. Anything else is an
    :class:`InputError` naming the offending file: a missing exposure, an
    exposure that matches none of another repeat's, a duplicate, a
    different crop or ISO.

    Linearisation (eq. 4.1-4.2) and the mean of the repeats (eq. 4.31) are done in one
    pass per exposure on the integer raw values
    (:func:`glossrig.core.calibration.raw.linearize_mean`: exact integer sums, one float32
    rounding, within one float32 ulp of linearising each frame and then
    :func:`combine_repeats`; error budget there). The frames are left as they are;
    :func:`stream_stack` makes the same stack reading each frame only when its exposure
    is combined.
    """
    frames = list(frames)
    repeats = [int(r) for r in repeats]
    if not frames:
        raise InputError("stack_frames: no frames given")
    if len(repeats) != len(frames):
        raise InputError(f"stack_frames: {len(frames)} frames but {len(repeats)} repeat indices")
    for f in frames[1:]:
        _check_alike(f, frames[0], frames[0].mosaic.shape)
    return _stack(frames.__getitem__, [f.exposure_s for f in frames], [f.path for f in frames], repeats,
                  exposures_s, rel_tol, release=False, prefetch=False)


def stream_stack(read: Callable[[int], Any], exposures: Sequence[float], paths: Sequence[str],
                 repeats: Sequence[int], *, exposures_s: Sequence[float] | None = None, rel_tol: float = 1e-3,
                 prefetch: bool = True) -> ExposureStack:
    """:func:`stack_frames` of a sequence whose frames are read one exposure at a time:
    ``read(i)`` returns frame i (a :class:`~glossrig.core.calibration.raw.RawFrame`), whose
    file is ``paths[i]``, repeat ``repeats[i]`` and expected exposure ``exposures[i]`` (s;
    the capture manifest's). The frames are grouped by those exposures (the checks of
    :func:`stack_frames`, before any file is read); each group's frames are read, checked
    alike (their files' exposures agreeing within ``rel_tol``), combined and dropped, so only
    the stack and one exposure's frames are in memory (issue 19: a worker's memory) and
    never the whole sequence's. The stack's exposure times are the files' (the first
    repeat's), as in :func:`stack_frames`. ``prefetch``: the next exposure's frames are
    read in a thread while this one is combined (reading and checksums overlap the
    arithmetic; both release the GIL)."""
    repeats = [int(r) for r in repeats]
    if not len(exposures):
        raise InputError("stream_stack: no frames given")
    if not len(exposures) == len(paths) == len(repeats):
        raise InputError(f"stream_stack: {len(exposures)} exposures, {len(paths)} files and {len(repeats)} "
                         "repeat indices")
    return _stack(read, [float(e) for e in exposures], [str(p) for p in paths], repeats, exposures_s, rel_tol,
                  release=True, prefetch=prefetch)


def _stack(read: Callable[[int], Any], exposures: list[float], paths: list[str], repeats: list[int],
           exposures_s: Sequence[float] | None, rel_tol: float, release: bool, prefetch: bool) -> ExposureStack:
    """The stack of :func:`stack_frames` / :func:`stream_stack`: frames grouped by exposure,
    each group read (``read``), checked, linearised and averaged (eq. 4.1-4.2, 4.31)."""
    from concurrent.futures import ThreadPoolExecutor
    from contextlib import nullcontext

    from glossrig.core.calibration.raw import linearize_mean

    table, table_src, reps, slots = _exposure_slots(exposures, paths, repeats, exposures_s, rel_tol)
    n = table.size

    def group(k: int) -> list:
        return [read(slots[r][k]) for r in reps]

    combined, clipped = np.empty((0, 0, 0), np.float32), np.empty((0, 0, 0), bool)    # sized by the first frame
    first = None
    files: list[list[str]] = []
    file_t = np.empty(n)
    with ThreadPoolExecutor(1) if prefetch else nullcontext() as pool:
        nxt = pool.submit(group, 0) if pool is not None else None
        for k in range(n):
            fr = nxt.result() if nxt is not None else group(k)
            if pool is not None and k + 1 < n:
                nxt = pool.submit(group, k + 1)
            if first is None:
                first = fr[0]
                shape0 = (h, w) = first.mosaic.shape
                combined, clipped = np.empty((n, h, w), np.float32), np.empty((n, h, w), bool)
            file_t[k] = fr[0].exposure_s       # the file's exposure (read_raw checked it against the manifest's)
            for f in fr:
                _check_alike(f, first, shape0)
                if _match(f.exposure_s, file_t[k:k + 1], rel_tol) < 0:
                    raise InputError(f"exposure {f.exposure_s:g} s in the file does not match {file_t[k]:g} s of "
                                     f"{fr[0].path} (repeat {reps[0]}); the repeats of a sequence disagree",
                                     path=f.path)
            # eq. 4.1-4.2 and 4.31 in one pass per exposure (linearize_mean: error budget)
            combined[k], clipped[k] = linearize_mean([f.mosaic for f in fr], first.black, first.white)
            files.append([f.path for f in fr])
            if release:
                for f in fr:
                    f.mosaic = np.empty((0, 0), f.mosaic.dtype)
            del fr
    assert first is not None
    t = table.copy() if exposures_s is not None else file_t
    if np.any(np.diff(t) <= 0):
        raise InputError(f"the files' exposure times {t.tolist()} are not increasing in the order of {table_src}",
                         path=files[0][0])
    return ExposureStack(images=combined, exposure_s=t, clipped=clipped, repeats=len(reps),
                         cfa=np.asarray(first.cfa).copy(), files=files)


def _check_stack(images, exposure_s, clipped=None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    y = np.asarray(images)
    t = np.asarray(exposure_s, float)
    if y.ndim != 3:
        raise InputError(f"expected (exposures, H, W) images, got shape {y.shape}")
    if not np.issubdtype(y.dtype, np.floating):
        raise InputError(f"expected linearised float images, got {y.dtype}")
    if t.ndim != 1 or t.size != y.shape[0]:
        raise InputError(f"{y.shape[0]} images but exposure times of shape {t.shape}")
    if not np.all(np.isfinite(t)) or not np.all(t > 0):
        raise InputError(f"exposure times must be positive, got {t.tolist()}")
    if np.any(np.diff(t) <= 0):
        raise InputError(f"exposure times must be strictly increasing (sort the sequence; no duplicates), "
                         f"got {t.tolist()}")
    _check_finite(y, "images")
    if clipped is not None:
        clipped = np.asarray(clipped, bool)
        if clipped.shape != y.shape:
            raise InputError(f"clipped mask of shape {clipped.shape} does not match images {y.shape}")
    return y, t, clipped


# ------------------------------------------------------------ eq. 4.32-4.38

@dataclass
class NeighbourReport:
    """What :func:`neighbour_correct` did, per exposure k.

    ``factor[k]``: multiplier applied to image k (1 for the reference and
    for skipped images); ``partner[k]``: index of the image it was
    compared with (-1: reference or skipped); ``pixels[k]``: pixels used;
    ``reference``: index of the reference image; ``skipped``: images left
    uncorrected for lack of pixels.
    """

    reference: int
    factor: np.ndarray
    partner: np.ndarray
    pixels: np.ndarray
    skipped: list[int]


def _pairs_centre_out(n: int, ref: int) -> list[tuple[int, int]]:
    """Eq. 4.32 (read as intended): (i, i+1) for i = ref..n-2, then (i, i-1)
    for i = ref..1. The printed second set, (1, i-1), is a typo."""
    return [(i, i + 1) for i in range(ref, n - 1)] + [(i, i - 1) for i in range(ref, 0, -1)]


def _gain_ratio(out: np.ndarray, usable: np.ndarray, t: np.ndarray, a: int, b: int, step: int, lo: float, hi: float,
                min_pixels: int) -> tuple[float | None, int]:
    """Factor that brings image b to the LED gain of (corrected) image a, and
    the number of pixels it rests on (None if fewer than ``min_pixels``).

    Pixels are chosen where a third image q (next to a or b, outside the
    pair) predicts both values inside (lo, hi): q's noise is independent of
    a's and b's, so the choice does not favour pixels whose noise pushed
    them into the window, which biases a ratio by ~0.02 % per pair
    (compounding along the chain; tests/test_hdr.py). The ratio is
    sum(b) / sum(a) over those pixels after dropping pixels whose own
    ratio is more than 6 robust sigmas (1.4826 MAD) from the median ratio
    (hot pixels, a moving highlight): a mean of ratios is biased by
    E[1/x] > 1/E[x], a median of ratios by the ratio's skew.

    q is the image beyond a (towards the reference), else beyond b. When it
    leaves fewer than ``min_pixels`` - in a sparse exposure plan the longer
    neighbour saturates where the pair is well exposed (more than ~3x apart on
    both sides, :mod:`glossrig.core.radiometry.exposure_plan`) - the other one is tried,
    and then the longer image of the pair itself: choosing on one image's
    noise biases only its own sum, by second-order edge terms (measured:
    < 0.001 % for images 4x apart, single repeats), where choosing on both
    images' values biases the ratio by 0.1 % there. That link beats an image
    left with the LED's full frame-to-frame jitter (0.5 %).
    """
    n = out.shape[0]
    cnt_max = 0
    longer = a if t[a] > t[b] else b
    for q in [k for k in (a - step, b + step) if 0 <= k < n and k not in (a, b)] + [longer]:
        fac, cnt = _gain_ratio_with(out, usable, t, a, b, q, lo, hi, min_pixels)
        if fac is not None:
            return fac, cnt
        cnt_max = max(cnt_max, cnt)
    return None, cnt_max


def _scaled_bound(c: np.float32, bound: float, above: bool) -> np.float32:
    """The float32 threshold g on x for which ``x * c > bound`` (``above``) equals ``x > g``,
    or ``x * c < bound`` equals ``x < g``, for every float32 x, with the product rounded to
    float32 and compared as the array expression does. Rounding is monotone, so for c > 0
    the x that pass form a half-line; g is its last non-member (found from bound / c by a
    few ``nextafter`` steps). Saves a multiplication of the whole image per window test."""
    def passes(x) -> bool:
        p = np.array([x], np.float32) * c
        return bool((p > bound)[0] if above else (p < bound)[0])

    g = np.float32(bound / float(c))
    inf = np.float32(np.inf)
    if above:                    # the largest x that does not pass
        while passes(g):
            g = np.nextafter(g, -inf)
        while not passes(np.nextafter(g, inf)):
            g = np.nextafter(g, inf)
    else:                        # the smallest x that does not pass
        while passes(g):
            g = np.nextafter(g, inf)
        while not passes(np.nextafter(g, -inf)):
            g = np.nextafter(g, -inf)
    return g


def _gain_ratio_with(out, usable, t, a: int, b: int, q: int, lo: float, hi: float,
                     min_pixels: int) -> tuple[float | None, int]:
    """:func:`_gain_ratio` with pixels chosen by image ``q`` (a third image, or one of the pair):
    where q's value scaled to a's and b's exposures lies inside (lo, hi) (both scaled values'
    window tests as one interval of q's value, :func:`_scaled_bound`), no repeat of q, a or b
    is saturated (``usable``) and a's value is positive."""
    ca, cb = np.float32(t[a] / t[q]), np.float32(t[b] / t[q])
    lo_q = max(_scaled_bound(ca, lo, True), _scaled_bound(cb, lo, True))
    hi_q = min(_scaled_bound(ca, hi, False), _scaled_bound(cb, hi, False))
    sel = (out[q] > lo_q) & (out[q] < hi_q)
    sel &= usable[q]
    sel &= usable[a]
    sel &= usable[b]
    sel &= out[a] > 0
    cnt = int(np.count_nonzero(sel))
    if cnt < min_pixels:
        return None, cnt
    ya = out[a][sel].astype(np.float64)
    yb = out[b][sel].astype(np.float64)
    ratio = yb / ya
    med = np.median(ratio)
    mad = 1.4826 * np.median(np.abs(ratio - med))
    if mad > 0:
        inl = np.abs(ratio - med) <= 6.0 * mad
        ya, yb = ya[inl], yb[inl]
    cnt = int(ya.size)
    if cnt < min_pixels:
        return None, cnt
    rho = yb.sum() / ya.sum()
    return float((t[b] / t[a]) / rho), cnt                 # = R E_b / E_a: removes b's own gain


#: neighbour_correct's defaults: the value window of the pixels a gain ratio rests on, and
#: the fewest such pixels that make a link (the thesis's 100); the exposure planner
#: (:mod:`glossrig.core.radiometry.exposure_plan`) predicts the links with the same figures.
NEIGHBOUR_WINDOW = (0.1, 0.9)
NEIGHBOUR_MIN_PIXELS = 100


def neighbour_correct(images, exposure_s, *, clipped=None, method: str = "robust", lo: float = NEIGHBOUR_WINDOW[0],
                      hi: float = NEIGHBOUR_WINDOW[1], min_pixels: int = NEIGHBOUR_MIN_PIXELS,
                      reference: int | str = "centre", copy: bool = True
                      ) -> tuple[np.ndarray, NeighbourReport]:
    """Thesis "Neighbor correction" (eq. 4.32-4.38): remove the LED's
    frame-to-frame intensity jitter from a combined sequence.

    A linear sensor gives SI_k = g_k E_k L for exposure E_k, scene signal L
    and the LED's (unknown) relative output g_k in frame k. Going from the
    reference image outwards (eq. 4.32), each image b is scaled so that its
    ratio to its already corrected neighbour a equals E_b / E_a; then every
    image carries the reference frame's g (which patch normalisation, eq.
    4.45-4.50, later divides out together with the slow drift).

    **Eq. 4.36 is inverted.** The thesis takes R = mean(SI_a / SI_b) (eq.
    4.35) and multiplies SI_b by fac = (E_a / E_b) / R. With SI_a = g_a E_a L
    and SI_b = g_b E_b L, R = g_a E_a / (g_b E_b), so fac = g_b / g_a and
    fac SI_b = (g_b^2 / g_a) E_b L: the jitter of b is doubled instead of
    removed (and errors compound along the chain). The factor that removes
    it is 1 / fac = R E_b / E_a, giving g_a E_b L. ``method="robust"`` uses
    it; ``method="thesis"`` reproduces the printed equations for comparison
    (tests/test_hdr.py shows both).

    ``method="robust"`` (default) also departs from the thesis in how it
    measures the ratio:

    * pixels are used where a third, independent exposure q of the sequence
      predicts both values inside (``lo``, ``hi``) = (0.1, 0.9) and no
      repeat was saturated (``clipped``), instead of a direction-dependent
      threshold t^p in {0.9, 0.4} on b alone (eq. 4.33-4.34). Choosing on
      the noisy values of a and b themselves - the thesis, or "well exposed
      in both" - keeps pixels whose noise pushed them into the window and
      biases the ratio by ~0.02 % per pair, compounding to ~0.1-0.15 % at
      the ends of the 18-exposure chain (measured; tests/test_hdr.py);
    * the ratio is sum(SI_b) / sum(SI_a) over those pixels after dropping
      outliers more than 6 robust sigmas from the median per-pixel ratio
      (hot pixels, a highlight at a clipping edge), not the mean of
      SI_a / SI_b (eq. 4.35), which is biased by E[1/x] > 1/E[x]; a plain
      median of ratios is biased by the ratio distribution's skew;
    * when the third image leaves fewer than ``min_pixels`` (100, as in the
      thesis) such pixels, the third image on the other side and then the
      pair's longer image choose them (:func:`_gain_ratio`); with still too few,
      b is compared with the next already corrected image towards the
      reference instead; if none has enough overlap b is left uncorrected
      and listed in ``report.skipped``. (The thesis skips the pair and
      then corrects the next image against the uncorrected b.)

    Both methods: eq. 4.35 writes SI^comb for image a; the text ("start in
    the center ... and correct towards each direction", errors that
    "propagate") describes a chain, so a's corrected value is used. Values
    that are saturated (1, or ``clipped``) are not scaled (eq. 4.37) and the
    result is clipped to [0, 1] (eq. 4.38; printed min(max(x, 1), 0) is 0
    for every x, the intended min(max(x, 0), 1) is implemented).

    ``reference``: "centre" (floor(n/2), the thesis), "best" (the image
    with most pixels in (lo, hi)) or an index. ``images`` (n, H, W) and
    ``exposure_s`` (n,) increasing. Returns the corrected float32 images and
    a :class:`NeighbourReport`. ``copy=False`` corrects float32 ``images`` in place (and
    returns them), for a caller that no longer needs the uncorrected stack: no second
    (n, H, W) array.
    """
    y, t, clipped = _check_stack(images, exposure_s, clipped)
    n = y.shape[0]
    if method not in ("robust", "thesis"):
        raise InputError(f"neighbour_correct: method must be 'robust' or 'thesis', got {method!r}")
    if not (0.0 <= lo < hi <= 1.0):
        raise InputError(f"neighbour_correct: need 0 <= lo < hi <= 1, got lo={lo}, hi={hi}")
    if int(min_pixels) < 1:
        raise InputError(f"neighbour_correct: min_pixels must be >= 1, got {min_pixels}")
    usable = np.empty(y.shape, bool)                     # not saturated (values are finite)
    for k in range(n):
        np.less(y[k], 1.0, out=usable[k])
        if clipped is not None:
            usable[k] &= ~clipped[k]
    if reference == "centre":
        ref = n // 2
    elif reference == "best":
        ref = int(np.argmax([np.count_nonzero((y[k] > lo) & (y[k] < hi) & usable[k]) for k in range(n)]))
    else:
        try:
            ref = int(reference)
        except (TypeError, ValueError):
            raise InputError(f"neighbour_correct: reference must be 'centre', 'best' or an index, "
                             f"got {reference!r}") from None
        if not 0 <= ref < n:
            raise InputError(f"neighbour_correct: reference index {ref} outside 0..{n - 1}")
    out = y.astype(np.float32, copy=copy)
    factor = np.ones(n)
    partner = np.full(n, -1)
    pixels = np.zeros(n, int)
    anchored = np.zeros(n, bool)
    anchored[ref] = True
    skipped: list[int] = []

    for a, b in _pairs_centre_out(n, ref):
        fac = None
        if method == "thesis":
            tp = 0.9 if a < b else 0.4                                   # eq. 4.33
            sel = (out[b] > 0.1) & (out[b] < tp)                         # eq. 4.34 (on SI^comb_b = out[b])
            cnt = int(np.count_nonzero(sel))
            if cnt >= min_pixels:
                r_bar = float(np.mean(out[a][sel].astype(np.float64) / out[b][sel]))   # eq. 4.35
                fac = (t[a] / t[b]) / r_bar                              # eq. 4.36, as printed
                used = a
        else:
            step = 1 if b > a else -1           # direction away from the reference
            for c in range(a, ref - step, -step):
                if not anchored[c]:
                    continue
                fac, cnt = _gain_ratio(out, usable, t, c, b, step, lo, hi, min_pixels)
                if fac is not None:
                    used = c
                    break
        if fac is None:
            skipped.append(b)
            pixels[b] = cnt
            continue
        scale = usable[b] & (out[b] < 1.0)                                # eq. 4.37
        np.multiply(out[b], np.float32(fac), out=out[b], where=scale)
        np.clip(out[b], 0.0, 1.0, out=out[b])                             # eq. 4.38 (intended)
        factor[b], partner[b], pixels[b] = fac, used, cnt
        anchored[b] = True
    return out, NeighbourReport(reference=ref, factor=factor, partner=partner, pixels=pixels, skipped=skipped)


# ------------------------------------------------------------ eq. 4.39-4.44

def hdr_thesis(images, exposure_s, *, min_valid: int = 4) -> np.ndarray:
    """Thesis "HDRI Regression", eq. 4.39-4.44, as printed.

    Per pixel, the exposures with 0 < SI < 1 (eq. 4.39; SI^norm there is
    read as the corrected images SI^corr of eq. 4.41) give points (E_i,
    SI_i); an unweighted least-squares line a E + b (eq. 4.42-4.43) is
    sampled at E = 1 s; with fewer than ``min_valid`` = 4 valid exposures the
    value is 0 (eq. 4.44). Returns float32 (H, W) in units of the white-black
    range per second.

    Kept to reproduce the thesis and to measure what :func:`hdr_ml` gains
    (validation/hdr_report.md). Its weaknesses for a linear sensor with
    shot noise: equal weights although the variance grows with the signal;
    an intercept that is pure noise for a linear sensor yet enters the
    value at 1 s; the validity test on the noisy (mean) value, which admits
    means of partly clipped repeats just below 1 and, near 0, only the
    positive noise excursions (the negative ones are clipped to 0 by
    linearisation and then rejected) - both bias the line; and a 0 for
    "unknown" that is indistinguishable from black.
    """
    y, t, _ = _check_stack(images, exposure_s)
    n, h, w = y.shape
    flat = y.reshape(n, -1)
    out = np.zeros(flat.shape[1], np.float32)
    tt = t[:, None]
    for s in range(0, flat.shape[1], _BLOCK):
        yb = flat[:, s:s + _BLOCK].astype(np.float64)
        v = (yb > 0.0) & (yb < 1.0)                                       # eq. 4.39
        cnt = v.sum(axis=0)
        ok = cnt >= min_valid
        c = np.maximum(cnt, 1)
        xm = (tt * v).sum(axis=0) / c
        ym = (yb * v).sum(axis=0) / c
        dx = (tt - xm) * v
        sxx = (dx * dx).sum(axis=0)
        sxy = (dx * (yb - ym)).sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            a = sxy / sxx                                                 # eq. 4.42
        b = ym - a * xm                                                   # eq. 4.43
        ok &= sxx > 0
        out[s:s + _BLOCK] = np.where(ok, a * 1.0 + b, 0.0)                # eq. 4.44
    return out.reshape(h, w)


@dataclass
class HdrResult:
    """Per-pixel HDR estimate of one sequence.

    ``rate`` float32 (H, W): linear response in fractions of the white-black
    range per second of exposure (NaN where ``status`` != VALID);
    ``variance`` float32 (H, W): its variance from shot and read noise
    (units^2; NaN where invalid) - the image-wide LED gain error left after
    neighbour correction is not included (patch normalisation removes it);
    ``n_valid`` uint8 (H, W): exposures used; ``status`` uint8 (H, W): a key
    of :data:`STATUS_REASONS`.
    """

    rate: np.ndarray
    variance: np.ndarray
    n_valid: np.ndarray
    status: np.ndarray

    def reason_counts(self) -> dict[str, int]:
        """How many pixels have each status (for logs and reports)."""
        vals, cnt = np.unique(self.status, return_counts=True)
        return {STATUS_REASONS[int(v)]: int(c) for v, c in zip(vals, cnt)}


def hdr_ml(images, exposure_s, noise: NoiseModel, *, repeats: int = 1, clipped=None, lo: float = LO,
           hi: float = HI, min_valid: int = 1, iterations: int = 4) -> HdrResult:
    """HDR rate of a linear sensor: inverse-variance weighted fit through
    the origin. Replaces thesis eq. 4.39-4.44 (see :func:`hdr_thesis`).

    Model: the combined value of exposure i is y_i = r t_i + noise with
    variance v_i = (r t_i / N_e + s^2) / m (``noise``: N_e electrons per
    unit, read sigma s; m ``repeats``). A linear sensor has no offset after
    black subtraction, so the line goes through the origin (the thesis fits
    an intercept, eq. 4.43). The weighted least-squares / quasi-likelihood
    estimate is

        r = sum_i w_i t_i y_i / sum_i w_i t_i^2,   w_i = 1 / v_i(r),

    iterated a few times because the weights depend on r. Without read
    noise w_i t_i is constant and r = sum(y_i) / sum(t_i), the exact Poisson
    maximum-likelihood rate; read noise shifts weight from the shortest
    exposures, where it rivals the shot noise (below ~0.001 of the range
    with the rig's sensor). With ``lo`` = 0.002 that changes the twin's
    results by < 0.01 % (validation/hdr_report.md, method D); it is kept for
    noisier cameras and lower ``lo``. Variance of r: 1 / sum_i w_i t_i^2
    (the inverse Fisher information).

    Valid exposures: first from the samples, lo < y_i < hi and no repeat
    saturated (pass 1, only to get a starting r); then from the *estimated
    expected* value, lo <= r t_i <= hi and no saturated repeat (passes 2..).
    Choosing on the noisy sample, as eq. 4.39 does, keeps a sample near a
    limit only when its noise pushed it inside, which biases r; choosing on
    r t_i does not look at the sample's own noise. ``lo`` = 0.002 (about 20
    electrons at ISO 320, 3.7 sigma above 0) keeps linearisation's clipping
    at 0 negligible. ``hi`` = 0.95 is as high as is safe: a frame near the
    top has ~1 % noise (shot noise, LED jitter, drift between repeats), so
    0.95 is >= 3.7 sigma below saturation and dropping the rare exposure
    with a saturated repeat (always done) biases the rest by < 1e-5; going
    higher would not be safe, going lower wastes information, since with
    the doubling exposure table the longest valid exposure carries about
    half of it (validation/hdr_report.md: 0.9 instead of 0.95 costs ~3 %
    in median error).

    Pixels with fewer than ``min_valid`` valid exposures get NaN rate and
    variance (not the thesis's 0, which reads as black): ``status`` says
    why (TOO_DARK, TOO_BRIGHT, TOO_FEW; :data:`STATUS_REASONS`). Dark current
    is not subtracted: it adds D / N_e per second to every rate (5e-6 with
    the twin's 0.05 e-/s), far below the ``lo`` limit.

    ``images`` (n, H, W) combined (and neighbour-corrected) values,
    ``exposure_s`` (n,) increasing, ``clipped`` (n, H, W) from
    :func:`combine_repeats` (else ``images >= 1`` marks saturation).

    Arithmetic in float32 (issue 19; the inputs are float32 and so are the results), in
    blocks that stay in cache. Error budget against the same computation in float64
    rounded once: each sum has at most n = 18 positive terms, so its relative rounding
    error is below n 2^-24 = 1.1e-6 (typically sqrt(n) 2^-24 / sqrt(3) = 1.4e-7), and
    the iteration stops at a relative change of 1e-6 (float32 cannot resolve 1e-7);
    measured on a full-resolution twin sequence (4.3 million pixels): rates within
    2.8e-7, variances within 3.6e-7 relative at the 99.99th percentile. The relative
    shot noise of a rate is at least 1e-3 (the brightest pixel's ~10^6 electrons over
    all exposures), so the budget is 1e-3 of the noise. A pixel whose r t_i lies within
    that rounding of ``lo`` or ``hi`` may take or drop exposure i (2 of the 4.3 million
    pixels there: rate change below 3e-7, variance 1.4e-4, since such an exposure
    carries almost no weight).
    """
    y, t, clipped = _check_stack(images, exposure_s, clipped)
    if not isinstance(noise, NoiseModel):
        raise InputError(f"hdr_ml needs a NoiseModel (e.g. NoiseModel.from_rig), got {type(noise).__name__}")
    if int(repeats) < 1:
        raise InputError(f"hdr_ml: repeats must be >= 1, got {repeats}")
    if not (0.0 < lo < hi <= 1.0):
        raise InputError(f"hdr_ml: need 0 < lo < hi <= 1, got lo={lo}, hi={hi}")
    if int(min_valid) < 1 or int(iterations) < 1:
        raise InputError(f"hdr_ml: min_valid and iterations must be >= 1, got {min_valid}, {iterations}")
    n, h, w = y.shape
    m = np.float32(int(repeats))
    inv_ne, s2 = np.float32(1.0 / noise.electrons_full_scale), np.float32(noise.read_sigma ** 2)
    lo32, hi32 = np.float32(lo), np.float32(hi)
    flat = y.reshape(n, -1)
    cflat = None if clipped is None else clipped.reshape(n, -1)
    P = flat.shape[1]
    rate = np.full(P, np.nan, np.float32)
    var = np.full(P, np.nan, np.float32)
    nval = np.zeros(P, np.uint8)
    status = np.zeros(P, np.uint8)
    t32 = t.astype(np.float32)
    tt, tt2 = t32[:, None], t32 * t32
    nan32 = np.float32(np.nan)
    for s in range(0, P, _ML_BLOCK):
        yb = np.ascontiguousarray(flat[:, s:s + _ML_BLOCK], dtype=np.float32)
        usable = yb < 1.0
        if cflat is not None:
            usable &= ~cflat[:, s:s + _ML_BLOCK]
        ty = yb * tt                                              # t_i y_i, the same every iteration
        v = usable & (yb > lo32) & (yb < hi32)                    # pass 1: from the samples
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.where(v, yb, np.float32(0)).sum(axis=0) / (t32 @ v.astype(np.float32))
        sw = np.zeros_like(r)
        valid = v
        for _ in range(int(iterations)):
            e = np.nan_to_num(r, nan=0.0) * tt                    # estimated expected values (none where r is unknown)
            valid = usable & (e >= lo32) & (e <= hi32)
            e *= inv_ne
            e += s2
            wt = np.divide(m, e, out=e)                           # 1 / variance of each combined value
            wt *= valid
            sw = tt2 @ wt
            wt *= ty
            with np.errstate(invalid="ignore", divide="ignore"):
                r_new = np.where(sw > 0, wt.sum(axis=0) / sw, nan32)
            done = np.allclose(r_new, r, rtol=1e-6, atol=0.0, equal_nan=True)
            r = r_new
            if done:
                break
        cnt = valid.sum(axis=0)
        ok = (cnt >= min_valid) & np.isfinite(r) & (r > 0)
        # why the others failed: from the shortest and longest exposure (sample or estimate)
        with np.errstate(invalid="ignore"):
            too_bright = ~usable[0] | (yb[0] >= hi32) | (r * t32[0] > hi32)
            too_dark = (yb[-1] <= lo32) | (r * t32[-1] < lo32)
        st = np.where(ok, VALID, np.where(too_bright & ~too_dark, TOO_BRIGHT,
                                          np.where(too_dark, TOO_DARK, TOO_FEW)))
        # a pixel with some valid exposures but fewer than min_valid is TOO_FEW
        st = np.where(~ok & (cnt > 0), TOO_FEW, st)
        rate[s:s + _ML_BLOCK] = np.where(ok, r, nan32)
        with np.errstate(divide="ignore"):
            var[s:s + _ML_BLOCK] = np.where(ok, np.float32(1) / np.where(sw > 0, sw, np.float32(np.inf)), nan32)
        nval[s:s + _ML_BLOCK] = np.minimum(cnt, 255)
        status[s:s + _ML_BLOCK] = st
    return HdrResult(rate=rate.reshape(h, w), variance=var.reshape(h, w), n_valid=nval.reshape(h, w),
                     status=status.reshape(h, w))


def hdr_from_stack(stack: ExposureStack, noise: NoiseModel, *, correction: str | None = "robust",
                   overwrite: bool = False, **kwargs) -> HdrResult:
    """The radiometric stage for one (rotation, LED): neighbour correction
    (eq. 4.32-4.38, ``correction`` "robust", "thesis" or None) then
    :func:`hdr_ml` (``kwargs`` go to it). Patch normalisation
    (:func:`glossrig.core.radiometry.patch.normalise_by_patch`) follows once the
    marker's white patch is known. ``overwrite=True`` corrects ``stack.images`` in place
    (no second copy of the stack; keep :meth:`ExposureStack.ends` first for
    :func:`exposure_to_fix`)."""
    images = stack.images
    if correction is not None:
        images, _ = neighbour_correct(images, stack.exposure_s, clipped=stack.clipped, method=correction,
                                      copy=not overwrite)
    return hdr_ml(images, stack.exposure_s, noise, repeats=stack.repeats, clipped=stack.clipped, **kwargs)


def exposure_to_fix(stack: ExposureStack, status, *, lo: float = LO, hi: float = HI) -> np.ndarray:
    """Per pixel, the exposure time (s) that would have given a pixel of ``status``
    TOO_DARK or TOO_BRIGHT (an :class:`HdrResult`'s, of this ``stack``) a valid value;
    NaN for valid pixels and where it cannot be told.

    Too dark: the longest exposure scaled by the ratio of the noise floor ``lo`` to the
    pixel's expected value there, i.e. ``lo / r`` with the rate ``r`` of the two longest
    exposures, ``(y_n + y_n-1) / (t_n + t_n-1)`` (the shot-noise maximum-likelihood rate
    over them; no validity window, since every exposure of a dark pixel is below it; the
    shorter ones carry little signal and, clipped at 0 by linearisation, would bias it
    upwards). A single pixel's value is noisy (about 30 % at half the floor with the
    rig's sensor): read it over a region. Infinite where no signal was seen at all. Too
    bright: ``hi / r`` with ``r`` from the shortest exposure when that one is not
    saturated (its value above ``hi``); NaN when it is saturated, since then only
    "shorter than the shortest" is known."""
    st = np.asarray(status)
    t = np.asarray(stack.exposure_s, float)
    out = np.full(st.shape, np.nan)
    dark = st == TOO_DARK
    if dark.any():
        last = slice(max(0, t.size - 2), t.size)
        yd = stack.images[last][:, dark].astype(np.float64)
        ok = ~stack.clipped[last][:, dark] & (yd < 1.0)
        num = np.where(ok, yd, 0.0).sum(axis=0)
        den = (t[last, None] * ok).sum(axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = num / den
            out[dark] = np.where(r > 0, lo / r, np.inf)
    bright = st == TOO_BRIGHT
    if bright.any():
        y0 = stack.images[0][bright].astype(np.float64)
        seen = ~stack.clipped[0][bright] & (y0 < 1.0) & (y0 > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            out[bright] = np.where(seen, hi * t[0] / y0, np.nan)
    return out

