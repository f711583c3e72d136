"""The typed rig (issue 18): every section of the rig file is read and checked once, by
load_rig, into dataclasses; a bad value anywhere stops with the file and the key named."""
from __future__ import annotations

import math
import re

import pytest

from glossrig.core.errors import InputError
from glossrig.core.rig import (CaptureTiming, Checkerboard, Cylinder, CylinderMarkers, Holder, HolderMarker,
                               Lighting, Reference, Sensor, default_rig_path, load_rig)
from glossrig.core.toml_input import check_number

TEXT = default_rig_path().read_text()


def with_value(text: str, section: str, key: str, value: str | None) -> str:
    """``text`` with ``key = value`` in ``[section]`` (the line removed when ``value`` is None)."""
    lines = text.splitlines()
    start = lines.index(f"[{section}]")
    for i in range(start + 1, len(lines)):
        if lines[i].startswith("["):
            break
        if re.match(rf"{re.escape(key)}\s*=", lines[i]):
            if value is None:
                del lines[i]
            else:
                lines[i] = f"{key} = {value}"
            return "\n".join(lines) + "\n"
    raise AssertionError(f"no {key} in [{section}]")


def test_every_section_is_exposed_as_attributes():
    rig = load_rig(default_rig_path())
    assert rig.name == "thesis" and rig.description.startswith("Cylindrical image-based BRDF rig")
    assert rig.cylinder == Cylinder(radius_with_sample=25.8, sample_height=50.0, bottom=-35.0, top=80.0,
                                    radius_bare=25.1)
    assert (rig.cylinder_radius, rig.sample_height) == (25.8, 50.0)
    assert rig.holder == Holder(width=70.0, height=30.0, depth=60.0, top=-35.0,
                                marker=HolderMarker(outer_width=24.0, outer_height=24.0, frame=4.0, centre_y=-50.0))
    assert rig.cylinder_markers == CylinderMarkers(side=7.9, count=3, centre_height=68.0, band_bottom=58.0,
                                                   band_top=78.0, paper_thickness=0.1)
    assert rig.lighting == Lighting(distance_from_axis=300.0, row_offset=13.5, radiant_intensity_W_sr=0.12,
                                    housing_radius=4.0, jitter=0.005, drift_amplitude=0.01,
                                    drift_period_s=(1200.0, 3600.0))
    assert len(rig.leds) == 16 and (rig.leds[1].id, rig.leds[1].channel, rig.leds[1].gpio) == (2, 2, 27)
    assert rig.camera.image_px == (6032, 4032) and rig.camera.lens == "105 mm" and rig.camera.bits == 14
    assert rig.sensor == Sensor(electrons_per_dn_iso100=2.2, read_noise_e=3.0, dark_current_e_s=0.05,
                                full_well_e=60000.0, electrons_per_radiance_s_f11=(6.0e4, 6.9e4, 5.2e4))
    assert len(rig.exposure_times_s) == 18 and rig.sequence_iso == 320 and rig.sequences_per_led == 3
    assert rig.sample_rotations == (-45.0, 0.0, 45.0, 90.0)
    assert rig.checkerboard == Checkerboard(inner_corners=(9, 6), square=25.0)
    assert rig.reference == Reference(material="white paper", assumed_albedo=0.8)
    assert rig.capture == CaptureTiming(overhead_s_per_shot=None)
    with pytest.raises(AttributeError):
        rig.sensor.read_noise_e = 0.0          # frozen


def test_optional_keys_and_sections_take_their_defaults(tmp_path):
    text = with_value(with_value(TEXT, "cylinder_markers", "paper_thickness", None), "leds", "housing_radius", None)
    text = with_value(text, "exposures", "sequences_per_led", None)
    text = text.replace("[reference]\nmaterial = \"white paper\"\nassumed_albedo = 0.8\n", "")
    text += "\n[capture]\noverhead_s_per_shot = 7.5\n"
    (tmp_path / "rig.toml").write_text(text)
    rig = load_rig(tmp_path / "rig.toml")
    assert rig.cylinder_markers.paper_thickness == 0.0 and rig.lighting.housing_radius == 4.0
    assert rig.sequences_per_led == 1 and rig.reference is None
    assert rig.capture.overhead_s_per_shot == 7.5


def test_the_leds_own_fluctuations_are_the_rig_files(tmp_path):
    """``[leds] jitter / drift_amplitude / drift_period_s``: a rig file states its LEDs' own fluctuations
    (the twin simulates them, diagnose takes them as a healthy rig's); without them, the project's
    figures (glossrig.core.led_fluctuations). The RMS drift slope follows from them: amplitude x 2 pi x
    sqrt(1 / (2 P_lo P_hi)), P in minutes - 0.02 x 2 pi x sqrt(1 / (2 x 10 x 10)) = 0.00889 / min."""
    from glossrig.core import led_fluctuations as lf

    text = TEXT
    for key in ("jitter", "drift_amplitude", "drift_period_s"):
        text = with_value(text, "leds", key, None)
    (tmp_path / "bare.toml").write_text(text)
    bare = load_rig(tmp_path / "bare.toml")
    assert (bare.lighting.jitter, bare.lighting.drift_amplitude, bare.lighting.drift_period_s) == (
        lf.LED_JITTER, lf.LED_DRIFT_AMPLITUDE, lf.LED_DRIFT_PERIOD_S)
    assert bare.lighting.drift_slope_rms_per_min() == lf.drift_slope_rms_per_min()
    text = with_value(with_value(TEXT, "leds", "drift_amplitude", "0.02"), "leds", "drift_period_s", "[600.0, 600.0]")
    (tmp_path / "own.toml").write_text(with_value(text, "leds", "jitter", "0.01"))
    own = load_rig(tmp_path / "own.toml").lighting
    assert (own.jitter, own.drift_amplitude, own.drift_period_s) == (0.01, 0.02, (600.0, 600.0))
    assert own.drift_slope_rms_per_min() == pytest.approx(0.02 * 2 * math.pi * math.sqrt(1 / 200), rel=1e-12)


BAD = [
    ("cylinder", "radius_with_sample", "0.5", r"cylinder\.radius_with_sample must be >= 1 and <= 500, got 0\.5"),
    ("cylinder", "top", '"high"', r"cylinder\.top must be a number, got 'high'"),
    ("holder", "depth", "-60.0", r"holder\.depth must be > 0"),
    ("holder.marker", "centre_y", "nan", r"holder\.marker\.centre_y must be a number, got nan"),
    ("cylinder_markers", "count", "2.5", r"cylinder_markers\.count must be an integer >= 1"),
    ("leds", "radiant_intensity_W_sr", "0.0", r"leds\.radiant_intensity_W_sr must be > 0, got 0\.0"),
    ("leds", "row_offset", "inf", r"leds\.row_offset must be a number, got inf"),
    ("leds", "jitter", "0.5", r"leds\.jitter must be >= 0 and <= 0\.2, got 0\.5"),
    ("leds", "drift_period_s", "[3600.0, 1200.0]", r"leds\.drift_period_s must be \[low, high\] with low <= high"),
    ("leds", "drift_period_s", "[1200.0]", r"leds\.drift_period_s must hold \[low, high\] in seconds"),
    ("camera", "bits", "20", r"camera\.bits must be >= 8 and <= 16, got 20"),
    ("camera", "image_px", "[6032]", r"camera\.image_px must hold 2 values"),
    ("sensor", "full_well_e", "-1.0", r"sensor\.full_well_e must be > 0, got -1\.0"),
    ("sensor", "electrons_per_radiance_s_f11", "[6.0e4, 0.0, 5.2e4]",
     r"sensor\.electrons_per_radiance_s_f11\[1\] must be > 0"),
    ("sensor", "read_noise_e", None, r"missing key 'sensor\.read_noise_e'"),
    ("exposures", "sequences_per_led", "0", r"exposures\.sequences_per_led must be an integer >= 1, got 0"),
    ("exposures", "calibration_time_s", "true", r"exposures\.calibration_time_s must be a number, got True"),
    ("exposures", "sample_rotations", "[0.0, 400.0]", r"exposures\.sample_rotations\[1\] must be >= -360"),
    ("checkerboard", "inner_corners", "[9, 1]", r"checkerboard\.inner_corners\[1\] must be an integer >= 2"),
    ("checkerboard", "square", None, r"missing key 'checkerboard\.square'"),
    ("reference", "assumed_albedo", "1.5", r"reference\.assumed_albedo must be > 0 and <= 1, got 1\.5"),
]


@pytest.mark.parametrize("section, key, value, message", BAD, ids=[f"{s}.{k}" for s, k, _, _ in BAD])
def test_a_bad_value_in_any_section_names_the_file_and_key(tmp_path, section, key, value, message):
    bad = tmp_path / "bad_rig.toml"
    bad.write_text(with_value(TEXT, section, key, value))
    with pytest.raises(InputError, match=message) as ei:
        load_rig(bad)
    assert str(ei.value).startswith(f"{bad}: ")


@pytest.mark.parametrize("change, message", [
    (("angle = 25.0,  channel = 3", "angle = 250.0,  channel = 3"), r"leds\.table\[2\]\.angle must be >= -180"),
    (("channel = 3,", "channel = 3.0,"), r"leds\.table\[2\]\.channel must be an integer >= 1, got 3\.0"),
    (('row = "upper",  angle = 25.0', 'row = "top",  angle = 25.0'), r"leds\.table\[2\]\.row must be one of"),
    (("#capture", "[capture]\noverhead_s_per_shot = -1.0"), r"capture\.overhead_s_per_shot must be >= 0"),
    (("\n[sensor]\n", "\n[sensor_x]\n"), r"missing key 'sensor'"),
    (('name = "thesis"', 'name = "thesis"\ncapture = 3'), r"key 'capture' must be dict, got int"),
])
def test_bad_led_table_and_sections_name_the_file_and_key(tmp_path, change, message):
    old, new = change
    text = TEXT + "\n#capture\n"
    assert old in text
    bad = tmp_path / "bad_rig.toml"
    bad.write_text(text.replace(old, new, 1))
    with pytest.raises(InputError, match=message) as ei:
        load_rig(bad)
    assert str(ei.value).startswith(f"{bad}: ")


def test_check_number_is_the_one_number_check():
    assert check_number(3, "k", "f.toml") == 3.0 and isinstance(check_number(3, "k", "f.toml"), float)
    assert check_number(3, "k", "f.toml", lo=1, integer=True) == 3
    for value, kw, message in [(True, {}, "f.toml: k must be a number, got True"),
                               (math.nan, {}, "f.toml: k must be a number, got nan"),
                               (0.0, {"lo": 0.0, "lo_open": True, "hi": 1.0}, "f.toml: k must be > 0 and <= 1, got 0.0"),
                               (2.0, {"hi": 2.0, "hi_open": True}, "f.toml: k must be < 2, got 2.0"),
                               (0, {"lo": 1, "integer": True}, "f.toml: k must be an integer >= 1, got 0"),
                               (1.0, {"integer": True}, "f.toml: k must be an integer, got 1.0")]:
        with pytest.raises(InputError) as ei:
            check_number(value, "k", "f.toml", **kw)
        assert str(ei.value) == message


def test_plan_defaults_come_from_the_rig_attributes(tmp_path):
    from glossrig.hardware.plan import THESIS_OVERHEAD_S, load_plan

    rig = tmp_path / "rig.toml"
    rig.write_text(TEXT)
    plan_file = tmp_path / "plan.toml"
    plan_file.write_text(f'rig = "{rig}"\nsample = "s"\nleds = [1]\n')
    plan = load_plan(plan_file)
    assert plan.repeats == 3 and plan.overhead_s_per_shot == pytest.approx(THESIS_OVERHEAD_S)
    rig.write_text(with_value(TEXT, "exposures", "sequences_per_led", "2") + "\n[capture]\noverhead_s_per_shot = 4.0\n")
    plan = load_plan(plan_file)
    assert plan.repeats == 2 and plan.overhead_s_per_shot == 4.0
