"""Frame-space and pixel-space causes: the sensor and the LEDs seen in the raw DN
(thesis 4.3.1-4.3.3; EMVA 1288 for the sensor model).

Base model per pixel: ``DN - black = rate * t`` over the exposures where the pixel
is not clipped, with the variance of a photon-transfer sensor (shot + read
noise). Each cause bends that line in its own way:

* black_level_offset b: ``DN - black = b + rate t``. The offset is the same at
  every exposure, so it stands out against the short exposures of dark pixels.
* sensor_nonlinearity c: ``DN - black = x (1 - c x / (white - black))``, x = rate t:
  a deficit that grows with the signal level, the same at any exposure time.
* shutter_error delta: ``DN - black = rate (t + delta)``: the true exposure time differs
  from the nominal one by a constant, most in relative terms at the shortest times.
* channel_response c_R, c_G, c_B: the non-linearity with its own c per colour channel (the
  channels' readout paths differ); named only where it beats the common non-linearity.
* led_drift a: ``DN - black = rate t (1 + a tau)`` with tau the frame's time (minutes)
  from the middle of its LED's sequence: a gain trend against capture order that
  the same pixel shows at every signal level (the LED warms, thesis fig. 4.12).
* hot_pixels (pixel space): a pixel's dark current adds the same rate (DN/s)
  under every LED, so a hot pixel stands out against its same-colour
  neighbours at the same place in every LED's rate image.

Each cause is fitted alone; the frame-space causes a single effect makes significant beside
the one that explains it are then explained away by forward stepwise selection
(:mod:`.conditional`).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import median_filter
from scipy.optimize import minimize_scalar

from glossrig.core.diagnose.catalogue import MAX_PIXELS, CauseResult, chi2
from glossrig.core.workers import InWorker, one_blas_thread
from glossrig.core.diagnose.data import FrameData

CLIP_MARGIN = 0.95          # a DN above CLIP_MARGIN * the effective white is treated as clipped
HOT_Z = 6.0                 # a hot pixel stands this many sigma above its neighbours in every training LED
ISOLATED_Z = 3.0            # ... while its 5x5 neighbourhood stays within this many sigma
#: search bounds of the frame-space causes' parameters (shutter_error's: :func:`shutter_bounds`)
BOUNDS = {"black_level_offset": (-50.0, 50.0), "sensor_nonlinearity": (-0.1, 0.3),
          "channel_response": (-0.1, 0.3), "led_drift": (-0.02, 0.02)}


def effective_white(dn, white):
    """The level where pixels really saturate: a compressive sensor clips below the stated white
    level, so the highest DN the frames reach (99.99th percentile) is taken when lower."""
    return float(min(white, np.percentile(dn, 99.99)))


def channel_white(lf, white) -> np.ndarray:
    """(h, w) effective white of every pixel of an LED's crop: :func:`effective_white` of the pixels
    of its colour channel. Each channel reaches the ADC through its own path, so where the channels'
    responses differ (channel_response) each saturates at its own level: measured on a synthetic
    stack whose G channel compresses by 5 %, saturated G pixels read 14731 DN against a clip test
    at 0.95 x the 15520 the other channels reach, and were taken as unclipped."""
    col = lf.colours()
    out = np.empty(col.shape)
    for k in np.unique(col):
        sel = col == k
        out[sel] = effective_white(lf.dn[:, sel], white)
    return out


def unclipped(dn, white):
    """Exposures of a pixel that are safely below saturation, decided without their own noise.

    Taking ``dn < margin * white`` of the frame itself drops exactly the frames whose noise
    pushed them up, which biases the longest usable exposure of every pixel low: a fake gain
    trend along the exposure sequence (measured: -0.0037 / min on a null capture). An exposure
    is kept when the next longer one (exposures sorted by time, axis 0) is unclipped, so the
    decision rests on another frame's noise; the longest exposure is kept on its own test.
    """
    below = dn < CLIP_MARGIN * white
    ok = np.empty_like(below)
    ok[:-1] = below[:-1] & below[1:]
    ok[-1] = below[-1]
    return ok


class FrameSet:
    """Pixels sampled from each LED's crop: Z (n_exp, P) signal above the stated black."""

    def __init__(self, fd: FrameData, seed: int = 0, max_pixels: int | None = None):
        """``max_pixels``: pixels sampled per LED (default: this module's MAX_PIXELS, read now)."""
        rng = np.random.default_rng(seed)
        cap = MAX_PIXELS if max_pixels is None else int(max_pixels)
        self.fd = fd
        self.Z, self.T, self.ok, self.tau, self.led, self.colour = [], [], [], [], [], []
        rng_dn = fd.white - float(np.mean(fd.leds[0].black))
        self.range = rng_dn
        for lf in fd.leds:
            n_exp, h, w = lf.dn.shape
            flat = lf.dn.reshape(n_exp, -1)
            idx = np.arange(h * w)
            if idx.size > cap:
                idx = np.sort(rng.choice(idx.size, cap, replace=False))
            dn = flat[:, idx].astype(np.float64)
            z = dn - lf.black.ravel()[idx][None, :]
            ok = unclipped(dn, channel_white(lf, fd.white).ravel()[idx][None, :])
            self.Z.append(z)
            self.ok.append(ok)
            self.T.append(lf.exposure_s[:, None] * np.ones((1, idx.size)))
            self.tau.append(((lf.time_s - 0.5 * (lf.time_s.min() + lf.time_s.max())) / 60.0)[:, None]
                            * np.ones((1, idx.size)))
            self.led.append(lf.led)
            self.colour.append(lf.colours().ravel()[idx])
        self.n_exp = [z.shape[0] for z in self.Z]
        #: a label per sequence: the LED's id, with its rotation where the capture has several (an LED is
        #: then sequenced once per rotation, each with its own drift)
        several = len({lf.rotation for lf in fd.leds}) > 1
        self.label = [f"{lf.led}@{lf.rotation:g}deg" if several else str(lf.led) for lf in fd.leds]
        # Fixed variances (EMVA 1288) from the base model's prediction: a chi^2 whose variance moves
        # with the prediction, sum (z - mu)^2 / V(mu), is minimised by mu too high by ~1 / (2 K) DN
        # (Pearson's chi^2 for Poisson counts; K = 0.69 e-/DN here: 0.7 DN). Measured on null
        # captures, twin and synthetic alike: b = 0.71 DN and a drift of -0.006 / min. With V fixed,
        # every model is compared by weighted least squares with the same weights.
        self.V = []
        for i in range(len(self.Z)):
            W = 1.0 / fd.variance(self.Z[i])
            r = _fit_rates(self.Z[i], self.T[i], W, self.ok[i])
            W = 1.0 / fd.variance(r[None, :] * self.T[i])
            r = _fit_rates(self.Z[i], self.T[i], W, self.ok[i])
            self.V.append(fd.variance(r[None, :] * self.T[i]))

    def folds(self):
        """Even / odd exposure index: two folds interleaved in exposure time and capture order."""
        out = []
        for parity in (0, 1):
            tr, te = [], []
            for n in self.n_exp:
                e = (np.arange(n) % 2 == parity)[:, None]
                tr.append(e)
                te.append(~e)
            out.append((tr, te))
        return out


def _fit_rates(Z, T, W, M, offset=0.0, gain=None, WM=None):
    """Per-pixel weighted least-squares rate of (Z - offset) = rate * T * gain over mask M.
    ``WM``: the weights with zeros outside M (``np.where(M, W, 0)``), when the caller has them."""
    G = T if gain is None else T * gain
    WG = (np.where(M, W, 0.0) if WM is None else WM) * G
    # W G (Z - offset) where M, 0 elsewhere: the products of summing np.where(M, W * G * (Z - offset), 0)
    # with three passes over the (exposures x pixels) arrays fewer; on the synthetic frames of
    # tests/test_diagnose.py every cause's held-out error is the same to 5e-14 relative
    num = np.sum(WG * (Z - offset), axis=0)
    den = np.sum(WG * G, axis=0)
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)


def _score(fs: FrameSet, model, fold):
    """Held-out chi^2 (pooled over LEDs) of ``model(i, train_mask) -> prediction (n_exp, P)``."""
    tr, te = fold
    ss, n = 0.0, 0
    for i in range(len(fs.Z)):
        pred = model(i, tr[i] & fs.ok[i])
        m = te[i] & fs.ok[i]
        ss += float(np.sum(np.where(m, (fs.Z[i] - pred) ** 2 / fs.V[i], 0.0)))
        n += int(m.sum())
    return ss / max(n, 1)


def _linear_pred(fs, i, M, offset=0.0, gain=None, c=0.0):
    """Per-pixel rate fitted over mask M (weights 1 / V of :class:`FrameSet`); prediction
    (n_exp, P) of the signal above black."""
    return _line(fs.Z[i], fs.T[i], 1.0 / fs.V[i], M, fs.range, offset, gain, c)


def _line(Z, T, W, M, rng, offset=0.0, gain=None, c=0.0):
    """:func:`_linear_pred` on arrays: ``Z`` (n_exp, P) signal above black, ``T`` exposure
    times, ``W`` weights, ``M`` mask, ``rng`` the signal range (white - black); ``c`` the
    compression at white, a scalar or one value per pixel (P,)."""
    G = T if gain is None else T * gain
    WM = np.where(M, W, 0.0)
    r = _fit_rates(Z, T, W, M, offset, gain, WM=WM)
    if np.all(np.asarray(c) == 0.0):
        return offset + r[None, :] * G
    Zo = Z - offset
    for _ in range(4):
        # non-linear: Gauss-Newton step on the per-pixel rate of z = x - c x^2 / range
        x = r[None, :] * G
        f = x - c * x * x / rng
        J = G * np.maximum(1 - 2 * c * x / rng, 0.2)
        WJ = WM * J             # W J where M, 0 elsewhere (as in _fit_rates)
        num = np.sum(WJ * (Zo - f), axis=0)
        den = np.sum(WJ * J, axis=0)
        step = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
        r = r + np.clip(step, -0.5 * np.abs(r) - 1.0, 0.5 * np.abs(r) + 1.0)
    x = r[None, :] * G
    return offset + x - c * x * x / rng


def _scalar_fit(cost, bounds, grid_n=21):
    grid = np.linspace(*bounds, grid_n)
    vals = np.array([cost(p) for p in grid])
    k = int(np.argmin(vals))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, grid_n - 1)]
    return float(minimize_scalar(cost, bounds=(lo, hi), method="bounded").x), grid, vals


def _train_cost(fs, pred_fn, fold):
    tr, _ = fold
    ss, n = 0.0, 0
    for i in range(len(fs.Z)):
        M = tr[i] & fs.ok[i]
        pred = pred_fn(i, M)
        ss += float(np.sum(np.where(M, (fs.Z[i] - pred) ** 2 / fs.V[i], 0.0)))
        n += int(M.sum())
    return ss / max(n, 1)


def _train_and_score(fs, model, fold) -> tuple[float, float]:
    """:func:`_train_cost` and :func:`_score` of ``model`` from one prediction per LED."""
    tr, te = fold
    s_tr = s_te = 0.0
    n_tr = n_te = 0
    for i in range(len(fs.Z)):
        M = tr[i] & fs.ok[i]
        r2 = (fs.Z[i] - model(i, M)) ** 2 / fs.V[i]
        T = te[i] & fs.ok[i]
        s_tr += float(np.sum(np.where(M, r2, 0.0)))
        s_te += float(np.sum(np.where(T, r2, 0.0)))
        n_tr += int(M.sum())
        n_te += int(T.sum())
    return s_tr / max(n_tr, 1), s_te / max(n_te, 1)


def _frame_cause(fs: FrameSet, name, doc, pname, unit, bounds: tuple[float, float], make_pred, grid_n=13) -> CauseResult:
    """A global scalar cause in frame space: fitted per fold on the training exposures."""
    base_err = ext_err = 0.0
    gains, est = [], []
    prof = np.zeros(grid_n)
    grid = np.linspace(*bounds, grid_n)
    for fold in fs.folds():
        e0 = _score(fs, lambda i, M: _linear_pred(fs, i, M), fold)
        held: dict[float, float] = {}

        def cost(q, fold=fold, held=held):
            # one prediction per value: its training cost (the search) and held-out error (the profile)
            train_cost, held[float(q)] = _train_and_score(fs, make_pred(q), fold)
            return train_cost

        p, _, _ = _scalar_fit(cost, bounds, grid_n)
        e1 = held[float(p)] if float(p) in held else _score(fs, make_pred(p), fold)
        prof += np.array([held[float(q)] for q in grid]) / 2
        base_err += e0 / 2
        ext_err += e1 / 2
        gains.append((e0 - e1) / e0)
        est.append(p)
    allf = ([np.ones_like(o) for o in fs.ok], [np.ones_like(o) for o in fs.ok])
    cost_all = lambda q: _train_cost(fs, make_pred(q), allf)
    p, _, _ = _scalar_fit(cost_all, bounds, grid_n)
    h = (bounds[1] - bounds[0]) * 1e-3
    n = sum(int(o.sum()) for o in fs.ok)
    curv = n * (cost_all(p + h) - 2 * cost_all(p) + cost_all(p - h)) / h ** 2
    se = math.sqrt(2 * cost_all(p) / curv) if curv > 0 else float("nan")
    return CauseResult(name, "frames", doc, {pname: p, "unit": unit, "fold_estimates": est}, {pname: se},
                       ext_err, base_err, gains, 1, profile={"grid": grid.tolist(), "error": prof.tolist()},
                       magnitude=p)


def frame_causes(fd: FrameData | FrameSet, log=None) -> list[CauseResult]:
    """Every frame- and pixel-space cause, fitted and scored, then the frame-space causes the
    strongest explains blocked (:func:`glossrig.core.diagnose.conditional.explain_away`: forward
    stepwise selection; the conditional gains in their ``params["conditional"]``). ``fd``: the frames, or a
    :class:`FrameSet` of them already built (its pixel sample and fixed variances are then
    shared with :func:`glossrig.core.diagnose.residuals.frame_structure`). ``log``
    (callable(str)) gets one line per cause as it finishes (progress). Runs with one BLAS
    thread (:func:`glossrig.core.workers.one_blas_thread`)."""
    with one_blas_thread():
        return _frame_causes(fd, log)


def _frame_causes(fd: FrameData | FrameSet, log=None) -> list[CauseResult]:
    from glossrig.core.progress import Elapsed

    took = Elapsed()
    fs = fd if isinstance(fd, FrameSet) else FrameSet(fd)
    fd = fs.fd
    out: list[CauseResult] = []

    def add(r: CauseResult) -> None:
        out.append(r)
        if log is not None:
            log(f"  {r.name} fitted and scored ({took})")

    doc = ("Black level offset: the sensor's true black level differs from the one the raw file states by b DN "
           "(temperature, firmware). Every frame carries b on top of rate * t, so the relative error is largest "
           "in short exposures and dark pixels and dies away with the signal.")
    add(_frame_cause(fs, "black_level_offset", doc, "b_dn", "DN", BOUNDS["black_level_offset"],
                     lambda b: (lambda i, M: _linear_pred(fs, i, M, offset=b))))
    doc = ("Compressive sensor response (full-well and ADC non-linearity, EMVA 1288 sec. 8): the signal x above "
           "black is read as x (1 - c x / (white - black)); the deficit grows with the signal level and is the "
           "same at any exposure time, so long and short exposures of one pixel disagree in proportion to DN.")
    add(_frame_cause(fs, "sensor_nonlinearity", doc, "c", "relative compression at white",
                     BOUNDS["sensor_nonlinearity"],
                     lambda c: (lambda i, M: _linear_pred(fs, i, M, c=c))))
    add(channel_response_cause(fs, out[-1]))
    from glossrig.core.diagnose.frame_gains import gain_series

    series = gain_series(fs)        # the frame gains' fit, shared by the shutter's and the drift's tests
    for r in out:                   # and the base of the check of the three sensor causes fitted so far
        r.check = _sensor_check(fs, r, series)
        if r.check is not None and not r.check["passed"] and r.significant_without_check:
            r.note = (r.note + "; " if r.note else "") + (
                f"its structure does not survive a free gain per frame (chi^2 drop {r.check['chi2']:.1f} against "
                f"{r.check['bound']:.1f}): an LED's frame-to-frame jitter can make it")
    add(shutter_cause(fs, series))
    add(_drift_cause(fs, series))
    for r in out[-2:]:
        if r.check is not None and not r.check["passed"] and r.significant_without_check:
            r.note = (r.note + "; " if r.note else "") + (
                f"its test passes, but the frames' gains carry structure common to every LED at each exposure time "
                f"beyond the trends and the shutter term (chi^2 {r.check['chi2']:.1f} against {r.check['bound']:.1f}): "
                "a camera effect outside the catalogue, or a sensor cause's, not this cause")
    add(hot_pixel_cause(fd))
    from glossrig.core.diagnose.conditional import explain_away

    explain_away(fs, out)
    if log is not None:
        log(f"  frame-space causes conditioned on the strongest (forward stepwise) ({took})")
    return out


CHANNEL_NAMES = ("R", "G", "B")


def _sensor_check(fs: FrameSet, r: CauseResult, series) -> dict | None:
    """The check of sensor cause ``r`` (black offset, compression, channel response) on the frame
    gains (:func:`glossrig.core.diagnose.frame_gains.sensor_check`): its terms at its estimate on all
    exposures (``params``) undone and the gains refitted, against ``series`` (the frames as they are)."""
    from glossrig.core.diagnose.conditional import term, theta
    from glossrig.core.diagnose.frame_gains import gain_series, sensor_check

    t = term(fs, r.name)
    if t is None or series is None:
        return None
    th = theta(r.params[t.param])
    return sensor_check(series, gain_series(fs, lambda i: t.kw(i, th), camera=False), len(th))


def channel_response_cause(fs: FrameSet, common: CauseResult) -> CauseResult:
    """Per-channel response error: each colour channel compresses by its own c_k (R, G, B)."""
    doc = ("Per-channel response error: the sensor's response is linear for the pipeline, but each colour "
           "channel of a real camera reaches the ADC through its own path - the colour pixels of a Bayer sensor "
           "sit on separate column amplifiers and readout channels, and a camera may apply a per-channel analog "
           "(white-balance) gain before the ADC - so the channels leave linearity at different signal levels "
           "(EMVA 1288 measures the linearity error per colour channel for this reason). Model: the signal x above "
           "black of a pixel of colour k is read as x (1 - c_k x / (white - black)), one c_k per channel, fitted "
           "on the even (odd) exposures and scored on the others. The pixels of a colour are independent of the "
           "others' (a rate per pixel), so each c_k is fitted alone. A common non-linearity is the special case "
           "c_R = c_G = c_B: this cause is named only when it beats sensor_nonlinearity held out by more than "
           "its own threshold (two parameters more), otherwise it is blocked by it. A per-channel gain alone is "
           "not seen in the raw series (each pixel's rate absorbs it) and cancels in the sample / reference "
           "ratio.")
    bounds = BOUNDS["channel_response"]
    # each colour's pixels of each LED, sliced once: (Z, T, W, ok)
    parts = [[(fs.Z[i][:, s], fs.T[i][:, s], 1.0 / fs.V[i][:, s], fs.ok[i][:, s], s)
              for s in (fs.colour[i] == k for k in range(3))] for i in range(len(fs.Z))]
    base_err = ext_err = 0.0
    gains, est = [], []
    for fold in fs.folds():
        tr, _ = fold
        e0 = _score(fs, lambda i, M: _linear_pred(fs, i, M), fold)
        ck = np.zeros(3)
        for k in range(3):
            if not any(p[k][4].any() for p in parts):
                continue

            def cost(q, k=k, tr=tr):
                ss = 0.0
                for i, p in enumerate(parts):
                    Z, T, W, ok, s = p[k]
                    M = tr[i] & ok
                    ss += float(np.sum(np.where(M, (Z - _line(Z, T, W, M, fs.range, c=q)) ** 2 * W, 0.0)))
                return ss
            ck[k] = _scalar_fit(cost, bounds, 13)[0]
        e1 = _score(fs, lambda i, M, ck=ck: _linear_pred(fs, i, M, c=ck[fs.colour[i]]), fold)
        base_err += e0 / 2
        ext_err += e1 / 2
        gains.append((e0 - e1) / e0)
        est.append(ck)
    c_mean = np.mean(est, axis=0)
    params: dict[str, object] = {"c": {n: float(v) for n, v in zip(CHANNEL_NAMES, c_mean)},
                                 "unit": "relative compression at white",
              "fold_estimates": [{n: float(v) for n, v in zip(CHANNEL_NAMES, e)} for e in est]}
    stderr = {"c": {n: float(abs(a - b) / 2) for n, a, b in zip(CHANNEL_NAMES, est[0], est[1])}}
    vs = (common.error - ext_err) / common.error if common.error > 0 else 0.0
    params["gain_over_common"] = vs
    r = CauseResult("channel_response", "frames", doc, params, stderr, ext_err, base_err, gains, 3,
                    magnitude=float(np.max(c_mean) - np.min(c_mean)))
    r.note = "magnitude = spread of c over the channels; fold spread as uncertainty"
    if not vs > r.threshold - common.threshold:
        r.blocked_by = common.name
        if r.significant:
            r.note += (f"; a common non-linearity explains as much (held-out error {r.error:.6g} vs "
                       f"{common.error:.6g}): not named as a per-channel error")
    return r


def shutter_cause(fs: FrameSet, series=None) -> CauseResult:
    """Exposure-time (shutter) error: the true exposure is ``t + delta`` for the nominal t. ``series``: the
    frame gains' fit (:func:`.frame_gains.gain_series`) its test reads (None: fitted here)."""
    doc = ("Exposure-time (shutter) error: a focal-plane or leaf shutter opens and closes in a finite time, so "
           "the true exposure differs from the nominal one by a near-constant delta (ISO 516 defines the "
           "effective exposure time by the shutter's opening and closing; measured offsets are tens of "
           "microseconds). DN - black = rate (t + delta): the relative error delta / t is largest at the "
           "shortest times and the same at every signal level and pixel, unlike a black offset (additive in DN, "
           "largest for dark pixels) or a non-linearity (a function of the DN level). Tested on the gains of the "
           "frames, the same for every LED, beside each LED's drift (glossrig.core.diagnose.frame_gains).")
    from glossrig.core.diagnose.frame_gains import gain_series, shutter_test

    r = _frame_cause(fs, "shutter_error", doc, "delta_s", "seconds added to every nominal exposure",
                     shutter_bounds(fs),
                     lambda d: (lambda i, M: _linear_pred(fs, i, M, gain=(fs.T[i] + d) / fs.T[i])))
    from glossrig.core.diagnose.frame_gains import camera_check

    r.test = shutter_test(gain_series(fs) if series is None else series)
    r.check = camera_check(r.test)
    if r.test is not None:
        r.params["delta_s"], r.stderr["delta_s"] = r.test["delta_s"], r.test["stderr_s"]
        r.magnitude = r.test["delta_s"]
        r.note = ("delta and its standard error from the frame gains' shutter term, significance from its test "
                  f"(chi^2 {r.test['chi2']:.1f} against {r.test['bound']:.1f}); fold_estimates: the per-pixel fits "
                  "of the held-out score")
    return r


def shutter_bounds(fs: FrameSet) -> tuple[float, float]:
    """Search bounds of the shutter error delta: -0.5 to 2 times the shortest exposure time."""
    tmin = float(min(np.min(t) for t in fs.T))
    return (-0.5 * tmin, 2.0 * tmin)


def _drift_cause(fs: FrameSet, series=None) -> CauseResult:
    """LED drift, its held-out gain in frame space and its test on the frame gains' fit ``series``
    (:func:`.frame_gains.gain_series`; None: fitted here)."""
    doc = ("LED drift (thesis 4.3.3, fig. 4.12): the LED's output changes slowly while its exposure sequence is "
           "taken (warm-up, temperature), a gain 1 + a tau with tau the frame's time from the middle of the "
           "sequence. Every pixel of a frame shares the gain, whatever its signal level: the residual follows "
           "capture order, not DN. Fitted per LED (a in 1/min) on the gains of the frames, against the "
           "frame-to-frame jitter those gains show (glossrig.core.diagnose.frame_gains).")
    bounds = BOUNDS["led_drift"]
    base_err = ext_err = 0.0
    gains = []
    per_led: dict[str, list[float]] = {}
    fold_est = []           # per fold: the slope of every LED sequence, in FrameSet order
    for fold in fs.folds():
        tr, te = fold
        e0 = _score(fs, lambda i, M: _linear_pred(fs, i, M), fold)
        slopes = []
        for i in range(len(fs.Z)):
            def cost(a, i=i, tr=tr):
                M = tr[i] & fs.ok[i]
                pred = _linear_pred(fs, i, M, gain=1 + a * fs.tau[i])
                return float(np.sum(np.where(M, (fs.Z[i] - pred) ** 2 / fs.V[i], 0.0)))
            a, _, _ = _scalar_fit(cost, bounds, 11)
            slopes.append(a)
        e1 = _score(fs, lambda i, M, slopes=slopes: _linear_pred(fs, i, M, gain=1 + slopes[i] * fs.tau[i]), fold)
        base_err += e0 / 2
        ext_err += e1 / 2
        gains.append((e0 - e1) / e0)
        fold_est.append([float(a) for a in slopes])
        for i, a in enumerate(slopes):
            per_led.setdefault(fs.label[i], []).append(a)
    from glossrig.core.diagnose.frame_gains import drift_test, gain_series

    test = drift_test(gain_series(fs) if series is None else series)
    led_slopes: dict[str, float]
    if test is None:
        led_slopes = {k: float(np.mean(v)) for k, v in per_led.items()}
        params: dict = {"gain_slope_per_min": led_slopes, "unit": "1/min", "fold_estimates": fold_est}
        stderr = {"gain_slope_per_min": {k: float(abs(v[0] - v[1]) / 2) for k, v in per_led.items()}}
        note = "magnitude = largest |gain slope| (1/min); fold spread as uncertainty; no frame-gain series to test"
    else:
        led_slopes = test["slope_per_min"]
        params = {"gain_slope_per_min": led_slopes, "unit": "1/min", "fold_estimates": fold_est,
                  "jitter": test["jitter"]}
        stderr = {"gain_slope_per_min": test["stderr_per_min"]}
        note = ("slopes and standard errors from the frame gains' trend, significance from its test "
                f"(chi^2 {test['chi2']:.1f} against {test['bound']:.1f}, {test['dof']} LEDs; jitter "
                f"{test['jitter']:.2%}); fold_estimates: the per-pixel fits of the held-out score; "
                "magnitude = largest |gain slope| (1/min)")
    mag = float(max(abs(v) for v in led_slopes.values()))
    from glossrig.core.diagnose.frame_gains import camera_check

    r = CauseResult("led_drift", "frames", doc, params, stderr, ext_err, base_err, gains, len(fs.Z),
                    magnitude=mag, test=test, check=camera_check(test))
    r.note = note
    return r


def rate_maps(fd: FrameData, parity: int | None = None):
    """Per LED: full-crop rate (DN/s) from all unclipped exposures (or those of one index
    parity) and its variance."""
    out = []
    for lf in fd.leds:
        z = lf.dn.astype(np.float64) - lf.black[None]
        ok = unclipped(lf.dn, effective_white(lf.dn, fd.white))
        if parity is not None:
            ok &= (np.arange(len(ok)) % 2 == parity)[:, None, None]
        t = lf.exposure_s[:, None, None]
        w = 1.0 / fd.variance(z)
        den = np.sum(np.where(ok, w * t * t, 0.0), axis=0)
        rate = np.sum(np.where(ok, w * t * z, 0.0), axis=0) / np.maximum(den, 1e-30)
        out.append((rate, 1.0 / np.maximum(den, 1e-30)))
    return out


def _neighbour_excess(rate, var):
    """Rate minus the 3x3 median of its own CFA colour, normalised by noise + 2 % of the local level."""
    med = np.empty_like(rate)
    for di in range(2):
        for dj in range(2):
            med[di::2, dj::2] = median_filter(rate[di::2, dj::2], size=3, mode="nearest")
    ex = rate - med
    sig = np.sqrt(var + (0.02 * np.abs(med)) ** 2)
    return ex, sig


def _is_spike(ex, sig, rate):
    """HOT_Z sigma above the same-colour neighbours, and isolated: no other pixel of the 5x5
    window around it (any colour) more than ISOLATED_Z sigma above or 2 ISOLATED_Z below its own
    neighbours (a hot pixel in a neighbour's median window pushes that neighbour's excess down
    by up to ~3.5 sigma; an edge leaves deep negative excess on its dark side).

    Measured on a twin capture with hot pixels (scale 0.25, 2e-4 of the pixels): of the
    spikes above 6 sigma, true hot pixels have neighbours within 1.7 sigma (90th percentile)
    while the ~350 spurious ones per LED (sample edges, marker corners) have neighbours at a
    median 10 sigma: a dark current is one pixel, scene detail is not."""
    z = ex / sig
    hi = np.full_like(z, -np.inf)
    lo = np.full_like(z, np.inf)
    for di in range(-2, 3):
        for dj in range(-2, 3):
            if di or dj:
                zz = np.roll(np.roll(z, di, 0), dj, 1)
                hi, lo = np.maximum(hi, zz), np.minimum(lo, zz)
    return (z > HOT_Z) & (hi < ISOLATED_Z) & (lo > -2 * ISOLATED_Z)


def _consistent(excesses):
    """A dark current adds the same DN/s under every LED; scene detail scales with each LED's light."""
    e = np.stack(excesses)
    return (e.max(axis=0) - e.min(axis=0)) < 0.25 * np.abs(e).max(axis=0)


def _hot_set(excesses):
    """Hot pixels of some LEDs' excess maps [(ex, sig), ...]: isolated spikes in every map
    sharing one dark current D (DN/s, the median spike). Returns (mask, D)."""
    spikes = np.all([_is_spike(e, s, None) for e, s in excesses], axis=0)
    ex = np.median([e for e, _ in excesses], axis=0)
    if not (spikes & (ex > 0)).any():
        return np.zeros_like(spikes), 0.0
    # D: the mode of the spikes' heights (densest +-12 % window). Hot pixels of one dark current
    # form a tight cluster; on a single training LED the other isolated spikes (render fireflies,
    # measured up to 1e5 DN/s) spread over decades and would drag a median anywhere.
    lg = np.sort(np.log10(ex[spikes & (ex > 0)]))
    count = np.searchsorted(lg, lg + 0.05, side="right") - np.searchsorted(lg, lg - 0.05, side="left")
    k = int(np.argmax(count))
    D = float(10 ** np.median(lg[np.abs(lg - lg[k]) <= 0.05]))
    sig = np.max([s for _, s in excesses], axis=0)
    return spikes & (np.abs(ex - D) < np.maximum(HOT_Z * sig, 0.25 * D)), D


def hot_pixel_cause(fd: FrameData) -> CauseResult:
    doc = ("Hot pixels: a fraction of the sensor's pixels has a dark current D far above the nominal one "
           "(lattice defects). The extra charge grows with exposure time like light, so the HDR rate of the pixel "
           "is raised by the same D (DN/s) under every LED: an isolated spike against its same-colour neighbours, "
           "at the same place and of the same height in every LED's image, while scene detail (edges, marker "
           "corners) is extended and scales with each LED's light. Model: a set of pixels sharing one D, found "
           "under every LED in the even (odd) exposures and predicted in the odd (even) ones. The fraction is the number found divided by the "
           "pixels where a spike of D would be found (HOT_Z sigma and isolated), i.e. corrected for the "
           "pixels whose scene is too bright to show it.")
    maps = rate_maps(fd)
    ex = [_neighbour_excess(r, v) for r, v in maps]
    n = len(ex)
    base_err = ext_err = 0.0
    gains = []
    if n < 2:
        return CauseResult("hot_pixels", "pixels", doc, {"fraction": 0.0}, {"fraction": float("nan")}, 1.0, 1.0,
                           [0.0], 1, identifiable=False, note="needs two LEDs or more (same spike under each)")
    # each half's excess maps once: every half is the training half of one fold and the held-out
    # half of the other (they were computed twice, 4 of the 5 rate_maps passes over the full crop)
    halves = [[_neighbour_excess(r, v) for r, v in rate_maps(fd, parity)] for parity in (0, 1)]
    for parity in (0, 1):
        # pixel set and D from one half of the exposures (every LED: the spike must be the same
        # under each), scored on the other half; splitting by LED instead leaves one training
        # LED with two, and a single LED cannot tell a hot pixel from an LED-specific spike
        # (render fireflies, a shadow edge): measured, held-out gain -65 at a 1.5e-4 fraction
        cand, D = _hot_set(halves[parity])
        held = halves[1 - parity]
        e0 = float(np.mean([chi2(e, s) for e, s in held]))
        e1 = float(np.mean([chi2(e - D * cand, s) for e, s in held]))
        base_err += e0 / 2
        ext_err += e1 / 2
        gains.append((e0 - e1) / e0)
    cand, D = _hot_set(ex)
    # pixels where a spike of height D passes the test in every LED whatever the noise
    # (3 sigma above HOT_Z): the fraction is counted there (detection efficiency)
    visible = np.all([(D / s > HOT_Z + 3) for _, s in ex], axis=0) if D > 0 else np.zeros_like(cand)
    n_vis = max(int(visible.sum()), 1)
    frac = float((cand & visible).sum() / n_vis) if D > 0 else 0.0
    se = float(math.sqrt(max(cand.sum(), 1)) / n_vis)
    r = CauseResult("hot_pixels", "pixels", doc, {"fraction": frac, "n_pixels": int(cand.sum()),
                                                 "dark_current_e_s": D * fd.e_per_dn, "visible_pixels": n_vis,
                                                 "unit": "fraction of pixels"},
                    {"fraction": se}, ext_err, base_err, gains, 1, magnitude=frac)
    r.note = ("one dark current D shared by the hot pixels (1 parameter); the pixel set is measured on the "
              "training exposures under every LED; split: even / odd exposures")
    return r


def frame_stage(sample_dir, measured, log=None, max_pixels: int | None = None):
    """The whole frame-space stage: the sample's raw frames in the measured crops
    (:func:`glossrig.core.diagnose.data.load_frames`), one :class:`FrameSet` of them, every
    frame- and pixel-space cause (:func:`frame_causes`) and the linear sensor's residual
    structure (:func:`glossrig.core.diagnose.residuals.frame_structure`) on that same pixel
    sample (it was built twice before), and the veil the dark pixels of each LED's crop read
    (:func:`glossrig.core.diagnose.stray_light.dark_veil`: stray light's frame-space signature).
    ``measured``: anything with the measurement's ``geometry`` (rotation -> crop and white-patch
    mask); ``max_pixels`` as :class:`FrameSet`'s. The structure also holds the frame gains' structure
    common to the LEDs per exposure time (:func:`glossrig.core.diagnose.frame_gains.camera_entry`, under
    ``frame_gains.CAMERA_KEY``). Returns (causes, structure, veil)."""
    from glossrig.core.diagnose.data import load_frames
    from glossrig.core.diagnose.frame_gains import CAMERA_KEY, camera_entry
    from glossrig.core.diagnose.residuals import frame_structure
    from glossrig.core.diagnose.stray_light import dark_veil

    fd = load_frames(sample_dir, measured)
    fs = FrameSet(fd, max_pixels=max_pixels)
    causes = frame_causes(fs, log)
    structure = frame_structure(fs)
    cam = camera_entry(causes)
    if cam is not None:
        structure[CAMERA_KEY] = cam
    return causes, structure, dark_veil(fd, measured.geometry)


class FrameStage(InWorker):
    """:func:`frame_stage` run in one worker process (:class:`glossrig.core.workers.InWorker`),
    started at construction, beside the BRDF-space causes in the calling process: on a 2-core
    machine the two halves of the diagnosis then share the cores instead of taking turns (the
    frame stage reads its raws and needs only the crops of the measurement, not its tables).
    :meth:`result` waits for it and shuts the worker down; ``with`` stops it on an error."""

    def __init__(self, sample_dir, measured):
        from types import SimpleNamespace

        # the pixel budget is this process's (a caller may have lowered MAX_PIXELS; the worker imports
        # the module afresh and would not see it)
        super().__init__(frame_stage, str(sample_dir), SimpleNamespace(geometry=measured.geometry),
                         max_pixels=MAX_PIXELS)
