"""Expected error of the extended-Ward parameters a rig design would measure.

A design fixes the sample angles (thesis 4.3.5) and, with the LEDs' distances
and the camera's exposure table, the noise of every BRDF sample. For a material
with extended-Ward parameters theta (thesis eq. 4.79-4.80: rho_d, rho_s,
alpha_x, alpha_y, lobe_rotation) and independent Gaussian sample errors
sigma_i, the Fisher information is

    I(theta) = sum_i  J_i^T J_i / sigma_i^2,      J_i = d f(angles_i; theta) / d theta

and ``I^-1`` is the Cramer-Rao bound on the covariance of any unbiased
estimator (the weighted least squares of thesis eq. 4.81 with inverse-variance
weights attains it asymptotically). :func:`expected_errors` returns the square
roots of its diagonal. ``weighting="mirror"`` instead gives the asymptotic
covariance of the pipeline's own estimator (:mod:`glossrig.core.fitting.fit`, weights
of thesis eq. 4.82 that are not inverse variances): the sandwich
``A^-1 B A^-1`` with ``A = sum w_i^2 J_i^T J_i``, ``B = sum w_i^4 sigma_i^2 J_i^T J_i``.

The Jacobian is analytic (:func:`ward_jacobian`, checked against finite
differences of :func:`glossrig.core.models.ward.ward_from_angles` in the tests).

Noise models (the choice is the caller's; the design tools default to ``hdr``):

* :class:`RelativeNoise`: ``sigma = rel * f`` (a few per cent).
* :class:`HdrNoise`: derived from the rig file's camera, sensor and LEDs (the
  twin's photon-transfer figures, thesis 4.2-4.3): the green channel's photo-
  electron rate ``r = k_G (11/N)^2 L`` of the radiance ``L = f I cos(theta_in) / d^2``
  (LED radiant intensity I, distance d), estimated from every exposure of the
  sequence table whose signal stays below 90 % of saturation, each weighted by
  its inverse variance ``t^2 / (r t + D t + sigma_read^2 + K^2/12)`` (shot,
  dark and read noise, quantisation); plus a relative LED-fluctuation term in
  quadrature (default 1 %, the twin's ``led_drift``, thesis 4.3.3). Pixels
  saturated at the shortest exposure carry no information.

Assumptions stated once: samples (pixels) are independent, so standard errors
scale as 1/sqrt(number of pixels), i.e. as 1/scale with the image scale; the
LED fluctuation is common to a whole frame in reality, so these are lower
bounds unless the residual gain of each sequence is given as a nuisance
parameter (:func:`gain_marginal_information`, ``design_errors(gain_rel=...)``,
``hdr:0`` then leaves the per-pixel term out); the peak clipping of thesis eq. 6.5 is not modelled. Relative errors
are ``sigma_p / p`` for rho_d, rho_s, alpha_x, alpha_y and ``sigma`` in radians
for the lobe rotation, which is not identifiable for an isotropic lobe and is
then left out.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.models.ward import WardParams, ward_geometry, ward_param_jacobian, ward_parts

PARAMS = ("rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation")


def ward_jacobian(theta_in, theta_out, theta_h, phi_h, p: WardParams):
    """Extended Ward value (eq. 4.79) and its derivatives with respect to
    (rho_d, rho_s, alpha_x, alpha_y, lobe_rotation), shape (n, 5), at flat angle
    arrays (radians). Zero below the horizon. The project's one evaluation,
    :func:`glossrig.core.models.ward.ward_param_jacobian`, for flat angle arrays."""
    geom = ward_geometry(theta_in, theta_out, theta_h, phi_h)
    f, parts = ward_parts(geom, p)
    return f, ward_param_jacobian(geom, p, parts)


@dataclass(frozen=True)
class RelativeNoise:
    """sigma = rel * f."""

    rel: float = 0.03

    def __post_init__(self):
        if not (math.isfinite(self.rel) and self.rel > 0):
            raise InputError(f"relative noise must be > 0, got {self.rel!r}")

    def sigma(self, f, cos_in=None, dist_mm=None) -> np.ndarray:
        return self.rel * np.asarray(f, float)

    def describe(self) -> str:
        return f"relative: sigma = {self.rel:g} f"


@dataclass(frozen=True)
class HdrNoise:
    """Noise of the HDR estimate of a BRDF value (module docstring)."""

    electrons_per_radiance_s: float      # green channel at the sequence aperture
    radiant_intensity_W_sr: float
    times_s: tuple[float, ...]
    conversion_gain: float               # e-/DN at the sequence ISO
    saturation_e: float
    read_noise_e: float
    dark_current_e_s: float
    led_rel: float = 0.01
    usable_fraction: float = 0.9

    @classmethod
    def from_rig(cls, rig, led_rel: float = 0.01) -> HdrNoise:
        """From the rig file's ``[sensor]``, ``[camera]``, ``[leds]`` and ``[exposures]`` sections
        (checked by :func:`glossrig.core.rig.load_rig`)."""
        sen = rig.sensor
        k = sen.electrons_per_radiance_s_f11
        e_per_dn = sen.electrons_per_dn_iso100 * 100.0 / rig.sequence_iso
        full, read, dark = sen.full_well_e, sen.read_noise_e, sen.dark_current_e_s
        intensity = rig.lighting.radiant_intensity_W_sr
        cam = rig.camera
        span_dn = cam.white_level - max(cam.black_level)
        if not (0 <= led_rel < 1):
            raise InputError(f"LED fluctuation must lie in [0, 1), got {led_rel!r}")
        return cls(electrons_per_radiance_s=k[1] * (11.0 / rig.sequence_aperture) ** 2,
                   radiant_intensity_W_sr=intensity, times_s=tuple(rig.exposure_times_s),
                   conversion_gain=e_per_dn, saturation_e=min(full, span_dn * e_per_dn),
                   read_noise_e=read, dark_current_e_s=dark, led_rel=led_rel)

    def electron_rate(self, f, cos_in, dist_mm) -> np.ndarray:
        """Green-channel photo-electrons per second of a BRDF value ``f`` (1/sr) lit at
        incidence cosine ``cos_in`` from ``dist_mm``: ``k_G (11/N)^2 f I cos / d^2``."""
        d_m = np.asarray(dist_mm, float) * 1e-3
        L = np.asarray(f, float) * self.radiant_intensity_W_sr * np.maximum(np.asarray(cos_in, float), 0.0) / d_m ** 2
        return self.electrons_per_radiance_s * L

    def sensor_relative(self, rate, times_s=None, saturation_rate=None) -> np.ndarray:
        """Relative standard deviation from sensor noise alone (shot, dark, read,
        quantisation) of the inverse-variance HDR merge of ``times_s`` (default: the
        rig's table) at electron ``rate``; inf when no exposure is usable.
        ``saturation_rate`` (default ``rate``) decides which exposures stay below
        ``usable_fraction`` of saturation (a planner passes a brighter bound)."""
        rate = np.asarray(rate, float)
        sat = rate if saturation_rate is None else np.asarray(saturation_rate, float)
        K = self.conversion_gain
        info = np.zeros(np.broadcast(rate, sat).shape)
        for t in (self.times_s if times_s is None else times_s):
            use = sat * t < self.usable_fraction * self.saturation_e
            var_rate = (rate * t + self.dark_current_e_s * t + self.read_noise_e ** 2 + K * K / 12.0) / (t * t)
            info += np.where(use, 1.0 / var_rate, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where((info > 0) & (rate > 0), 1.0 / (np.sqrt(info) * rate), np.inf)

    def relative(self, f, cos_in, dist_mm) -> np.ndarray:
        """Relative standard deviation of the HDR BRDF estimate (inf when no exposure is usable)."""
        return self.relative_with_sensor_only(f, cos_in, dist_mm)[0]

    def relative_with_sensor_only(self, f, cos_in, dist_mm) -> tuple[np.ndarray, np.ndarray]:
        """(:meth:`relative`, the same without the per-pixel LED term) from one evaluation of the
        HDR merge: the second is what ``glossrig extract`` writes as a row's variance (the merge's
        sensor noise, :meth:`sensor_relative`, which is >= 0 or inf), and so what a fit weights by;
        the first adds the independent LED fluctuation in quadrature."""
        sensor = self.sensor_relative(self.electron_rate(f, cos_in, dist_mm))
        return np.hypot(sensor, self.led_rel), sensor

    def sigma(self, f, cos_in, dist_mm) -> np.ndarray:
        return self.relative(f, cos_in, dist_mm) * np.asarray(f, float)

    def describe(self) -> str:
        return (f"hdr: green-channel shot/dark/read noise of the inverse-variance HDR merge of "
                f"{len(self.times_s)} exposures ({self.times_s[0]:g}-{self.times_s[-1]:g} s, "
                f"{self.electrons_per_radiance_s:.3g} e-/s per W m^-2 sr^-1, saturation "
                f"{self.saturation_e:.0f} e-, read {self.read_noise_e:g} e-) + {self.led_rel:g} "
                f"relative LED fluctuation, LED {self.radiant_intensity_W_sr:g} W/sr")


def noise_model(spec: str, rig=None):
    """``hdr`` (from ``rig``), ``hdr:LED_REL`` or ``relative:REL``."""
    spec = spec.strip()
    kind, _, arg = spec.partition(":")
    try:
        if kind == "hdr":
            if rig is None:
                raise InputError("the hdr noise model needs a rig")
            return HdrNoise.from_rig(rig, float(arg) if arg else 0.01)
        if kind == "relative":
            return RelativeNoise(float(arg) if arg else 0.03)
    except ValueError:
        raise InputError(f"noise model {spec!r}: the value after ':' must be a number") from None
    raise InputError(f"noise model must be 'hdr[:LED_REL]' or 'relative[:REL]', got {spec!r}")


def identifiable(p: WardParams, tol: float = 1e-6) -> np.ndarray:
    """Mask of the parameters the data can determine: the lobe rotation of an
    isotropic lobe (alpha_x = alpha_y) is not."""
    m = np.ones(5, bool)
    if abs(p.alpha_x - p.alpha_y) <= tol * max(p.alpha_x, p.alpha_y):
        m[4] = False
    return m


def error_scale(p: WardParams) -> np.ndarray:
    """What a standard error is divided by to make it relative: the parameter
    itself, and 1 radian for the lobe rotation."""
    return np.array([p.rho_d, p.rho_s, p.alpha_x, p.alpha_y, 1.0])


def information(J: np.ndarray, sigma: np.ndarray, weight: np.ndarray | None = None) -> np.ndarray:
    """``sum_i J_i^T J_i / sigma_i^2 * weight_i`` over samples with finite, positive sigma."""
    J = np.asarray(J, float)
    s = np.asarray(sigma, float)
    w = np.where(np.isfinite(s) & (s > 0), 1.0 / np.where(s > 0, s, 1.0) ** 2, 0.0)
    if weight is not None:
        w = w * np.asarray(weight, float)
    # einsum, not BLAS: the same bits whatever the thread count (a design sweep
    # must give the same answer on one process and on a cluster).
    return np.einsum("ni,nj->ij", J * w[:, None], J)


def gain_marginal_information(J: np.ndarray, sigma: np.ndarray, f: np.ndarray, gain_rel: float,
                              weight: np.ndarray | None = None) -> np.ndarray:
    """Information about the Ward parameters from one exposure sequence (one LED at one
    sample rotation) whose values share one unknown relative gain.

    The LED's output varies from frame to frame (thesis 4.3.3, fig. 4.12); neighbour
    correction (eq. 4.32-4.38) ties a sequence's frames to one of them and patch
    normalisation (eq. 4.45-4.50) divides that one out, up to a residual gain g
    common to every pixel of the sequence: y_i = (1 + g) f_i + e_i,
    g ~ N(0, ``gain_rel``^2), e_i ~ N(0, sigma_i^2) independent. With g as a nuisance
    parameter (equivalently, the correlated covariance diag(sigma^2) + gain_rel^2 f f^T,
    by Woodbury) the information about theta is the Schur complement

        I = sum J^T J / sigma^2 - b b^T / (c + 1 / gain_rel^2),
        b = sum J f / sigma^2,  c = sum f^2 / sigma^2.

    Unlike the per-pixel term of :class:`HdrNoise` (``led_rel``), it does not
    shrink with the number of pixels. ``gain_rel`` = 0 gives :func:`information`."""
    A = information(J, sigma, weight)
    if not (math.isfinite(gain_rel) and gain_rel >= 0):
        raise InputError(f"gain error must be >= 0, got {gain_rel!r}")
    if gain_rel == 0:
        return A
    s = np.asarray(sigma, float)
    w = np.where(np.isfinite(s) & (s > 0), 1.0 / np.where(s > 0, s, 1.0) ** 2, 0.0)
    if weight is not None:
        w = w * np.asarray(weight, float)
    f = np.asarray(f, float)
    b = np.einsum("n,ni->i", w * f, np.asarray(J, float))
    c = float(np.einsum("n,n->", w * f, f))
    return A - np.outer(b, b) / (c + 1.0 / gain_rel ** 2)


def sandwich_parts(J: np.ndarray, sigma: np.ndarray, w: np.ndarray, weight: np.ndarray | None = None):
    """(A, B) of the weighted-least-squares covariance ``A^-1 B A^-1`` for fit weights ``w``
    (residual multipliers, thesis eq. 4.82) and true errors ``sigma``."""
    J = np.asarray(J, float)
    s = np.asarray(sigma, float)
    ok = np.isfinite(s)
    w2 = np.where(ok, np.asarray(w, float) ** 2, 0.0)
    m = np.ones_like(w2) if weight is None else np.asarray(weight, float)
    A = np.einsum("ni,nj->ij", J * (w2 * m)[:, None], J)
    B = np.einsum("ni,nj->ij", J * (w2 * w2 * np.where(ok, s, 0.0) ** 2 * m)[:, None], J)
    return A, B


def covariance_from_information(I: np.ndarray, mask: np.ndarray | None = None, prior: np.ndarray | None = None) -> np.ndarray:
    """Inverse of the information over the ``mask`` parameters (the others get
    inf); ``prior`` (same shape) is added first. Singular -> inf on the diagonal."""
    I = np.asarray(I, float)
    if prior is not None:
        I = I + prior
    n = I.shape[0]
    mask = np.ones(n, bool) if mask is None else np.asarray(mask, bool)
    cov = np.full((n, n), np.nan)
    cov[np.diag_indices(n)] = np.inf
    sub = I[np.ix_(mask, mask)]
    d = np.sqrt(np.clip(np.diag(sub), 0, None))
    if np.any(d == 0):
        return cov
    S = sub / np.outer(d, d)
    lam = np.linalg.eigvalsh(S)
    if lam[0] <= 1e-13 * lam[-1]:
        return cov
    inv = np.linalg.inv(S) / np.outer(d, d)
    cov[np.ix_(mask, mask)] = inv
    return cov


def sandwich_covariance(A: np.ndarray, B: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """``A^-1 B A^-1`` over the ``mask`` parameters (the others: inf on the diagonal, NaN
    off it), the asymptotic covariance of a least-squares estimator whose weights are not
    the inverse variances (:func:`sandwich_parts`; Huber 1967); ``A`` singular: ``A``'s
    inverse as :func:`covariance_from_information` gives it (inf on the diagonal)."""
    n = np.asarray(A).shape[0]
    mask = np.ones(n, bool) if mask is None else np.asarray(mask, bool)
    Ai = covariance_from_information(A, mask)
    if not np.all(np.isfinite(np.diag(Ai)[mask])):
        return Ai
    Ai = np.where(np.isfinite(Ai), Ai, 0.0)
    cov = Ai @ np.asarray(B, float) @ Ai
    cov[~mask, :] = np.nan
    cov[:, ~mask] = np.nan
    for i in np.flatnonzero(~mask):
        cov[i, i] = np.inf
    return cov


def weak_prior(p: WardParams, factor: float = 10.0) -> np.ndarray:
    """A diagonal information matrix worth a standard deviation of ``factor``
    times each parameter (``factor`` radians for the rotation): negligible next
    to any real design, it keeps a design with no informative sample finite."""
    return np.diag(1.0 / (factor * error_scale(p)) ** 2)


@dataclass
class ExpectedError:
    """Standard errors and relative errors of one material under one design."""

    params: WardParams
    stderr: dict
    relative: dict
    geometric_mean_relative: float
    n_samples: int

    def to_json(self) -> dict:
        def fin(x):
            return None if not math.isfinite(x) else float(x)
        return {"params": self.params.as_dict(), "stderr": {k: fin(v) for k, v in self.stderr.items()},
                "relative": {k: fin(v) for k, v in self.relative.items()},
                "geometric_mean_relative": fin(self.geometric_mean_relative), "n_samples": self.n_samples}


def summarise(p: WardParams, cov: np.ndarray, n_samples: int) -> ExpectedError:
    """Standard errors, relative errors and their geometric mean over the identifiable parameters."""
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    se = np.where(np.isnan(se), np.inf, se)
    rel = se / error_scale(p)
    m = identifiable(p)
    gm = float(np.exp(np.mean(np.log(rel[m])))) if np.all(np.isfinite(rel[m])) and np.all(rel[m] > 0) else math.inf
    return ExpectedError(params=p, stderr=dict(zip(PARAMS, map(float, se))),
                         relative=dict(zip(PARAMS, map(float, rel))), geometric_mean_relative=gm,
                         n_samples=int(n_samples))


def expected_errors(theta_in, theta_out, theta_h, phi_h, cos_in, dist_mm, p: WardParams, noise,
                    weighting: str = "fisher", phi_in=None, phi_out=None, weight=None) -> ExpectedError:
    """Expected standard errors of the Ward parameters of ``p`` measured at the
    given sample angles (radians), incidence cosines and LED distances (mm).

    ``weighting="fisher"``: the Cramer-Rao bound ``I^-1``. ``"mirror"``: the
    sandwich covariance of the fit with thesis eq. 4.82's weights (needs
    ``phi_in`` and ``phi_out``). ``weight`` multiplies every sample's
    contribution (e.g. the number of pixels a subsampled row stands for)."""
    f, J = ward_jacobian(theta_in, theta_out, theta_h, phi_h, p)
    sigma = noise.sigma(f, cos_in, dist_mm)
    m = identifiable(p)
    if weighting == "fisher":
        cov = covariance_from_information(information(J, sigma, weight), m)
    elif weighting == "mirror":
        from glossrig.core.fitting.fit import peak_weight

        if phi_in is None or phi_out is None:
            raise InputError("weighting 'mirror' needs phi_in and phi_out")
        w = peak_weight(theta_in, phi_in, theta_out, phi_out, mode="mirror")
        A, B = sandwich_parts(J, sigma, w, weight)
        cov = sandwich_covariance(A, B, m)
    else:
        raise InputError(f"weighting must be 'fisher' or 'mirror', got {weighting!r}")
    n = int(np.count_nonzero(np.isfinite(sigma)))
    return summarise(p, cov, n)
