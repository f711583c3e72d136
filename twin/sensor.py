"""The twin's image sensor: scene radiance -> raw Bayer mosaic (uint16 DN).

A photon-transfer (EMVA 1288-style linear camera) model with the figures of
the rig's ``[sensor]`` section (scenes/thesis_rig.toml) and the camera's CFA,
black and white levels (``[camera]``). Per pixel, with c the CFA colour of
the pixel (thesis 4.3.1, fig. 4.6-4.7):

1. expected photo-electrons  mu_p = L_c * k_c * (11 / N)^2 * t * gain, where
   L_c is the scene radiance (W m^-2 sr^-1) of colour c, k_c the rig's
   ``electrons_per_radiance_s_f11`` (photo-electrons per second per unit
   radiance at f/11; image-plane irradiance scales with 1/N^2), t the
   exposure time and ``gain`` a free multiplier (e.g. LED intensity);
2. optional ``pre_electrons`` effects (see below);
3. shot noise and dark signal: electrons ~ Poisson(mu_p + D t) (photon and
   dark-current counts are independent Poisson variables, so their sum is
   one Poisson draw with the summed mean);
4. clipped at the full-well capacity;
5. read noise: + Normal(0, sigma_r) electrons;
6. conversion: DN = electrons / K with K = electrons_per_dn_iso100 * 100 / ISO
   (e-/DN; higher ISO = more DN per electron);
7. + the black level of the pixel's CFA position;
8. optional ``post_dn`` effects;
9. rounded, clipped to [0, white_level] (values at the white level are
   saturated, as the pipeline assumes, thesis eq. 4.39) and stored as uint16.

Predicted variance (photon transfer curve, Janesick, "Photon Transfer", SPIE
2007; EMVA Standard 1288 release 4.0, eq. 7): for a mean signal mu_y DN above
black (below saturation), sigma_y^2 = mu_y / K + sigma_r^2 / K^2 + 1/12, the
last term being the quantisation noise of rounding to integer DN.

Simplification (adjustable later): read noise is one figure in electrons at
every ISO. Shot noise is drawn exactly. :meth:`SensorModel.expose` runs steps
3-7 (and 9) in compiled Dr.Jit code (:mod:`glossrig.twin.sensor_drjit`:
Hoermann's PTRS rejection sampler for lambda >= 10 and CDF inversion below,
Box-Muller read noise, per-pixel PCG32 streams keyed by one 64-bit draw from
the frame's generator); a pixel whose mean exceeds the full well by so much
that it stays below it with probability < exp(-50) is set to the full well
without a draw. :meth:`SensorModel.prepare` does step 1 once for all the
exposures of a sequence (issue 19; validation/twin/benchmark.md has the
speed-up). :meth:`SensorModel.expose_reference` is the former NumPy path
(``Generator.poisson``; means above twice the full well capped there, which
changes nothing as such a pixel is clipped at the full well in step 4 with
probability 1 - 1e-4000), kept as the reference: same statistics, other draws
(tests/test_sensor_fast.py).

Effects: ``expose(..., effects=...)`` takes one object or a sequence of
objects. For each stage, in order, every effect that has a method of the
stage's name is called as ``array = effect.<stage>(array, ctx)``:

* ``pre_electrons(expected_e, ctx)``: float32 (H, W) expected
  photo-electrons per pixel before noise (e.g. LED flicker, vignetting,
  PRNU);
* ``post_dn(dn, ctx)``: float32 (H, W) raw values in DN including the black
  level, before rounding and clipping (e.g. banding, hot pixels).

It must return an array of the same shape (it may modify its argument in
place and return it). ``ctx`` is a :class:`SensorContext` with the exposure,
ISO, f-number, frame index, the frame's random generator and the sensor.

Memory: a full frame is 6032 x 4032; the reference path holds one float32
(H, W) work array besides the caller's radiance and draws noise in blocks of
:data:`BLOCK_ROWS` rows; the fast path holds the prepared radiance (float32,
(H, W)) and per exposure two float32 half-frames and the uint16 mosaic in
Dr.Jit memory.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from glossrig.core.calibration.demosaic import cfa_array, cfa_string
from glossrig.core.errors import InputError

from .dng import XYZ_TO_SRGB

__all__ = ["SensorModel", "SensorContext", "SensorEffect", "PreparedRadiance", "frame_rng", "image_rng"]

#: Rows of the mosaic whose noise is drawn at once (bounds the float64/int64
#: temporaries of Generator.poisson). Fixed: it is part of what a seed means.
BLOCK_ROWS = 256


def frame_rng(seed: int, frame_index: int) -> np.random.Generator:
    """The random generator of frame ``frame_index`` of a capture seeded
    with ``seed``: independent streams per frame (NumPy SeedSequence spawn
    keys), so any frame can be re-made alone, in any order, bit for bit."""
    if int(seed) < 0 or int(frame_index) < 0:
        raise InputError(f"seed and frame index must be >= 0, got {seed}, {frame_index}")
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(int(frame_index),)))


#: First spawn-key word of :func:`image_rng` streams, so they never meet :func:`frame_rng`'s
#: (whose spawn key is the bare frame index).
_IMAGE_STREAM = 0x1A6E0001
_ROLE_CODE = {"calibration": 1, "sequence": 2, "checkerboard": 3}


def image_rng(seed: int, role: str, rotation: float, leds, repeat: int = 0, exposure_index: int = 0,
              view: int | None = None) -> np.random.Generator:
    """The random generator of one planned image, keyed by what the image *is*: its role,
    sample rotation (to 0.001 degree), the LEDs on, the repeat, the index in its
    exposure sequence and the checkerboard view - never by how many images this process
    made before. Sensor noise and LED fluctuations drawn from it are therefore the same
    whether a capture runs in one go, is resumed after an interruption or is re-made
    image by image (design.md: an interrupted run resumes byte-identical)."""
    if int(seed) < 0:
        raise InputError(f"seed must be >= 0, got {seed}")
    if role not in _ROLE_CODE:
        raise InputError(f"role {role!r} not one of {tuple(_ROLE_CODE)}")
    milli = round(float(rotation) * 1000)
    rot = 2 * milli if milli >= 0 else -2 * milli - 1            # zigzag: non-negative, one-to-one
    mask = 0
    for i in leds:
        mask |= 1 << int(i)
    key = (_IMAGE_STREAM, _ROLE_CODE[role], rot, mask, int(repeat), int(exposure_index),
           0 if view is None else int(view) + 1)
    if min(key) < 0:
        raise InputError(f"repeat, exposure index and view must be >= 0, got {repeat}, {exposure_index}, {view}")
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=key))


@dataclass
class SensorContext:
    """What an effect hook gets to know about the frame being exposed."""

    exposure_s: float
    iso: float
    aperture: float
    frame_index: int
    rng: np.random.Generator
    sensor: SensorModel

    @property
    def cfa(self) -> np.ndarray:
        return cfa_array(self.sensor.cfa)


class SensorEffect(Protocol):
    """An effect needs only the stages it acts at; both are optional."""

    def pre_electrons(self, expected_e: np.ndarray, ctx: SensorContext) -> np.ndarray: ...

    def post_dn(self, dn: np.ndarray, ctx: SensorContext) -> np.ndarray: ...


def _stage(effects, stage: str, arr: np.ndarray, ctx: SensorContext) -> np.ndarray:
    for eff in effects:
        fn = getattr(eff, stage, None)
        if fn is None:
            continue
        out = fn(arr, ctx)
        if not isinstance(out, np.ndarray) or out.shape != arr.shape:
            raise TypeError(f"effect {type(eff).__name__}.{stage} must return an array of shape {arr.shape}, "
                            f"got {type(out).__name__} {getattr(out, 'shape', '')}")
        arr = out.astype(np.float32, copy=False)
    return arr


def _effect_list(effects) -> list:
    if effects is None:
        return []
    if isinstance(effects, (list, tuple)):
        return list(effects)
    return [effects]


@dataclass(frozen=True)
class PreparedRadiance:
    """A radiance image with its exposure-independent sensor input (:meth:`SensorModel.prepare`)."""

    radiance: np.ndarray
    rate: Any = None            # glossrig.twin.sensor_drjit.Rate, or None without Dr.Jit


@dataclass(frozen=True)
class SensorModel:
    """Linear photon-transfer sensor (see module docstring).

    ``cfa`` names the 2x2 pattern from pixel (0, 0); ``black_level`` gives
    the black level of its four positions row by row; electron figures are
    at ISO 100 where they depend on ISO.
    """

    cfa: str
    bits: int
    white_level: int
    black_level: tuple[int, int, int, int]
    electrons_per_dn_iso100: float
    read_noise_e: float
    dark_current_e_s: float
    full_well_e: float
    electrons_per_radiance_s_f11: tuple[float, float, float]

    def __post_init__(self):
        cfa_array(self.cfa)
        if not (0 < self.white_level < 2 ** 16) or not all(0 <= b < self.white_level for b in self.black_level):
            raise InputError(f"sensor levels out of range: black {self.black_level}, white {self.white_level}")
        if len(self.electrons_per_radiance_s_f11) != 3 or min(self.electrons_per_radiance_s_f11) <= 0:
            raise InputError("electrons_per_radiance_s_f11 must hold 3 positive values (R, G, B)")
        if self.electrons_per_dn_iso100 <= 0 or self.full_well_e <= 0 or self.read_noise_e < 0 \
                or self.dark_current_e_s < 0:
            raise InputError("sensor gain and full well must be > 0, read noise and dark current >= 0")

    @classmethod
    def from_rig(cls, rig) -> SensorModel:
        """From a :class:`glossrig.core.rig.Rig`: ``rig.camera`` (cfa, bits,
        white_level, black_level) and the ``[sensor]`` section."""
        cam, sen = rig.camera, rig.sensor        # both checked by load_rig
        return cls(cfa=cam.cfa, bits=int(cam.bits), white_level=int(cam.white_level),
                   black_level=tuple(int(b) for b in cam.black_level),
                   electrons_per_dn_iso100=sen.electrons_per_dn_iso100, read_noise_e=sen.read_noise_e,
                   dark_current_e_s=sen.dark_current_e_s, full_well_e=sen.full_well_e,
                   electrons_per_radiance_s_f11=sen.electrons_per_radiance_s_f11)

    # ------------------------------------------------------------ helpers

    def conversion_gain(self, iso: float) -> float:
        """K in e-/DN at ``iso``: electrons_per_dn_iso100 * 100 / ISO."""
        iso = float(iso)
        if not (math.isfinite(iso) and iso > 0):
            raise InputError(f"ISO must be a positive number, got {iso!r}")
        return self.electrons_per_dn_iso100 * 100.0 / iso

    def black_2x2(self) -> np.ndarray:
        return np.asarray(self.black_level, np.float32).reshape(2, 2)

    def dark_dn(self, exposure_s: float, iso: float) -> float:
        """Mean dark signal above black in DN: D t / K."""
        return self.dark_current_e_s * float(exposure_s) / self.conversion_gain(iso)

    def dng_colour(self) -> tuple[np.ndarray, np.ndarray]:
        """(ColorMatrix1, AsShotNeutral) for :func:`glossrig.twin.dng.write_dng`.

        The raw value of colour c is k_c times the linear-sRGB radiance, so
        XYZ -> camera is diag(s) . M_XYZ->sRGB with s = k / max(k), and an
        equal-radiance (white) scene gives the camera neutral s (DNG 1.4,
        "Mapping Camera Color Space to CIE XYZ Space")."""
        k = np.asarray(self.electrons_per_radiance_s_f11, float)
        s = k / k.max()
        return s[:, None] * np.asarray(XYZ_TO_SRGB), s

    def _check_exposure(self, exposure_s, iso, aperture, gain) -> tuple[float, float, float, float]:
        return _pos("exposure_s", exposure_s), _pos("iso", iso), _pos("aperture", aperture), _pos("gain", gain, True)

    def expected_electrons(self, radiance_rgb: np.ndarray, exposure_s: float, aperture: float,
                           gain: float = 1.0) -> np.ndarray:
        """Step 1: expected photo-electrons per pixel, float32 (H, W), each
        pixel taking the radiance of its CFA colour."""
        exposure_s, aperture = _pos("exposure_s", exposure_s), _pos("aperture", aperture)
        gain = _pos("gain", gain, allow_zero=True)
        rad = np.asarray(radiance_rgb)
        if rad.ndim != 3 or rad.shape[2] != 3 or rad.shape[0] < 1 or rad.shape[1] < 1:
            raise InputError(f"radiance must be an (H, W, 3) array, got shape {rad.shape}")
        if not np.issubdtype(rad.dtype, np.floating):
            raise InputError(f"radiance must be floating point, got {rad.dtype}")
        scale = (11.0 / aperture) ** 2 * exposure_s * gain
        pat = cfa_array(self.cfa)
        e = np.empty(rad.shape[:2], np.float32)
        for i in range(2):
            for j in range(2):
                c = int(pat[i, j])
                k = np.float32(self.electrons_per_radiance_s_f11[c] * scale)
                np.multiply(rad[i::2, j::2, c], k, out=e[i::2, j::2], casting="same_kind")
        _check_finite(e, "radiance")
        return e

    # ------------------------------------------------------------- models

    def expected_dn(self, radiance_rgb: np.ndarray, exposure_s: float, iso: float, aperture: float,
                    gain: float = 1.0) -> np.ndarray:
        """Noise-free raw value (float32 DN, (H, W), black level included):
        (min(mu_p + D t, full well)) / K + black, clipped to [0, white]. No
        effects are applied. Away from the clipping limits this is the mean
        of :meth:`expose`."""
        exposure_s, iso, aperture, gain = self._check_exposure(exposure_s, iso, aperture, gain)
        e = self.expected_electrons(radiance_rgb, exposure_s, aperture, gain)
        e += np.float32(self.dark_current_e_s * exposure_s)
        np.minimum(e, np.float32(self.full_well_e), out=e)
        e /= np.float32(self.conversion_gain(iso))
        self._add_black(e)
        np.clip(e, 0, self.white_level, out=e)
        return e

    def variance_dn(self, mean_dn_above_black, iso: float, exposure_s: float):
        """Predicted temporal variance (DN^2) of a pixel whose photo-signal
        (dark signal excluded) is ``mean_dn_above_black`` DN:

        sigma^2 = (mu_p + D t / K) / K + sigma_r^2 / K^2 + 1/12

        (photon transfer, EMVA 1288 eq. 7, with the dark signal's own shot
        noise and rounding). Valid below saturation. Array or scalar in,
        same out."""
        K = self.conversion_gain(iso)
        mu = np.asarray(mean_dn_above_black, dtype=float)
        var = (mu + self.dark_dn(exposure_s, iso)) / K + (self.read_noise_e / K) ** 2 + 1.0 / 12.0
        return float(var) if var.ndim == 0 else var

    def _add_black(self, dn: np.ndarray) -> None:
        b = self.black_2x2()
        for i in range(2):
            for j in range(2):
                dn[i::2, j::2] += b[i, j]

    def prepare(self, radiance_rgb: np.ndarray) -> PreparedRadiance:
        """``radiance_rgb`` made ready for several :meth:`expose` calls (a sequence's 18
        exposures of one render): step 1 per unit exposure, t (11/N)^2 gain = 1, computed and
        handed to Dr.Jit once (issue 19: exposure-independent work done once per sequence).
        :meth:`expose` takes it in place of the radiance; the radiance must not change
        while it is in use."""
        rate = None
        if _fast_noise_available():
            from .sensor_drjit import Rate

            rate = Rate(self.expected_electrons(radiance_rgb, 1.0, 11.0))
        return PreparedRadiance(radiance=np.asarray(radiance_rgb), rate=rate)

    def expose(self, radiance_rgb: np.ndarray, exposure_s: float, iso: float, aperture: float,
               rng: np.random.Generator, gain: float = 1.0, effects: Any = None,
               frame_index: int = 0) -> np.ndarray:
        """One raw exposure: uint16 (H, W) CFA mosaic (steps 1-9 of the
        module docstring). ``rng`` supplies all randomness (see
        :func:`frame_rng` for per-frame generators); the same generator state
        gives the same mosaic. Steps 3-7 (and 9 without ``post_dn`` effects) run
        as one Dr.Jit kernel (:mod:`glossrig.twin.sensor_drjit`: exact Poisson and
        normal draws from per-pixel streams seeded by one 64-bit draw from ``rng``);
        without Dr.Jit's LLVM backend, as :meth:`expose_reference`."""
        return self._expose(radiance_rgb, exposure_s, iso, aperture, rng, gain, effects, frame_index, fast=True)

    def expose_reference(self, radiance_rgb: np.ndarray, exposure_s: float, iso: float, aperture: float,
                         rng: np.random.Generator, gain: float = 1.0, effects: Any = None,
                         frame_index: int = 0) -> np.ndarray:
        """:meth:`expose` with the NumPy noise step (``Generator.poisson`` and
        ``standard_normal`` in blocks of :data:`BLOCK_ROWS` rows): the same model,
        other random draws. The reference the fast path is tested and benchmarked
        against (tests/test_sensor.py, validation/twin/benchmark.py); about 10x slower."""
        return self._expose(radiance_rgb, exposure_s, iso, aperture, rng, gain, effects, frame_index, fast=False)

    def _expose(self, radiance_rgb, exposure_s, iso, aperture, rng, gain, effects, frame_index,
                fast: bool) -> np.ndarray:
        if not isinstance(rng, np.random.Generator):
            raise InputError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
        exposure_s, iso, aperture, gain = self._check_exposure(exposure_s, iso, aperture, gain)
        effs = _effect_list(effects)
        ctx = SensorContext(exposure_s=exposure_s, iso=iso, aperture=aperture, frame_index=int(frame_index),
                            rng=rng, sensor=self)
        prepared = radiance_rgb if isinstance(radiance_rgb, PreparedRadiance) else None
        pre = any(getattr(eff, "pre_electrons", None) is not None for eff in effs)
        post = any(getattr(eff, "post_dn", None) is not None for eff in effs)
        fast = fast and _fast_noise_available()
        if fast and prepared is not None and prepared.rate is not None and not pre:
            src, scale = prepared.rate, (11.0 / aperture) ** 2 * exposure_s * gain      # step 1 in the kernel
        else:
            e = self.expected_electrons(prepared.radiance if prepared is not None else radiance_rgb, exposure_s,
                                        aperture, gain)
            if pre:
                e = _stage(effs, "pre_electrons", e, ctx)
                _check_finite(e, "expected electrons after pre_electrons effects")
            src, scale = e, 1.0
        inv_k = 1.0 / self.conversion_gain(iso)
        if fast:
            from .sensor_drjit import noise_dn

            seed = int(rng.integers(0, 2 ** 64, dtype=np.uint64))
            e = noise_dn(src, seed=seed, dark_e=self.dark_current_e_s * exposure_s, full_well_e=self.full_well_e,
                         read_e=self.read_noise_e, inv_k=inv_k, black_2x2=self.black_2x2(),
                         white=None if post else self.white_level, scale=scale)
            rounded = not post
        else:
            self._noise_reference(e, rng, exposure_s, inv_k)
            rounded = False
        if post:
            e = _stage(effs, "post_dn", e, ctx)
        if not rounded:
            np.rint(e, out=e)
            np.clip(e, 0, self.white_level, out=e)
        return e.astype(np.uint16, copy=False)

    def _noise_reference(self, e: np.ndarray, rng: np.random.Generator, exposure_s: float, inv_k: float) -> None:
        """Steps 3-7 in NumPy, in place: expected electrons ``e`` -> DN with black level."""
        dark = np.float32(self.dark_current_e_s * exposure_s)
        full = np.float32(self.full_well_e)
        read = np.float32(self.read_noise_e)
        inv_k32 = np.float32(inv_k)
        for r0 in range(0, e.shape[0], BLOCK_ROWS):
            blk = e[r0:r0 + BLOCK_ROWS]
            blk += dark
            electrons = _shot(rng, blk, 2.0 * self.full_well_e)
            np.minimum(electrons, full, out=electrons)
            if read > 0:
                noise = rng.standard_normal(electrons.shape, dtype=np.float32)
                noise *= read
                electrons += noise
            np.multiply(electrons, inv_k32, out=blk)
        self._add_black(e)

    def describe(self) -> str:
        return (f"{cfa_string(self.cfa)} {self.bits}-bit, black {self.black_level}, white {self.white_level}, "
                f"K100={self.electrons_per_dn_iso100} e-/DN, read {self.read_noise_e} e-, "
                f"dark {self.dark_current_e_s} e-/s, full well {self.full_well_e:g} e-")


def _pos(name: str, v, allow_zero: bool = False) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {v!r}") from None
    if not math.isfinite(f) or f < 0 or (f == 0 and not allow_zero):
        raise InputError(f"{name} must be {'>= 0' if allow_zero else '> 0'}, got {v!r}")
    return f


def _check_finite(e: np.ndarray, what: str) -> None:
    lo, hi = float(e.min()), float(e.max())   # NaN propagates through min/max
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise InputError(f"{what} holds NaN or infinite values")
    if lo < 0:
        raise InputError(f"{what} holds negative values (min {lo:g})")


def _fast_noise_available() -> bool:
    """Dr.Jit's LLVM backend can run the noise kernel; warns once where it cannot."""
    from . import sensor_drjit

    if sensor_drjit.available():
        return True
    if not _WARNED:
        _WARNED.append(True)
        warnings.warn("Dr.Jit's LLVM backend is unavailable (libLLVM 19 missing): the twin's sensor model uses its "
                      "slow NumPy reference path (other random draws, the same statistics)", RuntimeWarning, stacklevel=3)
    return False


_WARNED: list[bool] = []


def _shot(rng: np.random.Generator, lam: np.ndarray, cap: float) -> np.ndarray:
    """Poisson(lam) as float32, with lam capped at ``cap`` (>= twice the full
    well, see module docstring). Modifies ``lam``."""
    np.minimum(lam, np.float32(cap), out=lam)
    return rng.poisson(lam).astype(np.float32)
