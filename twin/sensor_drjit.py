"""The sensor model's noise step in compiled Dr.Jit (LLVM) code: shot noise, full well, read
noise, conversion to DN, black level and (optionally) rounding - per pixel.

:meth:`glossrig.twin.sensor.SensorModel.expose` spends almost all of its time in this step
(issue 19: 57 s of a full-resolution 18-exposure sequence, mostly ``Generator.poisson`` on
24 MP per exposure, plus float64/int64 temporaries and a dozen numpy passes). Here every
pixel is handled by a SIMD lane of compiled code; the distributions are the same, drawn
exactly:

* **Shot noise** ``Poisson(lambda)``, lambda = expected photo-electrons + dark electrons.
  For lambda >= 10 by the transformed rejection method with squeeze, PTRS (W. Hoermann,
  "The transformed rejection method for generating Poisson random variables", Insurance:
  Mathematics and Economics 12, 1993, 39-45) - the algorithm and constants NumPy's own
  ``Generator.poisson`` uses (``random_poisson_ptrs``, with its Stirling-series
  ``random_loggam``); for lambda < 10 by inversion (sequential search of the CDF in
  float64, L. Devroye, "Non-Uniform Random Variate Generation", Springer 1986, X.3.2).
  Both are exact samplers (up to float64 arithmetic), not approximations.
* **Full well** (sensor.py step 4): a pixel with lambda >= :func:`full_well_shortcut` is
  set to the full well without a draw. The Chernoff bound P(X <= n) <= exp(-lambda + n +
  n ln(lambda / n)) (n < lambda) puts the probability that such a pixel would have stayed
  below the full well under exp(-50) ~ 2e-22 - a pixel count of 24 MP x 1e6 frames would
  see it once in 2e7 such captures, and float64 uniforms (2^-53 resolution) cannot
  represent it anyway. It replaces the former cap of lambda at twice the full well.
* **Read noise** ``Normal(0, sigma_r)`` electrons by the Box-Muller transform (G. Box, M.
  Muller, Ann. Math. Statist. 29, 1958) of two float32 uniforms, u1 in (0, 1] so that every
  draw is finite; the uniforms' 2^-24 resolution cuts the normal's tails at 5.8 sigma
  (8e-9 of its mass; 17 e- with the rig's 3 e- read noise), a change of its variance by
  3e-7 relative.

Work layout: a frame is one kernel launch whose lane j takes the pixel pair 2 j, 2 j + 1
(flat index; contiguous loads from the even and odd pixels of :class:`Rate`, one Box-Muller
transform for both read-noise draws); each branch (the shortcut, inversion, PTRS's first try)
runs only in the SIMD packets that need it (``dr.if_stmt``), and the pixels whose first PTRS
try needs the full logarithmic test (about a quarter of those with lambda >= 10) are compacted
(``dr.compress``) and finished in a second launch, so that no packet waits on a few slow
lanes. A sequence hands its radiance to Dr.Jit once (:class:`Rate`,
:meth:`glossrig.twin.sensor.SensorModel.prepare`); an exposure then costs one pass of compiled
code, and its rounded mosaic is written as one UInt32 per pixel pair that NumPy reads as the
uint16 mosaic without a copy (issue 19: the float32 copy and the uint16 conversion per
exposure are gone).

Random streams: every pixel (flat index i = row * W + col) has its own PCG32 generator (M. E.
O'Neill, "PCG: A Family of Simple Fast Space-Efficient Statistically Good Algorithms for
Random Number Generation", HMC-CS-2014-0905) for its Poisson draw, and every pixel pair
(2 j, 2 j + 1) one for the read noise of its two pixels (the cosine of its Box-Muller
transform for pixel 2 j, the sine for 2 j + 1; before issue 19's second round the pairs were
j and j + ceil(n / 2): the same distribution, other draws); a generator's state is a
SplitMix64 hash (G. Steele, D. Lea, C. Flood, "Fast splittable pseudorandom number
generators", OOPSLA 2014) of the frame's 64-bit seed and the index, its increment the
frame's. A pixel's values therefore depend only on the seed and its index - not on the
thread count or the order of evaluation, and a compacted pixel restarts its own stream so its
first PTRS try is the one already made - so the same seed gives the same mosaic bit for bit
on any machine with the LLVM backend.

Dr.Jit's LLVM backend needs libLLVM 19 (``glossrig.twin.mitsuba_env``); where it is
missing :func:`available` is False and the sensor model falls back to its NumPy
reference path (other random draws, the same statistics) with a warning.
"""
from __future__ import annotations

import math

import numpy as np

from glossrig.core.errors import InputError

__all__ = ["available", "noise_dn", "full_well_shortcut", "Rate"]

#: lambda below which the inversion sampler is used (NumPy's switch to PTRS is at 10 too).
SMALL_LAMBDA = 10.0
#: Upper bound on the inversion search: P(Poisson(10) > 200) < 1e-150.
INVERSION_MAX_K = 200.0
#: ln of the probability accepted for the full-well shortcut (module docstring).
SHORTCUT_LOG_P = -50.0

# NumPy's random_loggam coefficients (Stirling series of ln Gamma, distributions.c).
_LOGGAM_A = (8.333333333333333e-02, -2.777777777777778e-03, 7.936507936507937e-04, -5.952380952380952e-04,
             8.417508417508418e-04, -1.917526917526918e-03, 6.410256410256410e-03, -2.955065359477124e-02,
             1.796443723688307e-01, -1.39243221690590e00)
_LN_2PI = 1.8378770664093453

_state: dict = {}


def available() -> bool:
    """Whether Dr.Jit's LLVM backend can run here (libLLVM 19 present; decided before Dr.Jit
    is first imported, as :mod:`glossrig.twin.mitsuba_env` does for Mitsuba)."""
    if "ok" not in _state:
        from .mitsuba_env import llvm19_path

        ok = False
        if llvm19_path() is not None:
            import drjit as dr

            ok = bool(dr.has_backend(dr.JitBackend.LLVM))
        _state["ok"] = ok
    return bool(_state["ok"])


def full_well_shortcut(full_well_e: float, log_p: float = SHORTCUT_LOG_P) -> float:
    """The smallest lambda for which the Chernoff bound on P(Poisson(lambda) < full well) is
    below exp(``log_p``): the root of -lambda + n + n ln(lambda / n) = log_p above n (Newton)."""
    n = float(full_well_e)
    lam = n + math.sqrt(-2.0 * log_p * n)          # the Gaussian estimate (just below the root)
    for _ in range(50):
        f = -lam + n + n * math.log(lam / n) - log_p
        d = -1.0 + n / lam
        step = f / d
        lam -= step
        if abs(step) < 1e-9 * lam:
            break
    return lam


def _splitmix64(x):
    """SplitMix64 finaliser (Steele, Lea & Flood 2014) on a UInt64 array."""
    x = x + 0x9E3779B97F4A7C15
    x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9
    x = (x ^ (x >> 27)) * 0x94D049BB133111EB
    return x ^ (x >> 31)


_MASK64 = (1 << 64) - 1


def _splitmix64_int(x: int) -> int:
    """:func:`_splitmix64` on a Python int (the frame's PCG increment, computed once)."""
    x = (x + 0x9E3779B97F4A7C15) & _MASK64
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & _MASK64
    return x ^ (x >> 31)


def _stream(seed, gidx):
    """The PCG32 generator of the pixels (or pixel pairs) ``gidx`` (UInt64): its state a SplitMix64
    hash of the frame seed and the index (a pseudo-random place in the generator's 2^64 cycle,
    so the streams of a frame's pixels do not overlap in practice), its increment the frame's."""
    import drjit.llvm as L

    rng = L.PCG32()
    rng.state = _splitmix64(gidx ^ seed[0])
    rng.inc = L.UInt64(seed[1])
    return rng


def _loggam(dr, x):
    """ln Gamma(x) for x >= 1 as NumPy's ``random_loggam``: Stirling series at x0 = x + n >= 7,
    then ln Gamma(x) = ln Gamma(x0) - ln(x (x + 1) ... (x0 - 1))."""
    n = dr.select(x < 7.0, dr.floor(7.0 - x), 0.0)
    x0 = x + n
    x2 = 1.0 / (x0 * x0)
    gl0 = _LOGGAM_A[9]
    for c in reversed(_LOGGAM_A[:9]):
        gl0 = gl0 * x2 + c
    gl = gl0 / x0 + 0.5 * _LN_2PI + (x0 - 0.5) * dr.log(x0) - x0
    prod = type(x)(1.0)
    for j in range(1, 8):
        prod = dr.select(n >= j, prod * (x0 - j), prod)
    return gl - dr.log(prod)


def _inversion(lam, rng, p):
    """Poisson(lam) for lam < 10 by sequential search of the CDF in float64 (Devroye 1986,
    X.3.2): X = min{k : U < F(k)}, one uniform. F(0) = exp(-lam) is the frame's constant
    exp(-dark electrons) where lam is the dark signal alone (a pixel that sees no light: the
    background, 65 % of the pixels of LED 9's full-scale render of sample_2_6), computed per
    pixel only in the SIMD packets holding a lit pixel (``dr.if_stmt``)."""
    import drjit as dr
    import drjit.llvm as L

    u = rng.next_float64()
    p0 = dr.if_stmt(args=(lam,), cond=lam != p["dark"], true_fn=lambda lam: dr.exp(-lam),
                    false_fn=lambda lam: dr.zeros(L.Float64, dr.width(lam)) + p["p0_dark"])

    def body(k, pk, cdf, done):
        k1 = k + 1.0
        pk1 = pk * lam / k1
        cdf1 = cdf + pk1
        return (dr.select(done, k, k1), dr.select(done, pk, pk1), dr.select(done, cdf, cdf1),
                done | (u < cdf1) | (k1 >= INVERSION_MAX_K))

    k, _, _, _ = dr.while_loop(state=(dr.zeros(L.Float64, dr.width(lam)), p0, p0, u < p0),
                               cond=lambda k, pk, cdf, done: ~done, body=body, labels=("k", "pk", "cdf", "done"))
    return k, rng


def _ptrs_try(lam, rng, mask):
    """One try of PTRS (Hoermann 1993; the steps and constants of numpy's random_poisson_ptrs):
    the candidate k, whether the squeeze accepts it at once, and the full test's inputs."""
    import drjit as dr

    b = 0.931 + 2.53 * dr.sqrt(lam)
    a = -0.059 + 0.02483 * b
    vr = 0.9277 - 3.6224 / (b - 2.0)
    u = rng.next_float64(mask) - 0.5
    v = rng.next_float64(mask)
    us = 0.5 - dr.abs(u)
    k = dr.floor((2.0 * a / us + b) * u + lam + 0.43)
    return k, (us >= 0.07) & (v <= vr), (a, b, us, v)


def _ptrs_body(lam):
    """One PTRS try as a loop body ``(k, done, rng) -> (k, done, rng)``: the squeeze, and the
    full (logarithmic) acceptance test where the squeeze does not decide (with numpy's
    random_loggam for ln k!), only in the SIMD packets that need it."""
    import drjit as dr
    import drjit.llvm as L

    loglam = dr.log(lam)
    log_invalpha = dr.log(1.1239 + 1.1328 / (0.931 + 2.53 * dr.sqrt(lam) - 3.4))

    def body(k, done, rng):
        kl, quick, (a, b, us, v) = _ptrs_try(lam, rng, ~done)
        reject = (kl < 0.0) | ((us < 0.013) & (v > us))

        def full_test(kl, a, b, us, v):
            kc = dr.maximum(kl, 0.0)
            lhs = dr.log(v / (a / (us * us) + b)) + log_invalpha
            return lhs <= -lam + kc * loglam - _loggam(dr, kc + 1.0)

        slow = dr.if_stmt(args=(kl, a, b, us, v), cond=~done & ~quick & ~reject, true_fn=full_test,
                          false_fn=lambda kl, a, b, us, v: dr.zeros(L.Bool, dr.width(kl)))
        accept = ~done & (quick | (~reject & slow))
        return dr.select(accept, kl, k), done | accept, rng

    return body


def _ptrs(lam, rng):
    """Poisson(lam) for lam >= 10 by PTRS, tries until one is accepted."""
    import drjit as dr
    import drjit.llvm as L

    k, _, rng = dr.while_loop(state=(dr.zeros(L.Float64, dr.width(lam)), dr.zeros(L.Bool, dr.width(lam)), rng),
                              cond=lambda k, done, rng: ~done, body=_ptrs_body(lam), labels=("k", "done", "rng"))
    return k


def _read_noise(seed_r, lane):
    """Standard-normal read-noise draws of the two pixels of ``lane`` (UInt64): one generator
    and one Box-Muller transform (G. Box, M. Muller, Ann. Math. Statist. 29, 1958) per lane,
    its cosine for the lane's first pixel, its sine for the second. u1 lies in (0, 1], so
    every draw is finite; the float32 uniforms cut the tails at 5.8 sigma, beyond which 8e-9
    of the mass lies."""
    import drjit as dr

    rng = _stream(seed_r, lane)
    u1 = 1.0 - rng.next_float32()
    u2 = rng.next_float32()
    r = dr.sqrt(-2.0 * dr.log(u1))
    sin, cos = dr.sincos(2.0 * math.pi * u2)
    return r * cos, r * sin


def _read_dn(z, gidx, width, p):
    """Steps 5-7 without the photo-electrons: read noise / K + the black level of the pixel's
    CFA position."""
    import drjit as dr
    import drjit.llvm as L

    dn = z * (p["read"] * p["inv_k"])
    if "b00" in p:
        g = L.Float64(gidx) + 0.5
        row = dr.floor(g / width)
        col = dr.floor(g - row * width)
        row_odd = (row - 2.0 * dr.floor(row * 0.5)) > 0.5
        col_odd = (col - 2.0 * dr.floor(col * 0.5)) > 0.5
        return dn + dr.select(row_odd, dr.select(col_odd, p["b11"], p["b10"]), dr.select(col_odd, p["b01"], p["b00"]))
    return dn + p["black"]


def _add_electrons(k, rest, p):
    """Steps 4 and 6 for the photo-electron count ``k`` (Float64) added to ``rest`` (read noise
    and black level in DN), then step 9's rounding and clipping where asked for."""
    import drjit as dr
    import drjit.llvm as L

    dn = dr.fma(L.Float(dr.minimum(k, p["full"])), p["inv_k"], rest)
    if p.get("white") is not None:
        dn = dr.clip(dr.round(dn), 0.0, p["white"])
    return dn


def _lam(rate, p):
    import drjit.llvm as L

    return L.Float64(rate * p["scale"]) + p["dark"]


def _first_pass(rate, z, gidx, seed, width, p):
    """One pixel per lane: the full-well shortcut, inversion below lambda = 10 and PTRS's first
    try elsewhere, each only in the SIMD packets that need it (``dr.if_stmt``). Returns the DN
    and whether the pixel's first try needs PTRS's full test (its DN is then read noise and
    black level only, to which :func:`_pending_pass` adds the photo-electrons)."""
    import drjit as dr
    import drjit.llvm as L

    rng = _stream(seed, gidx)
    lam = _lam(rate, p)
    skip = lam >= p["skip"]
    small = lam < SMALL_LAMBDA
    large = ~small & ~skip
    zero = dr.zeros(L.Float64, dr.width(lam))
    k, rng = dr.if_stmt(args=(lam, rng), cond=small, true_fn=lambda lam, rng: _inversion(lam, rng, p),
                        false_fn=lambda lam, rng: (zero, rng))

    def first_try(lam, rng):
        kl, quick, _ = _ptrs_try(lam, rng, dr.ones(L.Bool, dr.width(lam)))
        return kl, quick, rng

    kl, quick, rng = dr.if_stmt(args=(lam, rng), cond=large, true_fn=first_try,
                                false_fn=lambda lam, rng: (zero, dr.zeros(L.Bool, dr.width(lam)), rng))
    k = dr.select(skip, p["full"], dr.select(small, k, kl))
    rest = _read_dn(z, gidx, width, p)
    pending = large & ~quick
    return dr.select(pending, rest, _add_electrons(k, rest, p)), pending


def _pending_pass(dn, idx, rate, parity: int, seed, p) -> None:
    """PTRS to the end (Hoermann 1993) for the lanes ``idx`` whose pixel 2 j + ``parity``'s first
    try needs the full test, compacted (``dr.compress``) so that no SIMD packet waits on a few
    slow lanes; their Poisson stream starts afresh, so the first try is the very one
    :func:`_first_pass` made. Adds their photo-electrons to ``dn``. The values are evaluated
    before the scatter, so that ``dn`` is updated in place (a scatter into an array its own
    operand still reads would copy the whole array first)."""
    import drjit as dr
    import drjit.llvm as L

    if not dr.width(idx):
        return
    k = _ptrs(_lam(dr.gather(L.Float, rate, idx), p), _stream(seed, 2 * L.UInt64(idx) + parity))
    value = _add_electrons(k, dr.gather(L.Float, dn, idx), p)
    dr.eval(value)
    dr.scatter(dn, value, idx)


def _frame(rate: Rate, seeds, width, p, packed: bool) -> np.ndarray:
    """DN of a frame (flat pixel indices 0..n-1, n = ``rate.size``). Lane j takes the pixel pair
    2 j, 2 j + 1 (``rate.a``, ``rate.b``: contiguous loads, one read-noise transform for both
    pixels). ``packed`` (the values are rounded integers in [0, 65535]): the pair is stored as
    one UInt32, low half first, whose memory NumPy views as the uint16 mosaic without a copy;
    else float32 DN, interleaved."""
    import drjit as dr
    import drjit.llvm as L

    m = dr.width(rate.a)
    lane = dr.arange(L.UInt64, m)
    even = 2 * lane
    za, zb = _read_noise(seeds[1], lane)
    dn_a, pend_a = _first_pass(rate.a, za, even, seeds[0], width, p)
    dn_b, pend_b = _first_pass(rate.b, zb, even + 1, seeds[0], width, p)
    dr.eval(dn_a, pend_a, dn_b, pend_b)
    _pending_pass(dn_a, dr.compress(pend_a), rate.a, 0, seeds[0], p)
    _pending_pass(dn_b, dr.compress(pend_b), rate.b, 1, seeds[0], p)
    if packed:
        pair = L.UInt32(dn_a) | (L.UInt32(dn_b) << 16)
        dr.eval(pair)
        return pair.numpy().view("<u2")[:rate.size]
    out = np.empty(2 * m, np.float32)
    out[0::2] = dn_a.numpy()
    out[1::2] = dn_b.numpy()
    return out[:rate.size]


class Rate:
    """A frame's expected photo-electrons per unit exposure (``SensorModel`` step 1 with
    t (11/N)^2 gain = 1), held in Dr.Jit memory as the even and odd pixels (flat index) that
    :func:`_frame`'s lanes read, so a sequence converts its radiance once, not once per
    exposure."""

    def __init__(self, mosaic: np.ndarray):
        import drjit.llvm as L

        e = np.asarray(mosaic, np.float32)
        if e.ndim != 2 or e.size < 1:
            raise InputError(f"expected electrons must be a non-empty (H, W) array, got shape {e.shape}")
        self.shape = e.shape
        self.size = e.size
        flat = e.reshape(-1)
        m = (flat.size + 1) // 2
        odd = np.zeros(m, np.float32)
        odd[:flat.size // 2] = flat[1::2]
        self.a, self.b = L.Float(np.ascontiguousarray(flat[0::2])), L.Float(odd)


def noise_dn(expected_e, *, seed: int, dark_e: float, full_well_e: float, read_e: float,
             inv_k: float, black_2x2: np.ndarray, white: float | None = None, scale: float = 1.0) -> np.ndarray:
    """Raw values ((H, W), black level included) of a frame whose expected photo-electrons per
    pixel are ``scale`` times ``expected_e`` (float32 (H, W), or a :class:`Rate`): sensor.py
    steps 3-7 (Poisson(e + dark), full well, + Normal(0, read), / K, + black) as float32, and
    with ``white`` (at most 65535) also step 9's rounding and clipping to [0, white], as uint16
    (a view of Dr.Jit's memory, no copy). ``seed``: 64-bit frame seed (module
    docstring: streams per pixel)."""
    import drjit as dr
    import drjit.llvm as L

    if not available():
        raise RuntimeError("Dr.Jit's LLVM backend is not available (libLLVM 19 missing)")
    rate = expected_e if isinstance(expected_e, Rate) else Rate(expected_e)
    h, w = rate.shape
    bl = np.asarray(black_2x2, np.float32).reshape(2, 2)

    def op(cls, v):
        return dr.opaque(cls, v)

    p = {"dark": op(L.Float64, float(dark_e)), "p0_dark": op(L.Float64, math.exp(-float(dark_e))),
         "full": op(L.Float64, float(full_well_e)),
         "skip": op(L.Float64, full_well_shortcut(full_well_e)), "read": op(L.Float, float(read_e)),
         "inv_k": op(L.Float, float(inv_k)), "scale": op(L.Float, float(scale)),
         "white": None if white is None else op(L.Float, float(white))}
    if bl.min() == bl.max():
        p["black"] = op(L.Float, float(bl[0, 0]))
    else:
        p.update({f"b{i}{j}": op(L.Float, float(bl[i, j])) for i in range(2) for j in range(2)})
    seeds = tuple((op(L.UInt64, s), op(L.UInt64, _splitmix64_int(s) | 1))      # (hash key, PCG increment)
                  for s in (int(seed) & _MASK64, (int(seed) ^ 0x9E3779B97F4A7C15) & _MASK64))   # Poisson, read noise
    return _frame(rate, seeds, op(L.Float64, float(w)), p, packed=white is not None and white <= 65535).reshape(h, w)
