"""The twin's sensor model (glossrig.twin.sensor): linearity, photon transfer,
saturation, CFA sampling, determinism, effect hooks, and the path
sensor -> DNG -> core.raw."""
from __future__ import annotations

import re
from datetime import datetime, timezone

import numpy as np
import pytest

from glossrig.core.errors import InputError
from glossrig.core.calibration.raw import channel_index, linearize, read_raw
from glossrig.core.rig import default_rig_path, load_rig
from glossrig.twin.dng import write_dng
from glossrig.twin.sensor import SensorModel, frame_rng


@pytest.fixture(scope="module")
def rig():
    return load_rig(default_rig_path())


@pytest.fixture(scope="module")
def sensor(rig):
    return SensorModel.from_rig(rig)


def flat(h, w, value):
    return np.full((h, w, 3), value, np.float32)


def radiance_for_dn(sensor, dn, t, iso, aperture=11.0):
    """Grey radiance giving ``dn`` DN above black on the green pixels."""
    k = sensor.electrons_per_radiance_s_f11[1] * (11.0 / aperture) ** 2 * t
    return dn * sensor.conversion_gain(iso) / k


def green(mosaic, cfa="RGGB"):
    return mosaic[channel_index(mosaic.shape, cfa) == 1].astype(np.float64)


def test_from_rig_reads_camera_and_sensor_sections(rig, sensor):
    sec = rig.sensor
    assert sensor.cfa == rig.camera.cfa == "RGGB"
    assert sensor.white_level == rig.camera.white_level == 15520
    assert sensor.black_level == tuple(rig.camera.black_level)
    assert sensor.electrons_per_dn_iso100 == sec.electrons_per_dn_iso100 == 2.2
    assert sensor.electrons_per_radiance_s_f11 == sec.electrons_per_radiance_s_f11 == (6.0e4, 6.9e4, 5.2e4)
    assert sensor.conversion_gain(320) == pytest.approx(sec.electrons_per_dn_iso100 * 100 / 320)


def test_from_rig_rejects_a_bad_sensor_section(tmp_path):
    text = default_rig_path().read_text()
    bad = tmp_path / "bad_rig.toml"
    bad.write_text(re.sub(r"(?m)^read_noise_e = .*$", "read_noise_e = -3.0", text))
    with pytest.raises(InputError, match=r"bad_rig\.toml.*read_noise_e"):
        SensorModel.from_rig(load_rig(bad))
    bad.write_text(re.sub(r"(?m)^electrons_per_radiance_s_f11 = .*$", "electrons_per_radiance_s_f11 = [6.0e4, 6.9e4]",
                          text))
    with pytest.raises(InputError, match=r"bad_rig\.toml.*electrons_per_radiance_s_f11"):
        SensorModel.from_rig(load_rig(bad))


def test_expected_dn_follows_cfa_aperture_and_time(sensor):
    rad = np.zeros((4, 6, 3), np.float32)
    rad[..., 0] = 0.01                                   # red light only
    dn = sensor.expected_dn(rad, 0.5, 320, 11.0)
    cid = channel_index(dn.shape, "RGGB")
    black = np.tile(sensor.black_2x2(), (2, 3))
    above = dn - black
    dark = sensor.dark_dn(0.5, 320)
    k_red = sensor.electrons_per_radiance_s_f11[0]
    assert np.allclose(above[cid == 0], 0.01 * k_red * 0.5 / sensor.conversion_gain(320) + dark, rtol=1e-5)
    assert np.allclose(above[cid != 0], dark, atol=1e-4)
    wide = sensor.expected_dn(rad, 0.5, 320, 5.5) - black
    assert np.allclose(wide[cid == 0] - dark, 4 * (above[cid == 0] - dark), rtol=1e-5)   # (11/N)^2


def test_signal_doubles_with_exposure(sensor):
    iso, t = 320, 0.01
    rad = flat(48, 64, radiance_for_dn(sensor, 1500, t, iso))
    rng = frame_rng(1, 0)
    means = []
    for tt in (t, 2 * t, 4 * t):
        m = sensor.expose(rad, tt, iso, 11.0, rng)
        assert m.max() < sensor.white_level
        means.append(green(m).mean() - sensor.black_level[1] - sensor.dark_dn(tt, iso))
    assert means[1] / means[0] == pytest.approx(2.0, rel=0.01)
    assert means[2] / means[1] == pytest.approx(2.0, rel=0.01)
    assert means[0] == pytest.approx(1500, rel=0.01)


@pytest.mark.parametrize("iso", [320, 3200])
def test_photon_transfer_curve(sensor, iso):
    """Variance vs mean on flat fields: slope 1/K (within 5 %), intercept
    sigma_r^2 / K^2 (+ 1/12 quantisation); EMVA 1288 difference method."""
    t, h, w = 0.01, 128, 128
    K = sensor.conversion_gain(iso)
    top = (sensor.white_level - max(sensor.black_level)) * 0.7
    levels = [0.0] + list(np.geomspace(top / 300, top, 6))
    rng = frame_rng(7, iso)
    means, variances = [], []
    for lv in levels:
        rad = flat(h, w, radiance_for_dn(sensor, lv, t, iso))
        a = green(sensor.expose(rad, t, iso, 11.0, rng))
        b = green(sensor.expose(rad, t, iso, 11.0, rng))
        means.append(0.5 * (a.mean() + b.mean()) - sensor.black_level[1] - sensor.dark_dn(t, iso))
        variances.append(np.var(a - b) / 2)
    means, variances = np.array(means), np.array(variances)
    predicted = sensor.variance_dn(means, iso, t)
    assert np.allclose(variances, predicted, rtol=0.06)
    wts = 1 / predicted                      # weighted fit: sd of a variance estimate ~ variance
    slope, intercept = np.polyfit(means, variances, 1, w=wts)
    assert slope == pytest.approx(1 / K, rel=0.05)
    assert intercept == pytest.approx((sensor.read_noise_e / K) ** 2 + 1 / 12, rel=0.1)


def test_dark_current_on_long_exposures(sensor):
    dark = sensor.expose(flat(128, 128, 0.0), 30.0, 3200, 11.0, frame_rng(3, 0))
    mean = dark.astype(float).mean() - np.mean(sensor.black_level)
    assert sensor.dark_dn(30.0, 3200) > 20
    assert mean == pytest.approx(sensor.dark_dn(30.0, 3200), abs=1.5)


def test_saturation_clips_at_white_level(sensor):
    rng = frame_rng(0, 0)
    m = sensor.expose(flat(48, 64, 1e6), 30.0, 3200, 11.0, rng)
    assert m.dtype == np.uint16 and np.all(m == sensor.white_level)
    rad = flat(48, 64, radiance_for_dn(sensor, 1.5 * sensor.white_level, 1.0, 320))
    rad[:, :32] = radiance_for_dn(sensor, 3000, 1.0, 320)
    m = sensor.expose(rad, 1.0, 320, 11.0, rng)
    assert m.max() == sensor.white_level
    assert np.all(m[:, 32:] == sensor.white_level) and np.all(m[:, :32] < sensor.white_level)
    # At a low enough ISO the full well fills before the white level is reached.
    low_iso = 0.8 * 100 * sensor.electrons_per_dn_iso100 * (sensor.white_level - max(sensor.black_level)) \
        / sensor.full_well_e
    m = sensor.expose(flat(48, 64, 1e3), 1.0, low_iso, 11.0, rng)
    well = sensor.full_well_e / sensor.conversion_gain(low_iso)
    assert np.all(m < sensor.white_level)
    assert green(m).mean() - sensor.black_level[1] == pytest.approx(well, abs=1.0)


def test_same_seed_same_frame(sensor):
    rad = flat(48, 64, radiance_for_dn(sensor, 800, 0.1, 320))
    rad[10:20, 10:40] *= 20                                     # both noise regimes in one frame
    a = sensor.expose(rad, 0.1, 320, 11.0, frame_rng(42, 5))
    b = sensor.expose(rad, 0.1, 320, 11.0, frame_rng(42, 5))
    c = sensor.expose(rad, 0.1, 320, 11.0, frame_rng(42, 6))
    d = sensor.expose(rad, 0.1, 320, 11.0, frame_rng(43, 5))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c) and not np.array_equal(a, d)


class Doubler:
    def __init__(self):
        self.seen = None

    def pre_electrons(self, e, ctx):
        self.seen = (ctx.exposure_s, ctx.iso, ctx.aperture, ctx.frame_index, ctx.cfa.tolist())
        return e * 2


class Offset:
    def post_dn(self, dn, ctx):
        dn += 100.0 + ctx.rng.normal(0, 1e-3)
        return dn


class Broken:
    def post_dn(self, dn, ctx):
        return dn[:2]


def test_effect_hooks(sensor):
    rad = flat(64, 64, radiance_for_dn(sensor, 1000, 0.1, 320))
    base = green(sensor.expose(rad, 0.1, 320, 11.0, frame_rng(1, 0))).mean() - sensor.black_level[1]
    d = Doubler()
    m = sensor.expose(rad, 0.1, 320, 11.0, frame_rng(1, 0), effects=[d, Offset()], frame_index=9)
    assert d.seen == (0.1, 320.0, 11.0, 9, [[0, 1], [1, 2]])
    assert green(m).mean() - sensor.black_level[1] == pytest.approx(2 * base + 100, rel=0.01)
    single = sensor.expose(rad, 0.1, 320, 11.0, frame_rng(1, 0), effects=Offset())
    assert green(single).mean() - sensor.black_level[1] == pytest.approx(base + 100, rel=0.01)
    with pytest.raises(TypeError, match="Broken.post_dn"):
        sensor.expose(rad, 0.1, 320, 11.0, frame_rng(1, 0), effects=[Broken()])


def test_bad_input_is_rejected(sensor):
    rng = frame_rng(0, 0)
    with pytest.raises(InputError, match="negative"):
        sensor.expose(flat(4, 4, -1.0), 0.1, 320, 11.0, rng)
    with pytest.raises(InputError, match="NaN"):
        sensor.expose(flat(4, 4, np.nan), 0.1, 320, 11.0, rng)
    with pytest.raises(InputError, match=r"\(H, W, 3\)"):
        sensor.expose(np.zeros((4, 4), np.float32), 0.1, 320, 11.0, rng)
    with pytest.raises(InputError, match="exposure_s"):
        sensor.expose(flat(4, 4, 1.0), 0.0, 320, 11.0, rng)
    with pytest.raises(InputError, match="rng"):
        sensor.expose(flat(4, 4, 1.0), 0.1, 320, 11.0, 42)


def test_exposed_frame_survives_dng_and_core_raw(sensor, tmp_path):
    """twin sensor -> DNG -> pipeline reader -> eq. 4.1 gives back the
    sensor's own normalised signal."""
    t, iso = 0.5, 320
    rad = flat(48, 64, radiance_for_dn(sensor, 5000, t, iso))
    mosaic = sensor.expose(rad, t, iso, 11.0, frame_rng(2, 0))
    cm, neutral = sensor.dng_colour()
    write_dng(tmp_path / "s.dng", mosaic, cfa=sensor.cfa, black_level=sensor.black_level,
              white_level=sensor.white_level, exposure_s=t, iso=iso, aperture=11.0,
              time=datetime(2024, 1, 1, tzinfo=timezone.utc), color_matrix=cm, as_shot_neutral=neutral)
    frame = read_raw(tmp_path / "s.dng")
    assert np.array_equal(frame.mosaic, mosaic)
    lin = linearize(frame)
    expect = (sensor.expected_dn(rad, t, iso, 11.0) - np.tile(sensor.black_2x2(), (24, 32))) / (
        sensor.white_level - sensor.black_2x2()[0, 0])
    assert lin.mean() == pytest.approx(expect.mean(), rel=0.01)
