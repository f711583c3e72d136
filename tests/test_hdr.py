"""Radiometric calibration (glossrig.core.radiometry.hdr, glossrig.core.radiometry.patch; thesis 4.3.3):
repeat combination, neighbour correction (and the sign error of eq. 4.36), the
thesis regression against the inverse-variance HDR estimator, patch
normalisation, input validation. Synthetic sequences come from the twin's sensor
model (Poisson shot noise, read noise, 14-bit, black 600, white 15520)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from glossrig.core.calibration.demosaic import channel_index
from glossrig.core.errors import InputError
from glossrig.core.radiometry.hdr import (HI, LO, NEIGHBOUR_WINDOW, TOO_BRIGHT, TOO_DARK, TOO_FEW, VALID, NoiseModel,
                               combine_repeats, hdr_from_stack, hdr_ml, hdr_thesis, neighbour_correct, stack_frames,
                               stream_stack)
from glossrig.core.radiometry.patch import normalise_by_patch
from glossrig.core.calibration.raw import RawFrame, linearize_mosaic
from glossrig.twin.sensor import SensorModel, frame_rng


@pytest.fixture(scope="module")
def sensor(rig):
    return SensorModel.from_rig(rig)


@pytest.fixture(scope="module")
def times(rig):
    return np.array(rig.exposure_times_s)


@pytest.fixture(scope="module")
def noise(rig):
    return NoiseModel.from_rig(rig)


def radiance_for_rates(sensor, rates, iso, aperture):
    """(H, W, 3) radiance giving each pixel of ``rates`` (fraction of white-black
    per second, in its own CFA colour) at ``iso``/``aperture``; true rates back
    (dark current included)."""
    h, w = rates.shape
    ch = channel_index((h, w), sensor.cfa)
    k = np.asarray(sensor.electrons_per_radiance_s_f11) * (11.0 / aperture) ** 2
    e_per_unit = (sensor.white_level - sensor.black_level[0]) * sensor.conversion_gain(iso)
    rad = np.zeros((h, w, 3), np.float32)
    for c in range(3):
        rad[..., c] = np.where(ch == c, rates * e_per_unit / k[c], 0.0)
    truth = (sensor.expected_electrons(rad, 1.0, aperture).astype(np.float64) + sensor.dark_current_e_s) / e_per_unit
    return rad, truth


def twin_sequence(sensor, rates, times, iso, aperture, repeats=3, gains=None, seed=0):
    """Linearised (repeats, n, H, W) mosaics exposed by the twin's sensor model;
    ``gains`` (repeats, n) multiplies the light of each frame (LED jitter)."""
    rad, truth = radiance_for_rates(sensor, rates, iso, aperture)
    n = len(times)
    out = np.empty((repeats, n) + rates.shape, np.float32)
    for r in range(repeats):
        for i, t in enumerate(times):
            g = 1.0 if gains is None else float(gains[r, i])
            mos = sensor.expose(rad, t, iso, aperture, frame_rng(seed, r * n + i), gain=g)
            out[r, i] = linearize_mosaic(mos, sensor.black_2x2(), sensor.white_level)
    return out, truth


def log_rates(shape, lo_exp, hi_exp, seed):
    return 10 ** np.random.default_rng(seed).uniform(lo_exp, hi_exp, shape)


# ------------------------------------------------------------------ eq. 4.31

def test_combine_repeats_is_the_mean_and_flags_any_saturated_repeat():
    a = np.array([[[[0.2, 1.0]]], [[[0.4, 0.98]]]], np.float32)     # (2 repeats, 1 exposure, 1, 2)
    mean, clipped = combine_repeats(a)
    assert mean.shape == (1, 1, 2)
    np.testing.assert_allclose(mean[0, 0], [0.3, 0.99], rtol=1e-6)
    # the mean 0.99 < 1 would pass the thesis's test (eq. 4.39) though one repeat clipped
    assert clipped[0, 0].tolist() == [False, True]


def _repeats(m: int, seed: int, shape=(2, 23, 31)) -> np.ndarray:
    """m float32 repeats spanning 30 decades, a quarter of the pixels at or above 1 in some
    repeats, a few exactly 1.0 (linearize's saturated value). For m = 8 and 16, pixel
    (1, 0, 0) is 0.5, 2^-25, then 2^-54 in every later repeat: added in repeat order each
    2^-54 is half a float64 ulp of 0.5 + 2^-25 and rounds away (to even), so the sum stays
    0.5 + 2^-25 and the mean (0.5 + 2^-25) / m is a float32 tie that rounds to 0.5 / m;
    the exact sum, or numpy's pairwise order (blocks of 8 partial sums), keeps the 2^-54s
    and rounds up one float32 ulp."""
    rng = np.random.default_rng(seed)
    a = (10.0 ** rng.uniform(-30, 0, (m, *shape))).astype(np.float32)
    a[rng.random(a.shape) < 0.25 / m] = np.float32(1.0)
    a[:, 0, :2, :2] = np.float32(1.5)                        # saturated in every repeat
    if m in (8, 16):
        a[:, 1, 0, 0] = [0.5, 2.0 ** -25] + [2.0 ** -54] * (m - 2)
    return a


@pytest.mark.parametrize("m", [1, 2, 3, 8, 9, 16])
def test_combine_repeats_equals_numpys_mean_of_the_stack_bit_for_bit(m):
    """Eq. 4.31 taken one repeat at a time (issue 19) gives the plain numpy mean of the stacked
    repeats (float64 over axis 0 of the C-ordered stack, rounded to float32) exactly, and its
    saturation mask, whether the repeats come as an (m, n, H, W) array, a list or a generator.
    For m = 8, 16 one pixel tells the orders of addition apart (see _repeats): another order,
    or the exactly rounded mean, would fail this test."""
    a = _repeats(m, seed=m)
    ref = a.mean(axis=0, dtype=np.float64).astype(np.float32)
    for sat_level in (1.0, 0.5):
        ref_clip = (a >= sat_level).any(axis=0)
        for linear in (a, list(a), (np.array(r) for r in a)):
            mean, clipped = combine_repeats(linear, saturation=sat_level)
            assert mean.dtype == np.float32 and clipped.dtype == bool and mean.shape == a.shape[1:]
            np.testing.assert_array_equal(mean, ref)
            np.testing.assert_array_equal(clipped, ref_clip)
        assert clipped[0, :2, :2].all() and 0 < clipped.sum() < clipped.size
    if m in (8, 16):
        import math
        assert mean[1, 0, 0] == np.float32(0.5 / m)
        exact = np.float32(math.fsum(a[:, 1, 0, 0].astype(np.float64).tolist()) / m)
        assert exact == np.nextafter(np.float32(0.5 / m), np.float32(1))


def test_combine_repeats_holds_one_repeat_at_a_time():
    """A generator's repeats are dropped once added: when the generator makes repeat k, no
    earlier repeat is still referenced (weak references to them are dead), so the memory is
    one repeat and the accumulators, never the stack (issue 19: full-resolution extraction)."""
    import weakref

    a = _repeats(6, seed=1)
    made: list[weakref.ref] = []
    alive_at_make: list[int] = []

    def lazily():
        for r in a:
            alive_at_make.append(sum(w() is not None for w in made))
            x = np.array(r)            # a fresh array, like a repeat linearised on demand
            made.append(weakref.ref(x))
            yield x
            del x

    mean, clipped = combine_repeats(lazily())
    assert alive_at_make == [0] * 6 and len(made) == 6
    np.testing.assert_array_equal(mean, a.mean(axis=0, dtype=np.float64).astype(np.float32))
    np.testing.assert_array_equal(clipped, (a >= 1.0).any(axis=0))


@pytest.mark.parametrize("bad, match", [
    (np.zeros((2, 3, 4), np.float32), "repeats, exposures, H, W"),
    (np.zeros((0, 2, 3, 4), np.float32), "empty input"),
    (np.zeros((1, 2, 3, 4), np.uint16), "linearize"),
    (np.full((1, 2, 3, 4), np.nan, np.float32), "NaN"),
    ([np.zeros((2, 3, 4), np.float32), np.zeros((2, 3, 5), np.float32)], r"repeat 1 has shape \(2, 3, 5\)"),
    ([np.zeros((3, 4), np.float32)], "exposures, H, W"),
    ([np.zeros((2, 3, 4), np.float32), np.full((2, 3, 4), np.inf, np.float32)], r"repeat 1\) holds NaN"),
    ((r for r in ()), "no repeats"),
])
def test_combine_repeats_rejects_bad_input(bad, match):
    with pytest.raises(InputError, match=match):
        combine_repeats(bad)


# ------------------------------------------------------------------ eq. 4.32-4.38

def noise_free_sequence(times, gains, seed=0, shape=(120, 160)):
    """Noise-free combined images g_k t_k L (clipped to 1) of a scene L spanning
    six decades, so every exposure has many well-exposed pixels."""
    L = log_rates(shape, -2.5, 3.6, seed)
    y = np.clip(gains[:, None, None] * times[:, None, None] * L[None], 0, 1).astype(np.float32)
    return y, L


def test_printed_eq_4_36_squares_the_jitter_and_the_fixed_factor_removes_it(times):
    rng = np.random.default_rng(4)
    g = 1 + rng.normal(0, 0.01, times.size)
    y, L = noise_free_sequence(times, g)
    ref = times.size // 2
    ok = (y > 0.01) & (y < 0.98)        # away from 1, where a scaled value would clip

    fixed, rep_f = neighbour_correct(y, times, method="robust")
    assert rep_f.reference == ref and not rep_f.skipped
    for k in range(times.size):
        got = fixed[k][ok[k]] / (times[k] * L[ok[k]])
        np.testing.assert_allclose(got, g[ref], rtol=2e-5)        # every image now carries g_ref

    printed, rep_p = neighbour_correct(y, times, method="thesis")
    # the algebra of the docstring, pair (ref, ref+1): fac = g_b / g_a, output gain g_b^2 / g_a
    b = ref + 1
    assert rep_p.factor[b] == pytest.approx(g[b] / g[ref], rel=1e-5)
    got = printed[b][ok[b]] / (times[b] * L[ok[b]])
    np.testing.assert_allclose(got, g[b] ** 2 / g[ref], rtol=2e-5)
    # and the chain makes the spread of image gains worse than doing nothing
    gain_printed = np.array([np.median(printed[k][ok[k]] / (times[k] * L[ok[k]])) for k in range(times.size)])
    before = np.abs(g / g[ref] - 1).max()
    after_printed = np.abs(gain_printed / g[ref] - 1).max()
    assert after_printed > 1.5 * before


def chain_sigma(rep, k: int, e_white: float, repeats: int, lo: float = NEIGHBOUR_WINDOW[0]) -> float:
    """Standard error of image k's correction factor from the shot noise of its chain.

    Each link's ratio uses ``rep.pixels`` pixels whose values lie above ``lo`` of the white
    level (``lo``: neighbour_correct's window, NEIGHBOUR_WINDOW): a pixel's relative shot
    noise is at most 1 / sqrt(lo e_white repeats) (the
    repeats are averaged), a ratio of two such pixels has sqrt(2) times that, and a
    median-type estimator costs a factor ~1.25 (its efficiency for normal errors) over
    the mean: sigma_link <= 1.25 sqrt(2) / sqrt(lo e_white repeats pixels). The links from
    the reference to k add in quadrature. An upper bound (pixels sit between lo and hi)."""
    var, j = 0.0, k
    while j != rep.reference:
        var += 2 * 1.2533 ** 2 / (lo * e_white * repeats * rep.pixels[j])
        j = rep.partner[j]
    return float(np.sqrt(var))


def test_neighbour_correction_removes_led_jitter_on_twin_data(sensor, rig, times):
    rates = log_rates((96, 128), -2.5, 2.6, 1)
    gains = 1 + np.random.default_rng(2).normal(0, 0.005, (3, times.size))      # thesis-like jitter
    lin, _ = twin_sequence(sensor, rates, times, rig.sequence_iso, rig.sequence_aperture, gains=gains)
    comb, clipped = combine_repeats(lin)
    _, rep = neighbour_correct(comb, times, clipped=clipped)
    gbar = gains.mean(axis=0)
    ref = rep.reference
    done = [k for k in range(times.size) if k != ref and k not in rep.skipped]
    assert len(done) >= 12
    before = np.abs(gbar[done] / gbar[ref] - 1)
    after = np.abs(gbar[done] * rep.factor[done] / gbar[ref] - 1)
    # what is left is the ratio estimates' own shot noise: each image within 4 of its
    # chain's standard errors, and the mean square within chi-square's 99.9th percentile
    # (one dof per corrected image: 2.45 for 16); the uncorrected jitter is far outside that bound
    e_white = (sensor.white_level - float(np.mean(sensor.black_2x2()))) / sensor.conversion_gain(rig.sequence_iso)
    sig = np.array([chain_sigma(rep, k, e_white, repeats=lin.shape[0]) for k in done])
    bound = chi2.ppf(0.999, len(done)) / len(done)
    assert np.all(after < 4 * sig), (after / sig).round(2)
    assert np.mean((after / sig) ** 2) < bound
    assert np.mean((before / sig) ** 2) > 2 * bound


def naive_median_chain(y, t, lo=0.1, hi=0.9):
    """Chain of median ratios over pixels chosen on the pair's own noisy values
    (what the robust method avoids): returns the factors."""
    n = y.shape[0]
    ref = n // 2
    out = y.astype(np.float64).copy()
    fac = np.ones(n)
    for a, b in [(i, i + 1) for i in range(ref, n - 1)] + [(i, i - 1) for i in range(ref, 0, -1)]:
        sel = (out[a] > lo) & (out[a] < hi) & (out[b] > lo) & (out[b] < hi)
        if sel.sum() < 100:
            continue
        fac[b] = (t[b] / t[a]) / np.median(out[b][sel] / out[a][sel])
        out[b] *= fac[b]
    return fac


def test_robust_ratio_does_not_drift_along_the_chain(times):
    # no jitter at all: every factor should be 1; choosing pixels on the pair's own
    # noisy values biases each ratio and the bias compounds towards the chain's ends
    rng = np.random.default_rng(5)
    rates = 10 ** rng.uniform(-3, 2, 200_000)
    ne, m = 10257.5, 3
    lam = rates[None] * times[:, None] * ne
    y = np.zeros(lam.shape)
    for _ in range(m):
        y += np.clip((rng.poisson(lam) + rng.normal(0, 3.0, lam.shape)) / ne, 0, 1)
    y = (y / m).astype(np.float32)[:, None, :]
    _, rep = neighbour_correct(y, times, clipped=y >= 1)
    used = [k for k in range(times.size) if rep.partner[k] >= 0 and rep.pixels[k] >= 1000]
    assert len(used) >= 13
    assert np.abs(rep.factor[used] - 1).max() < 1e-3
    # links the fallbacks of _gain_ratio make on few pixels (frame 0.001 s: 180) carry the
    # shot noise of their ratio, ~2 %/sqrt(pixels) per pixel pair at values near 0.1, no drift
    weak = [k for k in range(times.size) if 0 <= rep.partner[k] and rep.pixels[k] < 1000]
    assert all(abs(rep.factor[k] - 1) < 0.03 / np.sqrt(rep.pixels[k]) for k in weak)
    naive = naive_median_chain(y, times)
    assert abs(naive[-1] - 1) > 8e-4 and abs(naive[-1] - 1) > 3 * abs(rep.factor[-1] - 1)


def test_neighbour_correct_skips_images_without_enough_pixels(times):
    y, _ = noise_free_sequence(times, np.ones(times.size), shape=(6, 10))     # 60 pixels: < 100 everywhere
    out, rep = neighbour_correct(y, times)
    assert sorted(rep.skipped) == [k for k in range(times.size) if k != rep.reference]
    np.testing.assert_array_equal(out, y)


@pytest.mark.parametrize("kwargs, match", [
    (dict(exposure_s=[1.0, 0.5, 2.0]), "strictly increasing"),
    (dict(exposure_s=[0.5, 1.0]), "3 images but exposure times"),
    (dict(method="mean"), "method"),
    (dict(reference=7), "reference index"),
    (dict(clipped=np.zeros((3, 2, 2), bool)), "clipped mask"),
])
def test_neighbour_correct_rejects_bad_input(kwargs, match):
    args = dict(images=np.full((3, 4, 4), 0.5, np.float32), exposure_s=[0.5, 1.0, 2.0])
    args.update(kwargs)
    with pytest.raises(InputError, match=match):
        neighbour_correct(args.pop("images"), args.pop("exposure_s"), **args)


# ------------------------------------------------------------------ eq. 4.39-4.44 vs hdr_ml

@pytest.fixture(scope="module")
def four_decades(sensor, rig, times):
    """Twin sequence of rates 0.01..100 /s (4 decades; all above 0.033 /s saturate at
    30 s, all above 1.05 /s at 1 s), 3 repeats, no LED jitter."""
    rates = log_rates((128, 128), -2, 2, 7)
    lin, truth = twin_sequence(sensor, rates, times, rig.sequence_iso, rig.sequence_aperture, seed=3)
    comb, clipped = combine_repeats(lin)
    return rates, truth, comb, clipped


def test_hdr_ml_is_unbiased_across_four_decades_including_saturating_pixels(four_decades, times, noise):
    rates, truth, comb, clipped = four_decades
    assert clipped[-1].mean() > 0.8 and clipped[12].mean() > 0.4          # most pixels saturate at long exposures
    res = hdr_ml(comb, times, noise, repeats=3, clipped=clipped)
    assert (res.status == VALID).all() and np.isfinite(res.rate).all()
    err = res.rate / truth - 1
    for d in range(-2, 2):
        sel = (rates >= 10.0 ** d) & (rates < 10.0 ** (d + 1))
        bias = err[sel].mean()
        se = err[sel].std() / np.sqrt(sel.sum())
        assert abs(bias) < 0.01                       # the requirement
        assert abs(bias) < 0.002 and abs(bias) < 5 * se + 5e-4
    # the variance estimate describes the actual scatter
    z = (res.rate - truth) / np.sqrt(res.variance)
    assert 0.9 < z.std() < 1.1


def test_hdr_ml_has_lower_error_than_the_printed_regression(four_decades, times, noise):
    rates, truth, comb, clipped = four_decades
    ml = hdr_ml(comb, times, noise, repeats=3, clipped=clipped).rate / truth - 1
    th = hdr_thesis(comb, times) / truth - 1
    assert np.all(hdr_thesis(comb, times) != 0)
    rms = lambda e: float(np.sqrt(np.mean(e ** 2)))
    assert rms(ml) < 0.8 * rms(th)
    for d in range(-2, 2):
        sel = (rates >= 10.0 ** d) & (rates < 10.0 ** (d + 1))
        assert np.percentile(np.abs(ml[sel]), 95) < np.percentile(np.abs(th[sel]), 95)
        assert rms(ml[sel]) < rms(th[sel])


def test_choosing_exposures_on_the_expected_value_avoids_selection_bias(times):
    # every pixel's rate puts the expected value of the 1 s exposure at the upper limit
    rng = np.random.default_rng(11)
    hi, ne, m, P = 0.95, 10257.5, 3, 120_000
    rates = hi / times[12] * np.exp(rng.uniform(-0.03, 0.03, P))
    lam = rates[None] * times[:, None] * ne
    y = np.zeros(lam.shape)
    for _ in range(m):
        y += np.clip((rng.poisson(lam) + rng.normal(0, 3.0, lam.shape)) / ne, 0, 1)
    y /= m
    v = (y > 0.002) & (y < hi)                                 # chosen on the noisy sample
    naive = (y * v).sum(0) / (times[:, None] * v).sum(0)
    res = hdr_ml(y[:, None, :].astype(np.float32), times, NoiseModel(ne, 3.0 / ne), repeats=m, hi=hi)
    naive_bias = float(np.mean(naive / rates - 1))
    ml_bias = float(np.nanmean(res.rate[0] / rates - 1))
    assert naive_bias < -1e-4
    assert abs(ml_bias) < 6e-5


def test_pixels_never_validly_exposed_are_nan_with_a_reason(sensor, rig, times, noise):
    rates = np.array([[0.0, 0.0, 2e4, 2e4], [0.5, 0.5, 0.5, 0.5]])        # black, blinding, ordinary
    lin, truth = twin_sequence(sensor, rates, times, rig.sequence_iso, rig.sequence_aperture)
    comb, clipped = combine_repeats(lin)
    res = hdr_ml(comb, times, noise, repeats=3, clipped=clipped)
    assert (res.status[0, :2] == TOO_DARK).all() and (res.status[0, 2:] == TOO_BRIGHT).all()
    assert np.isnan(res.rate[0]).all() and np.isnan(res.variance[0]).all() and (res.n_valid[0] == 0).all()
    assert (res.status[1] == VALID).all() and np.isfinite(res.rate[1]).all()
    np.testing.assert_allclose(res.rate[1], 0.5, rtol=0.02)
    few = hdr_ml(comb, times, noise, repeats=3, clipped=clipped, min_valid=15)
    assert (few.status[1] == TOO_FEW).all() and np.isnan(few.rate[1]).all()
    counts = res.reason_counts()
    assert counts["valid"] == 4 and sum(counts.values()) == 8 and len(counts) == 3
    th = hdr_thesis(comb, times)[0]
    assert (th[2:] == 0).all()                                          # the thesis's 0 reads as black
    # black pixels: eq. 4.39 keeps only the positive read-noise excursions (0 < SI), so the thesis
    # reports a spurious signal far above the true dark-current rate
    assert (th[:2] > 10 * truth[0, :2]).all()


def test_noise_model_matches_the_twin_sensor(sensor, rig, noise):
    R = sensor.white_level - sensor.black_level[0]
    for y in (0.001, 0.1, 0.9):
        dn2 = sensor.variance_dn(y * R, rig.sequence_iso, 0.0)
        assert noise.variance(y) * R ** 2 == pytest.approx(dn2, rel=1e-9)
    assert noise.variance(0.5, repeats=3) == pytest.approx(noise.variance(0.5) / 3)


@pytest.mark.parametrize("kwargs, match", [
    (dict(noise=None), "NoiseModel"),
    (dict(lo=0.5, hi=0.4), "lo < hi"),
    (dict(repeats=0), "repeats"),
    (dict(images=np.full((3, 2, 2), np.inf, np.float32)), "NaN or infinite"),
    (dict(exposure_s=[0.5, 0.5, 2.0]), "strictly increasing"),
    (dict(exposure_s=[0.0, 0.5, 2.0]), "positive"),
])
def test_hdr_ml_rejects_bad_input(kwargs, match, noise):
    args = dict(images=np.full((3, 2, 2), 0.5, np.float32), exposure_s=[0.5, 1.0, 2.0], noise=noise)
    args.update(kwargs)
    with pytest.raises(InputError, match=match):
        hdr_ml(args.pop("images"), args.pop("exposure_s"), args.pop("noise"), **args)


def test_noise_model_rejects_nonsense():
    with pytest.raises(InputError, match="electrons_full_scale"):
        NoiseModel(0.0, 1e-4)
    with pytest.raises(InputError, match="white level"):
        NoiseModel.from_sensor(white=500, black=600, iso=100, electrons_per_dn_iso100=2.2, read_noise_e=3)


# ------------------------------------------------------------------ stack_frames (eq. 4.31 from raw frames)

def frame(path, mosaic, exposure, iso=320):
    return RawFrame(path=path, mosaic=mosaic, cfa=np.array([[0, 1], [1, 2]], np.int8),
                    black=np.full((2, 2), 600, np.float32), white=15520.0, exposure_s=exposure, iso=iso,
                    aperture=11.0, timestamp=None, camera="twin")


def sequence_frames(sensor, rig, times, repeats=2, shape=(16, 16)):
    rad, truth = radiance_for_rates(sensor, log_rates(shape, -1, 1, 9), rig.sequence_iso, rig.sequence_aperture)
    frames, reps = [], []
    for r in range(repeats):
        for i, t in enumerate(times):
            mos = sensor.expose(rad, t, rig.sequence_iso, rig.sequence_aperture, frame_rng(1, r * 100 + i))
            frames.append(frame(f"seq_rep{r}_e{i:02d}.dng", mos, float(t)))
            reps.append(r)
    return frames, reps, truth


def test_stack_frames_sorts_combines_and_feeds_the_estimator(sensor, rig, times, noise):
    frames, reps, truth = sequence_frames(sensor, rig, times)
    order = np.random.default_rng(0).permutation(len(frames))
    stack = stack_frames([frames[i] for i in order], [reps[i] for i in order], exposures_s=times)
    assert stack.images.shape == (times.size, 16, 16) and stack.repeats == 2
    np.testing.assert_array_equal(stack.exposure_s, times)
    k = 5
    expected = (linearize_mosaic(frames[k].mosaic, 600, 15520) + linearize_mosaic(frames[times.size + k].mosaic,
                                                                                   600, 15520)) / 2
    np.testing.assert_allclose(stack.images[k], expected, rtol=1e-6)
    assert stack.files[k] == ["seq_rep0_e05.dng", "seq_rep1_e05.dng"]
    res = hdr_from_stack(stack, noise)
    assert np.isfinite(res.rate).all()
    assert abs(np.mean(res.rate / truth - 1)) < 0.01


def test_stack_frames_names_the_file_of_a_missing_exposure(sensor, rig, times):
    frames, reps, _ = sequence_frames(sensor, rig, times, shape=(4, 4))
    drop = times.size + 3                                   # repeat 1, exposure 3
    with pytest.raises(InputError, match=r"seq_rep0_e03\.dng: repeat 1 lacks exposure\(s\) 0\.002 s"):
        stack_frames(frames[:drop] + frames[drop + 1:], reps[:drop] + reps[drop + 1:])
    with pytest.raises(InputError, match=r"seq_rep1_e03\.dng: repeat 0 lacks exposure\(s\) 0\.002 s of the exposure"):
        stack_frames(frames[:3] + frames[4:], reps[:3] + reps[4:], exposures_s=times)


def test_stack_frames_rejects_repeats_that_disagree(sensor, rig, times):
    frames, reps, _ = sequence_frames(sensor, rig, times, shape=(4, 4))
    k = times.size + 6
    bad = list(frames)
    bad[k] = frame("odd.dng", frames[k].mosaic, 0.0200)
    with pytest.raises(InputError, match=r"odd\.dng: exposure 0\.02 s \(repeat 1\) matches no exposure"):
        stack_frames(bad, reps)
    bad = list(frames)
    bad[k] = frame("twice.dng", frames[k].mosaic, float(times[7]))
    with pytest.raises(InputError, match=r"repeat 1 has exposure 0\.0333 s twice \(also twice\.dng\)"):
        stack_frames(bad, reps)
    bad = list(frames)
    bad[k] = frame("iso.dng", frames[k].mosaic, float(times[6]), iso=640)
    with pytest.raises(InputError, match=r"iso\.dng: ISO 640"):
        stack_frames(bad, reps)
    bad = list(frames)
    bad[k] = frame("crop.dng", frames[k].mosaic[:2], float(times[6]))
    with pytest.raises(InputError, match=r"crop\.dng: crop size"):
        stack_frames(bad, reps)
    with pytest.raises(InputError, match="repeat indices"):
        stack_frames(frames, reps[:-1])


def _counting_reader(frames):
    """``read(i)`` for :func:`stream_stack` returning a copy of ``frames[i]``, and the largest
    number of frames it handed out whose pixels were still held (not released) at a read."""
    import dataclasses

    live, peak = [], [0]

    def read(i):
        f = dataclasses.replace(frames[i], mosaic=frames[i].mosaic.copy())
        live.append(f)
        peak[0] = max(peak[0], sum(g.mosaic.size > 0 for g in live))
        return f
    return read, peak


def test_stream_stack_equals_stack_frames_holding_two_exposures_at_most(sensor, rig, times):
    frames, reps, _ = sequence_frames(sensor, rig, times)
    whole = stack_frames(frames, reps)
    order = np.random.default_rng(3).permutation(len(frames))
    fr, rp = [frames[i] for i in order], [reps[i] for i in order]
    for prefetch in (True, False):
        read, peak = _counting_reader(fr)
        st = stream_stack(read, [f.exposure_s for f in fr], [f.path for f in fr], rp, prefetch=prefetch)
        np.testing.assert_array_equal(st.images, whole.images)
        np.testing.assert_array_equal(st.clipped, whole.clipped)
        np.testing.assert_array_equal(st.exposure_s, whole.exposure_s)
        assert st.files == whole.files and st.repeats == 2
        # one exposure's 2 repeats combined while the next one's are read (prefetch), never the sequence
        assert peak[0] <= (4 if prefetch else 2) < len(frames)


def test_stream_stack_checks_the_files_as_they_are_read(sensor, rig, times):
    import dataclasses

    frames, reps, _ = sequence_frames(sensor, rig, times, shape=(4, 4))
    k = times.size + 6                         # repeat 1, exposure 6: its file says 1 % longer
    odd = list(frames)
    odd[k] = dataclasses.replace(frames[k], path="odd.dng", exposure_s=float(times[6]) * 1.01)
    with pytest.raises(InputError, match=r"odd\.dng: exposure 0\.016766 s in the file does not match 0\.0166 s of "
                                         r"seq_rep0_e06\.dng \(repeat 0\)"):
        stream_stack(_counting_reader(odd)[0], [f.exposure_s for f in frames], [f.path for f in frames], reps)
    iso = list(frames)
    iso[k] = dataclasses.replace(frames[k], path="iso.dng", iso=640)
    with pytest.raises(InputError, match=r"iso\.dng: ISO 640"):
        stream_stack(_counting_reader(iso)[0], [f.exposure_s for f in frames], [f.path for f in frames], reps)
    # the grouping's checks come first, from the expected exposures, before any file is read
    with pytest.raises(InputError, match=r"seq_rep0_e03\.dng: repeat 1 lacks exposure"):
        stream_stack(lambda i: pytest.fail("read before the grouping was checked"),
                     [f.exposure_s for f in frames[:times.size + 3]], [f.path for f in frames[:times.size + 3]],
                     reps[:times.size + 3])


def test_neighbour_correct_in_place_equals_the_copy(sensor, rig, times):
    rates = log_rates((48, 64), -2.5, 2.6, 5)
    gains = 1 + np.random.default_rng(6).normal(0, 0.005, (2, times.size))
    lin, _ = twin_sequence(sensor, rates, times, rig.sequence_iso, rig.sequence_aperture, repeats=2, gains=gains)
    comb, clipped = combine_repeats(lin)
    copied, rep_c = neighbour_correct(comb, times, clipped=clipped)
    inplace, rep_i = neighbour_correct(comb, times, clipped=clipped, copy=False)
    assert inplace is comb and copied is not comb
    np.testing.assert_array_equal(inplace, copied)
    np.testing.assert_array_equal(rep_i.factor, rep_c.factor)


@pytest.mark.parametrize("bound", [0.1, 0.9, 0.002])
@pytest.mark.parametrize("ratio", [2.0, 0.5, 1 / 3, 0.062437, 31.3])
def test_scaled_window_bound_selects_exactly_the_pixels_the_product_does(bound, ratio):
    """neighbour_correct tests q's value against one interval instead of scaling it to a's
    and b's exposures: the same pixels, for every float32 value near the bound."""
    from glossrig.core.radiometry.hdr import _scaled_bound

    c = np.float32(ratio)
    centre = np.float32(bound / ratio)
    x = centre + np.arange(-2000, 2001, dtype=np.float32) * np.spacing(centre)      # every float32 nearby
    x = np.unique(np.concatenate([x, np.nextafter(x, np.float32(np.inf))]))
    for above in (True, False):
        g = _scaled_bound(c, bound, above)
        want = (x * c > bound) if above else (x * c < bound)
        got = (x > g) if above else (x < g)
        np.testing.assert_array_equal(got, want)


def _hdr_ml_float64(y, t, noise, m, iterations=50):
    """hdr_ml's estimator in float64, iterated to convergence (the reference of the float32 code)."""
    y = y.reshape(len(t), -1).astype(np.float64)
    tt = t[:, None]
    usable = y < 1
    v = usable & (y > LO) & (y < HI)
    r = (y * v).sum(0) / (tt * v).sum(0)
    for _ in range(iterations):
        e = r * tt
        valid = usable & (e >= LO) & (e <= HI)
        w = np.where(valid, 1 / ((e / noise.electrons_full_scale + noise.read_sigma ** 2) / m), 0)
        sw = (w * tt * tt).sum(0)
        r = (w * tt * y).sum(0) / sw
    return r, 1 / sw, r * tt


def test_hdr_ml_in_float32_agrees_with_float64_within_its_error_budget(sensor, rig, times, noise):
    """hdr_ml's docstring budget: sums of n positive float32 terms (relative error <= (n-1) 2^-24
    each; the rate is a ratio of two, its variance the inverse of one whose weights move with
    the rate), float32 exposure times (2^-24) and the 1e-6 stopping rule. Pixels whose r t_i
    lies within 1e-5 of a validity limit may take or drop that exposure: left out."""
    rates = log_rates((64, 96), -2.5, 2.6, 11)
    lin, _ = twin_sequence(sensor, rates, times, rig.sequence_iso, rig.sequence_aperture)
    comb, clipped = combine_repeats(lin)
    comb = np.where(clipped, np.float32(1.0), comb)        # the reference knows saturation from the value
    res = hdr_ml(comb, times, noise, repeats=lin.shape[0], clipped=clipped)
    r64, var64, e = _hdr_ml_float64(comb, times, noise, lin.shape[0])
    near = ((np.abs(e / LO - 1) < 1e-5) | (np.abs(e / HI - 1) < 1e-5)).any(axis=0)
    ok = np.isfinite(r64) & (r64 > 0) & ~near
    assert ok.mean() > 0.9
    u, n = 2.0 ** -24, times.size
    rate_tol = 2 * (n - 1) * u + 2 * u + 1e-6
    var_tol = (n - 1) * u + u + rate_tol
    np.testing.assert_allclose(res.rate.ravel()[ok], r64[ok], rtol=rate_tol, atol=0)
    np.testing.assert_allclose(res.variance.ravel()[ok], var64[ok], rtol=var_tol, atol=0)
    assert res.rate.dtype == res.variance.dtype == np.float32


# ------------------------------------------------------------------ eq. 4.45-4.50

def test_patch_normalisation_puts_the_patch_mean_at_one_per_channel():
    h, w = 40, 60
    ch = channel_index((h, w), "RGGB")
    led = np.array([1.8, 1.0, 0.4])                 # a coloured LED / channel sensitivities
    field = np.random.default_rng(1).uniform(0.9, 1.1, (h, w))
    hdr = (led[ch] * field * 3.0).astype(np.float32)
    hdr[0, 0] = np.nan                                # an unmeasured pixel outside the patch stays NaN
    mask = np.zeros((h, w), bool)
    mask[10:20, 30:44] = True
    hdr[10, 30] = np.nan                              # one saturated patch pixel is left out of the mean
    var = np.full((h, w), 4e-4, np.float32)
    res = normalise_by_patch(hdr, mask, "RGGB", variance=var)
    for c in range(3):
        sel = mask & (ch == c)
        assert np.nanmean(res.image[sel].astype(np.float64)) == pytest.approx(1.0, rel=1e-6)
        np.testing.assert_allclose(res.variance[ch == c], 4e-4 / res.scale[c] ** 2, rtol=1e-6)
    assert res.pixels.sum() == mask.sum() - 1
    assert np.isnan(res.image[0, 0])
    # the thesis's single average (eq. 4.49 as intended) leaves the image tinted
    th = normalise_by_patch(hdr, mask, "RGGB", method="thesis")
    assert np.nanmean(th.image[mask]) == pytest.approx(1.0, rel=1e-6)
    assert np.nanmean(th.image[mask & (ch == 0)]) > 1.5 * np.nanmean(th.image[mask & (ch == 2)])


@pytest.mark.parametrize("mutate, match", [
    (lambda hdr, mask: (hdr, mask[:-1]), "does not match the HDR image"),
    (lambda hdr, mask: (hdr, np.zeros_like(mask)), "holds no pixel"),
    (lambda hdr, mask: (hdr, np.pad(np.ones((1, 1), bool), ((0, hdr.shape[0] - 1), (0, hdr.shape[1] - 1)))),
     "no pixel of channel G"),
    (lambda hdr, mask: (np.where(mask, np.nan, hdr), mask), "have no valid HDR value"),
    (lambda hdr, mask: (-hdr, mask), "not positive"),
    (lambda hdr, mask: (hdr, mask.astype(np.uint8)), "boolean"),
])
def test_patch_normalisation_rejects_bad_input(mutate, match):
    hdr = np.ones((8, 8), np.float32)
    mask = np.zeros((8, 8), bool)
    mask[2:6, 2:6] = True
    hdr2, mask2 = mutate(hdr, mask)
    with pytest.raises(InputError, match=rf"seq_r000_led08\.dng: .*{match}"):
        normalise_by_patch(hdr2, mask2, "RGGB", name="seq_r000_led08.dng")
