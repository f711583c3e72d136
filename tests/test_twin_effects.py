"""Each non-ideality of the twin's catalogue does what its documentation says, and is
recorded in the truth."""
from __future__ import annotations

import numpy as np
import pytest

from glossrig.core.errors import InputError
from glossrig.core.models.materials import parse_material
from glossrig.twin.effects import CATALOGUE, EffectState, parse_effects

pytestmark = pytest.mark.mitsuba
ANISO = "ward:rho_d=0.05,rho_s=0.08,alpha_x=0.15,alpha_y=0.04,lobe_rotation=0.0"


def vrig(rig, effects, material=ANISO, scale=0.06):
    from glossrig.twin.virtual_rig import VirtualRig

    return VirtualRig(rig, parse_material(material), scale=scale, seed=3, effects=effects, spp=4)


def test_catalogue_complete_and_parsed():
    assert set(CATALOGUE) == {"led_jitter", "led_drift", "led_emission", "led_position_error", "vignetting",
                              "sensor_nonlinearity", "black_level_offset", "stray_light", "sample_radius_error",
                              "sample_rotation_offset", "hot_pixels"}
    assert parse_effects("vignetting=0.2, led_drift=0.02") == {"vignetting": 0.2, "led_drift": 0.02}
    for bad in ("nope=1", "vignetting", "vignetting=x", "vignetting=2"):
        with pytest.raises(InputError):
            parse_effects(bad)


def test_geometric_effects_change_the_rendered_rig_and_the_truth(rig):
    base = vrig(rig, {})
    v = vrig(rig, {"led_position_error": 3.0, "sample_radius_error": 0.5, "sample_rotation_offset": 10.0})
    t = v.truth()
    assert t["sample_radius_mm"] == pytest.approx(rig.cylinder_radius + 0.5)
    offs = np.array([np.subtract(t["led_positions_mm"][str(l.id)], l.position) for l in rig.leds])
    assert 1.5 < offs.std() < 4.5 and np.abs(offs).max() > 0.5
    assert t["effects"]["values"]["sample_rotation_offset"] == 10.0
    # a rotation offset of 10 degrees renders like the nominal rig at rotation + 10
    v2 = vrig(rig, {"sample_rotation_offset": 10.0})
    v2.set_rotation(20.0)
    base.set_rotation(30.0)
    np.testing.assert_allclose(v2.led_radiance(9), base.led_radiance(9), rtol=1e-4, atol=1e-7)


def test_rotation_offset_of_a_sample_the_twin_does_not_turn_is_refused(rig):
    """A lambert (or isotropic measured) sample is not turned by the twin: a rotation offset
    would be recorded in the truth and be in no image, so it is refused by name."""
    with pytest.raises(InputError, match="sample_rotation_offset.*'lambert'"):
        vrig(rig, {"sample_rotation_offset": 3.0}, material="lambert:0.5")


def test_surface_positions_lie_on_the_sample(rig):
    """points_mm() (the AOV render behind the LED emission pattern) gives each pixel the
    holder-frame point it sees: on the sample band, every point lies on the cylinder."""
    v = vrig(rig, {"sample_radius_error": 0.4})
    p = v.points_mm()
    band = (np.abs(p).sum(-1) > 0) & (np.abs(p[..., 1]) < rig.sample_height / 2 - 1.0)
    assert band.mean() > 0.01
    r = np.hypot(p[..., 0], p[..., 2])[band]
    assert np.mean(np.abs(r - (rig.cylinder_radius + 0.4)) < 0.05) > 0.99


def test_radiometric_effects(rig):
    base = vrig(rig, {})
    b = base.led_radiance(9)
    vig = vrig(rig, {"vignetting": 0.2}).led_radiance(9)
    lit = b[..., 1] > 1e-3
    ratio = vig[..., 1][lit] / b[..., 1][lit]
    assert ratio.max() <= 1.0 + 1e-6 and ratio.min() > 0.8 - 1e-3 and ratio.min() < 0.99
    em = vrig(rig, {"led_emission": 50.0}).led_radiance(9)
    r = em[..., 1][lit] / b[..., 1][lit]
    assert r.min() < 0.97 and r.std() > 0.005        # a pattern, not a constant
    sample = lit & (np.abs(base.points_mm()[..., 1]) < rig.sample_height / 2)
    r_sample = em[..., 1][sample] / b[..., 1][sample]
    assert 0.4 < r_sample.min() and r_sample.max() < 1.1   # cos^50 of a few degrees, never blacked out
    st = vrig(rig, {"stray_light": 0.01})
    img = st.image_radiance([9], np.random.default_rng(0))
    bg = b[..., 1] == 0                                 # pixels that see nothing
    expect = 0.01 * st.intensity / (np.pi * (np.linalg.norm(st.led_positions[9]) * 1e-3) ** 2)
    np.testing.assert_allclose(img[..., 1][bg], expect, rtol=1e-5)


def test_led_fluctuations_statistics(rig):
    e = EffectState({"led_jitter": 0.01}, seed=1, led_ids=rig.led_ids())
    rng = np.random.default_rng(0)
    g = np.array([e.led_gain(9, 0.0, rng) for _ in range(4000)])
    assert g.mean() == pytest.approx(1.0, abs=0.001) and g.std() == pytest.approx(0.01, rel=0.08)
    d = EffectState({"led_drift": 0.05}, seed=1, led_ids=rig.led_ids())
    ts = np.linspace(0, 7200, 500)
    g = np.array([d.led_gain(9, t, rng) for t in ts])
    assert g.max() == pytest.approx(1.05, abs=0.002) and g.min() == pytest.approx(0.95, abs=0.002)
    assert np.abs(np.diff(g)).max() < 0.01            # slow: low frequency


def test_sensor_level_effects(rig):
    black = np.full((4, 4), 600.0)
    white = rig.camera.white_level
    dn = black + np.array([[0, 1000, 5000, 14000]] * 4, float)
    e = EffectState({"sensor_nonlinearity": 0.05}, seed=0, led_ids=[1])
    out = e.apply_dn(dn.copy(), black, white, 1.0, 0.7, None)
    x = out - black
    assert x[0, 3] == pytest.approx(14000 * (1 - 0.05 * 14000 / (white - 600)))
    assert np.all(x[:, 1:] < dn[:, 1:] - black[:, 1:])
    b2 = np.full((1, 2), 600.0)
    over = e.apply_dn(b2 + np.array([[1e5, 5e5]]), b2, white, 1.0, 0.7, None)
    assert np.all(over >= white)          # far beyond white stays saturated, never folds back dark
    e = EffectState({"black_level_offset": 7.0}, seed=0, led_ids=[1])
    assert np.allclose(e.apply_dn(dn.copy(), black, white, 1.0, 0.7, None) - dn, 7.0)
    e = EffectState({"hot_pixels": 0.01}, seed=0, led_ids=[1])
    mask = e.hot_pixel_mask((1000, 1000), seed=4)
    assert mask.mean() == pytest.approx(0.01, rel=0.05)
    hot = e.apply_dn(np.full((1000, 1000), 600.0), np.full((1000, 1000), 600.0), white, 2.0, 0.5, mask)
    assert np.allclose(hot[mask], 600 + 200 * 2.0 / 0.5) and np.allclose(hot[~mask], 600)


def test_the_twin_simulates_the_rig_files_own_fluctuations(rig, tmp_path):
    """A capture is simulated with the LED fluctuations its rig file states (``[leds] jitter``,
    ``drift_amplitude``, ``drift_period_s``), not with constants of the code: the effects glossrig
    simulate applies (unless --ideal) and the drift periods the twin draws follow the file."""
    from glossrig.core.rig import load_rig
    from glossrig.twin.effects import rig_fluctuations
    from glossrig.twin.simulate import twin_effects

    assert twin_effects(rig, None) == rig_fluctuations(rig) == {
        "led_jitter": rig.lighting.jitter, "led_drift": rig.lighting.drift_amplitude}
    assert twin_effects(rig, None, ideal=True) == {}
    from pathlib import Path

    text = Path(rig.path).read_text()
    assert "jitter = 0.005 " in text and "drift_period_s = [1200.0, 3600.0]" in text
    text = (text.replace("jitter = 0.005 ", "jitter = 0.012 ").replace("drift_amplitude = 0.01 ", "drift_amplitude = 0.03 ")
            .replace("drift_period_s = [1200.0, 3600.0]", "drift_period_s = [300.0, 400.0]"))
    (tmp_path / "rig.toml").write_text(text)
    own = load_rig(tmp_path / "rig.toml")
    assert twin_effects(own, "led_jitter=0.002") == {"led_jitter": 0.002, "led_drift": 0.03}
    vr = vrig(own, twin_effects(own, None))
    periods = list(vr.effects.detail["drift_period_s"].values())
    assert len(periods) == 16 and all(300.0 <= p <= 400.0 for p in periods), periods
