"""The gain of every frame of an LED's exposure sequence, and the LED-drift test on them
(thesis 4.3.3, fig. 4.12; issue 14).

An LED's output changes from frame to frame: fast (jitter, which the pipeline's neighbour
correction removes, thesis eq. 4.32-4.38) and slowly (drift, thesis fig. 4.12). Both multiply
every pixel of a frame alike, so the raw series of an LED is

    DN_ep - black = r_p t_e g_e

with one rate r_p per pixel and one gain g_e per frame (:func:`frame_gains`, fitted by
weighted least squares with the EMVA 1288 variances of :class:`.frames.FrameSet`; the gains
are known up to one common factor, fixed at an information-weighted mean of 1). Their
covariance is the inverse of the Gauss-Newton information with the rates *profiled out*
(the Schur complement of the rates' block): a pixel seen in a few frames only tells the
gains of those frames relative to each other, and treating the rates as known understated
the slope's standard error three-fold on synthetic null stacks (a null chi^2 of 17 with 2
degrees of freedom; with the Schur complement the mean over 12 null stacks is 2.2).

**The drift test** (:func:`drift_test`). Drift is a slow trend of the gains in capture
time: per LED, ``g_e = alpha (1 + a tau_e)`` with tau_e the frame's time (minutes) from the
middle of its sequence, fitted by generalised least squares with covariance
``cov(g) + s^2 I``. ``s`` is the frame-to-frame jitter, one value for the rig's LEDs
(they are of one kind), estimated from the data by the method of moments: the pooled
generalised chi^2 of the trend fits equals its degrees of freedom (s = 0 when photon noise
alone explains the scatter, as on an ideal twin capture). The statistic is the sum over the
LEDs of ``(a / se(a))^2``, chi^2 with one degree of freedom per LED when no LED drifts; drift
is significant when it exceeds that distribution's upper tail at the same 4-sigma level as the
marker band's test (:data:`TAIL`, :mod:`.marker_band`): a false-alarm rate of 6.3e-5 a capture
under the noise model.

Why not the held-out gain of the frame space (:mod:`.frames`): its base model has no frame
gains, so a slow drift is scored against every pixel's photon noise, and each pixel's rate,
fitted over the part of the sequence where the pixel is neither dark nor clipped, takes up
most of it. Measured on the eight-LED blind study (validation/diagnose/blind_study_8led.md at
42aabcc): drifts of 0.0056-0.0083 /min gained 0.018-0.089 % held out, under the frame
threshold of 0.13 % for eight slopes. And the frame-to-frame jitter of a real LED (0.5 %,
the twin's ``led_jitter``) is structure that held-out score does not expect. On the gains the
drift is a trend in a short series whose scatter the test measures: on synthetic stacks with a
drift of 0.006 /min the statistic is 44-53 against a bound of 19.3 (two LEDs), and with 0.5 %
jitter and no drift it stays at 0.3-4.3.

Other sensor causes bend the gains too (a black offset, a compression, a shutter error); on
top of them (:mod:`.conditional`) the test runs on the frames with their terms undone
(:func:`linearised`).
"""
from __future__ import annotations

import numpy as np
from scipy.stats import chi2, norm

TEST_Z = 4.0            # the test's level in sigma: the marker band's (:data:`.marker_band.BAND_Z`)
#: the upper tail at which the LEDs' summed chi^2 is significant: the two-sided TEST_Z-sigma tail (6.3e-5)
TAIL = float(2 * norm.sf(TEST_Z))
MIN_FRAMES = 4          # an LED with fewer frames that any pixel sees unclipped has no trend to test
#: the scale degeneracy (gains x k, rates / k) is given this variance along the constant
#: direction in the trend fit: the trend's free intercept takes it, whatever its size
_FREE = 1.0


def frame_gains(Z, T, W, M, iters: int = 20) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gains of the frames of one LED: ``Z`` (n_exp, P) signal above black, ``T`` exposure
    times (n_exp, P), ``W`` weights (1 / variance), ``M`` the frames each pixel is used in.
    Gauss-Newton on the gains with the rates profiled out (module docstring). Returns the
    gains (n_exp,) of the frames any pixel sees (``seen``), their covariance, and ``seen``."""
    WM = np.where(M, W, 0.0)
    seen = np.sum(WM, axis=1) > 0
    Z, T, WM = Z[seen], T[seen], WM[seen]
    g = np.ones(len(Z))
    cov = np.zeros((len(Z), len(Z)))
    for _ in range(iters):
        G = T * g[:, None]
        c = np.sum(WM * G * G, axis=0)
        keep = c > 0
        r = np.where(keep, np.sum(WM * G * Z, axis=0) / np.where(keep, c, 1.0), 0.0)
        X = T * r[None, :]
        score = np.sum(WM * (Z - X * g[:, None]) * X, axis=1)
        B = (WM * X * G)[:, keep]
        info = np.diag(np.sum(WM * X * X, axis=1)) - (B / c[keep]) @ B.T
        cov = np.linalg.pinv(info, rcond=1e-10, hermitian=True)
        step = cov @ score
        g = g + step
        if np.max(np.abs(step)) < 1e-10:
            break
    info_w = np.sum(WM * (T * r[None, :]) ** 2, axis=1)
    k = float(np.sum(info_w * g) / np.sum(info_w))
    return g / k, cov / k ** 2, seen


def linearised(fs, i: int, offset=0.0, gain=None, c=0.0) -> tuple[np.ndarray, np.ndarray]:
    """LED ``i``'s signal with a selected model's terms undone - a black offset subtracted, a
    compression ``x (1 - c x / range)`` inverted, a per-frame gain (shutter error) divided out -
    and the weights carried through (the variance of x is the DN variance over (dz/dx)^2, then over
    the gain squared). The terms are :func:`.frames._linear_pred`'s."""
    z = fs.Z[i] - offset
    W = 1.0 / fs.V[i]
    c = np.asarray(c, float)
    if np.any(c != 0.0):
        cc = np.where(c == 0.0, 1e-12, c)
        disc = np.maximum(1.0 - 4.0 * cc * z / fs.range, 1e-6)
        x = fs.range / (2.0 * cc) * (1.0 - np.sqrt(disc))
        W = W * (1.0 - 2.0 * cc * x / fs.range) ** 2
        z = x
    if gain is not None:
        z = z / gain
        W = W * gain ** 2
    return z, W


def _trend(gs, covs, taus, s2: float):
    """GLS trend fit of every LED's gains at jitter variance ``s2``: per LED (slope, its standard
    error) and the pooled generalised chi^2 with its degrees of freedom."""
    out, chi, dof = [], 0.0, 0
    for g, cv, tau in zip(gs, covs, taus):
        n = len(g)
        S = cv + (s2 + 1e-14) * np.eye(n) + _FREE * np.ones((n, n))
        Si = np.linalg.inv(S)
        A = np.stack([np.ones(n), tau], axis=1)
        C = np.linalg.inv(A.T @ Si @ A)
        b = C @ (A.T @ Si @ g)
        res = g - A @ b
        chi += float(res @ Si @ res)
        dof += n - 2
        out.append((float(b[1] / b[0]), float(np.sqrt(C[1, 1]) / abs(b[0]))))
    return out, chi, dof


def drift_test(fs, terms=None) -> dict | None:
    """The drift test of the module docstring on a :class:`.frames.FrameSet`: every LED's frame
    gains, their trend in capture time, the jitter, and the LEDs' summed chi^2 against its bound.
    ``terms(i) -> dict`` (offset / gain / c of :func:`.frames._linear_pred`): the selected causes'
    terms to undo first (:func:`linearised`); None: the frames as they are. None when no LED has
    :data:`MIN_FRAMES` frames to fit a trend to."""
    gs, covs, taus, leds = [], [], [], []
    for i in range(len(fs.Z)):
        z, W = linearised(fs, i, **(terms(i) if terms is not None else {}))
        g, cov, seen = frame_gains(z, fs.T[i], W, fs.ok[i])
        if seen.sum() < MIN_FRAMES:
            continue
        gs.append(g)
        covs.append(cov)
        taus.append(fs.tau[i][seen, 0])
        leds.append(str(fs.led[i]))
    if not gs:
        return None
    out, chi, dof = _trend(gs, covs, taus, 0.0)
    s2 = 0.0
    if chi > dof:
        # method of moments: the jitter variance at which the pooled chi^2 equals its degrees of
        # freedom (chi^2 falls as s2 grows); bisection on a log scale up to 20 % jitter
        lo, hi = 1e-12, 0.04
        for _ in range(60):
            mid = float(np.sqrt(lo * hi))
            if _trend(gs, covs, taus, mid)[1] > dof:
                lo = mid
            else:
                hi = mid
        s2 = hi
        out, chi, dof = _trend(gs, covs, taus, s2)
    stat = float(sum((a / se) ** 2 for a, se in out))
    bound = float(chi2.isf(TAIL, len(out)))
    return {"slope_per_min": {k: a for k, (a, _) in zip(leds, out)},
            "stderr_per_min": {k: se for k, (_, se) in zip(leds, out)},
            "jitter": float(np.sqrt(s2)), "chi2": stat, "dof": len(out), "bound": bound, "tail": TAIL,
            "passed": bool(stat > bound),
            "rule": "per LED the frame gains' trend in capture time (GLS, rates profiled out, jitter by moments); "
                    "sum over LEDs of (slope / se)^2 against chi^2 with one degree per LED at the 4-sigma tail"}
