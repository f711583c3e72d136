"""The sensor model's Dr.Jit noise kernel (glossrig.twin.sensor_drjit, issue 19) against the
exact model: its Poisson draws follow the Poisson law (chi-square against the pmf), and
``SensorModel.expose`` gives the same pixel statistics as the NumPy reference path
(``expose_reference``) - mean and variance per CFA channel, black level, clipping at the
white level and at the full well - within their sampling errors; same seed, same mosaic.

Tolerances: a difference of two sample means (or variances) is compared with its standard
error, estimated from the samples (for a variance from the fourth central moment,
Var(s^2) ~ (m4 - s^4) / n), and must stay within Z = 5 standard errors: a false failure
has probability 6e-7 per comparison (two-sided normal tail), 3e-5 over the ~50 made here.
The seeds are fixed, so the outcome is reproducible."""
from __future__ import annotations

import math

import numpy as np
import pytest

from glossrig.core.calibration.raw import channel_index
from glossrig.core.rig import default_rig_path, load_rig
from glossrig.twin import sensor as sensor_mod
from glossrig.twin import sensor_drjit
from glossrig.twin.sensor import SensorModel, frame_rng

pytestmark = pytest.mark.skipif(not sensor_drjit.available(), reason="Dr.Jit's LLVM backend (libLLVM 19) missing")

Z = 5.0
#: chi-square tests: a p-value below this fails (false failure rate 1e-6 per test)
P_MIN = 1e-6


@pytest.fixture(scope="module")
def sensor():
    return SensorModel.from_rig(load_rig(default_rig_path()))


def poisson_draws(lam: float, n: int, seed: int) -> np.ndarray:
    """Raw Poisson(lam) draws of the kernel: no read noise, K = 1, black 0, no rounding."""
    e = np.full((n // 1024, 1024), lam, np.float32)
    return sensor_drjit.noise_dn(e, seed=seed, dark_e=0.0, full_well_e=1e9, read_e=0.0, inv_k=1.0,
                                 black_2x2=np.zeros((2, 2)), white=None).ravel()


def chi2_pvalue(draws: np.ndarray, lam: float) -> float:
    """p-value of Pearson's chi-square test of integer ``draws`` against Poisson(lam), with
    bins of expected count >= 50 (tails pooled into the end bins)."""
    from scipy import stats

    n = draws.size
    lo, hi = int(stats.poisson.ppf(1e-9, lam)), int(stats.poisson.isf(1e-9, lam)) + 1
    edges = [lo]
    acc = 0.0
    for k in range(lo, hi):
        acc += stats.poisson.pmf(k, lam) * n
        if acc >= 50:
            edges.append(k + 1)
            acc = 0.0
    edges[-1] = hi
    cdf = stats.poisson.cdf(np.asarray(edges) - 1, lam)
    expected = np.diff(np.concatenate([[0.0], cdf[1:-1], [1.0]])) * n
    observed = np.histogram(draws, bins=[-np.inf, *edges[1:-1], np.inf])[0]
    chi2 = float((((observed - expected) ** 2) / expected).sum())
    return float(stats.chi2.sf(chi2, len(expected) - 1))


@pytest.mark.parametrize("lam", [0.05, 0.7, 6.5, 9.99, 10.0, 37.2, 1234.5, 40000.0])
def test_kernel_draws_follow_the_poisson_law(lam):
    """Inversion below lambda = 10, PTRS from 10 on: integer draws whose histogram matches
    the Poisson pmf (2^21 draws; a rounded normal fails the same test, see below)."""
    x = poisson_draws(lam, 1 << 21, seed=int(lam * 1000) + 1)
    assert np.all(x == np.round(x)) and x.min() >= 0
    assert chi2_pvalue(x, lam) > P_MIN


@pytest.mark.parametrize("lam", [0.05, 1.5, 6.5])
def test_unlit_pixels_draw_the_poisson_law_of_the_dark_signal(lam):
    """A pixel that sees no light (expected photo-electrons 0) draws Poisson(dark electrons),
    its F(0) = exp(-dark) computed once per frame instead of per pixel."""
    e = np.zeros(((1 << 21) // 1024, 1024), np.float32)
    x = sensor_drjit.noise_dn(e, seed=int(lam * 1000) + 7, dark_e=lam, full_well_e=1e9, read_e=0.0, inv_k=1.0,
                              black_2x2=np.zeros((2, 2)), white=None).ravel()
    assert np.all(x == np.round(x)) and x.min() >= 0
    assert chi2_pvalue(x, lam) > P_MIN


def test_the_chi_square_test_rejects_a_normal_approximation():
    """The test above has the power to see a normal approximation (skewness 1/sqrt(lambda))."""
    lam = 37.2
    x = np.maximum(np.round(np.random.default_rng(0).normal(lam, math.sqrt(lam), 1 << 21)), 0)
    assert chi2_pvalue(x, lam) < P_MIN


def test_full_well_shortcut_is_the_chernoff_bound(sensor):
    lam = sensor_drjit.full_well_shortcut(sensor.full_well_e)
    n = sensor.full_well_e
    assert -lam + n + n * math.log(lam / n) == pytest.approx(sensor_drjit.SHORTCUT_LOG_P, abs=1e-6)
    assert n < lam < 1.1 * n


def _flat_electrons(sensor, lam, t, aperture=11.0, size=256):
    """Radiance (size, size, 3) giving ``lam`` expected photo-electrons on every CFA colour."""
    k = np.asarray(sensor.electrons_per_radiance_s_f11) * (11.0 / aperture) ** 2 * t
    return np.broadcast_to((lam / k).astype(np.float32), (size, size, 3)).copy()


def _z_mean(a, b):
    se = math.sqrt(a.var(ddof=1) / a.size + b.var(ddof=1) / b.size)
    return 0.0 if se == 0 and a.mean() == b.mean() else (a.mean() - b.mean()) / se


def _var_se2(x):
    m2 = x.var()
    return (((x - x.mean()) ** 4).mean() - m2 * m2) / x.size


def _z_var(a, b):
    se = math.sqrt(_var_se2(a) + _var_se2(b))
    return 0.0 if se == 0 and a.var() == b.var() else (a.var(ddof=1) - b.var(ddof=1)) / se


# expected photo-electrons per pixel at ISO 320 (white level at ~10260 e-): dark, the
# inversion sampler, PTRS from small to large, near and beyond the white level
LEVELS_ISO320 = [0.0, 0.4, 4.0, 30.0, 2000.0, 9000.0, 10300.0, 2e5]


@pytest.mark.parametrize("lam", LEVELS_ISO320)
def test_fast_path_statistics_equal_the_reference(sensor, lam):
    iso, t = 320, 0.01
    rad = _flat_electrons(sensor, lam, t)
    fast = sensor.expose(rad, t, iso, 11.0, frame_rng(11, int(lam)))
    ref = sensor.expose_reference(rad, t, iso, 11.0, frame_rng(12, int(lam)))
    assert fast.dtype == ref.dtype == np.uint16
    ch = channel_index(fast.shape, sensor.cfa)
    for c in range(3):
        a, b = fast[ch == c].astype(np.float64), ref[ch == c].astype(np.float64)
        assert abs(_z_mean(a, b)) < Z, (lam, c, a.mean(), b.mean())
        assert abs(_z_var(a, b)) < Z, (lam, c, a.var(), b.var())
        assert a.min() >= 0 and a.max() <= sensor.white_level


@pytest.mark.parametrize("lam", [0.0, 4.0, 30.0, 2000.0, 9000.0])
def test_fast_path_follows_the_photon_transfer_model(sensor, lam):
    """Below saturation: mean = expected_dn (black level + signal + dark signal) and
    variance = variance_dn (photon transfer, EMVA 1288 eq. 7), per CFA position."""
    iso, t = 320, 0.01
    rad = _flat_electrons(sensor, lam, t)
    m = sensor.expose(rad, t, iso, 11.0, frame_rng(13, int(lam))).astype(np.float64)
    mean_model = sensor.expected_dn(rad, t, iso, 11.0)
    K = sensor.conversion_gain(iso)
    var_model = sensor.variance_dn(lam / K, iso, t)
    for i in range(2):
        for j in range(2):
            x = m[i::2, j::2].ravel()
            mu = float(mean_model[i::2, j::2].mean())
            assert abs(x.mean() - mu) < Z * math.sqrt(var_model / x.size), (lam, i, j, x.mean(), mu)
            assert abs(x.var(ddof=1) - var_model) < Z * math.sqrt(_var_se2(x)), (lam, i, j, x.var(), var_model)


def test_fast_path_clips_at_the_full_well(sensor):
    """At an ISO where the full well fills before the white level: around and beyond the
    full well (partly clipped, clipped, and above the shortcut) as the reference."""
    low_iso = 0.8 * 100 * sensor.electrons_per_dn_iso100 * (sensor.white_level - max(sensor.black_level)) \
        / sensor.full_well_e
    fw, t = sensor.full_well_e, 1.0
    well_dn = fw / sensor.conversion_gain(low_iso)
    for k, lam in enumerate([fw - 200.0, fw + 800.0, sensor_drjit.full_well_shortcut(fw) * 1.001, 50 * fw]):
        rad = _flat_electrons(sensor, lam, t)
        fast = sensor.expose(rad, t, low_iso, 11.0, frame_rng(21, k)).astype(np.float64)
        ref = sensor.expose_reference(rad, t, low_iso, 11.0, frame_rng(22, k)).astype(np.float64)
        assert fast.max() < sensor.white_level
        assert abs(_z_mean(fast, ref)) < Z and abs(_z_var(fast, ref)) < Z, (lam, fast.mean(), ref.mean())
        if lam > fw + 8 * math.sqrt(lam):       # P(below the full well) < 1e-15 a pixel
            black = np.tile(sensor.black_2x2(), (fast.shape[0] // 2, fast.shape[1] // 2))
            sd = sensor.read_noise_e / sensor.conversion_gain(low_iso)       # read noise only
            assert abs((fast - black).mean() - well_dn) < Z * math.sqrt((sd * sd + 1 / 12) / fast.size)


def test_black_level_per_cfa_position_any_width():
    black = np.array([[600.0, 601.0], [602.0, 603.0]])
    for w in (7, 8):
        dn = sensor_drjit.noise_dn(np.zeros((5, w), np.float32), seed=1, dark_e=0.0, full_well_e=1e4, read_e=0.0,
                                   inv_k=1.0, black_2x2=black, white=65535)
        assert np.array_equal(dn, np.tile(black, (3, 4))[:5, :w])


def test_same_seed_same_mosaic_whatever_the_thread_count(sensor):
    """A pixel's draws depend only on the frame seed and its index: the same mosaic with one
    Dr.Jit thread as with several, and from the prepared radiance of a sequence."""
    import drjit as dr

    rad = _flat_electrons(sensor, 500.0, 0.1, size=64)
    rad[10:20, 5:50] *= 40                                   # inversion, PTRS and clipped pixels
    rad[30:40] *= 0.001
    a = sensor.expose(rad, 0.1, 320, 11.0, frame_rng(42, 5))
    assert np.array_equal(a, sensor.expose(rad, 0.1, 320, 11.0, frame_rng(42, 5)))
    assert not np.array_equal(a, sensor.expose(rad, 0.1, 320, 11.0, frame_rng(42, 6)))
    threads = dr.thread_count()
    try:
        dr.set_thread_count(1)
        assert np.array_equal(a, sensor.expose(rad, 0.1, 320, 11.0, frame_rng(42, 5)))
    finally:
        dr.set_thread_count(threads)
    prepared = sensor.prepare(rad)
    b = sensor.expose(prepared, 0.1, 320, 11.0, frame_rng(42, 5))
    assert np.array_equal(b, sensor.expose(prepared, 0.1, 320, 11.0, frame_rng(42, 5)))
    assert abs(_z_mean(a.astype(float), b.astype(float))) < Z


def test_prepared_radiance_has_the_statistics_of_the_radiance(sensor):
    """A sequence's prepared radiance (step 1 per unit exposure, scaled in the kernel) exposes
    like the radiance itself, gain included."""
    rad = _flat_electrons(sensor, 3000.0, 0.01)
    prepared = sensor.prepare(rad)
    for k, gain in enumerate((1.0, 0.37)):
        a = sensor.expose(prepared, 0.01, 320, 11.0, frame_rng(5, k), gain=gain).astype(float)
        b = sensor.expose_reference(rad, 0.01, 320, 11.0, frame_rng(6, k), gain=gain).astype(float)
        assert abs(_z_mean(a, b)) < Z and abs(_z_var(a, b)) < Z


def test_without_llvm_the_reference_path_is_used(sensor, monkeypatch):
    rad = _flat_electrons(sensor, 100.0, 0.1, size=32)
    monkeypatch.setattr(sensor_drjit, "available", lambda: False)
    monkeypatch.setattr(sensor_mod, "_WARNED", [])
    with pytest.warns(RuntimeWarning, match="reference path"):
        a = sensor.expose(rad, 0.1, 320, 11.0, frame_rng(1, 0))
    assert np.array_equal(a, sensor.expose_reference(rad, 0.1, 320, 11.0, frame_rng(1, 0)))


def test_pixel_pairs_sharing_a_box_muller_transform_are_uncorrelated(sensor):
    """Pixels 2 j and 2 j + 1 take the cosine and the sine of one Box-Muller transform: as
    independent normals their raw values are uncorrelated (|r| < Z / sqrt(n), the standard
    error of a correlation coefficient of n independent pairs), and so are the vertical
    neighbours, from other transforms."""
    iso, t = 320, 0.01
    rad = _flat_electrons(sensor, 0.0, t, size=1024)
    m = sensor.expose(rad, t, iso, 11.0, frame_rng(31, 0)).astype(np.float64)
    for a, b in ((m[:, 0::2], m[:, 1::2]), (m[0::2], m[1::2])):
        x, y = a.ravel() - a.mean(), b.ravel() - b.mean()
        r = float((x * y).sum() / math.sqrt((x * x).sum() * (y * y).sum()))
        assert abs(r) < Z / math.sqrt(x.size), r


def test_the_llvm_search_is_mitsuba_envs(monkeypatch, tmp_path):
    """glossrig.twin.mitsuba_env.llvm19_path, the one libLLVM 19 search (sensor_drjit.available
    calls it): a set DRJIT_LIBLLVM_PATH naming an existing libLLVM 19 is kept, else Debian's
    paths are tried, and without either there is none."""
    from glossrig.twin import mitsuba_env

    lib = tmp_path / "libLLVM.so.19.1"
    lib.write_bytes(b"")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(lib))
    assert mitsuba_env.llvm19_path() == str(lib)
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(tmp_path / "missing.so"))
    monkeypatch.setattr(mitsuba_env, "_LLVM19", (str(tmp_path / "nope.so.19.1"), str(lib)))
    assert mitsuba_env.llvm19_path() == str(lib)
    monkeypatch.setattr(mitsuba_env, "_LLVM19", ())
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(tmp_path / "missing.so"))   # the search above set it to lib
    assert mitsuba_env.llvm19_path() is None
