"""Capture plans (thesis 4.2.3): the shots a plan makes, in the thesis's order, their
identities (for resume), the time estimate, and bad plans refused with the file named."""
from __future__ import annotations

import pytest

from glossrig.core.capture import ImageEntry, rotation_tag
from glossrig.core.errors import InputError
from glossrig.core.rig import REPO_ROOT
from glossrig.hardware.plan import THESIS_OVERHEAD_S, describe, load_plan

RIG = REPO_ROOT / "scenes" / "thesis_rig.toml"
BASE = f"""rig = "{RIG}"
sample = "s"
rotations = [0, -45]
leds = [1, 2]
repeats = 2
exposures_s = [0.01, 0.02]
calibration = true
"""


def plan_from(tmp_path, text, name="plan.toml"):
    p = tmp_path / name
    p.write_text(text)
    return load_plan(p)


def test_shots_follow_the_thesis_order(tmp_path):
    plan = plan_from(tmp_path, BASE)
    shots = plan.shots()
    assert len(shots) == 2 * (1 + 2 * 2 * 2)
    first = shots[:9]
    assert first[0].role == "calibration" and first[0].leds == tuple(range(1, 17))
    assert first[0].exposure_s == plan.rig.calibration_time_s
    assert [(s.leds, s.repeat, s.exposure_s) for s in first[1:]] == [
        ((1,), 0, 0.01), ((1,), 0, 0.02), ((1,), 1, 0.01), ((1,), 1, 0.02),
        ((2,), 0, 0.01), ((2,), 0, 0.02), ((2,), 1, 0.01), ((2,), 1, 0.02)]
    assert {s.rotation for s in shots[9:]} == {-45.0}
    assert len({s.stem for s in shots}) == len(shots) == len({s.key for s in shots})
    assert shots[10].stem == "rotm045.00_led01_rep0_exp00"


def test_shot_identity_matches_the_manifest_entry_identity(tmp_path):
    for s in plan_from(tmp_path, BASE + "\n[checkerboard]\nviews = 1\n").shots():
        extra = {"view": s.view} if s.view is not None else {}
        e = ImageEntry(file="f", role=s.role, leds=list(s.leds), rotation=s.rotation, repeat=s.repeat,
                       exposure_s=s.exposure_s, iso=s.iso, aperture=s.aperture, time="t", sha256="h", extra=extra)
        assert e.key() == s.key


def test_rotation_tags():
    assert [rotation_tag(r) for r in (-45, 0, 90, 22.5, -7.5)] == ["m045.00", "p000.00", "p090.00", "p022.50",
                                                                  "m007.50"]


def test_rotations_that_would_share_file_names_are_refused(tmp_path):
    with pytest.raises(InputError, match="closer than 0.01 degree"):
        plan_from(tmp_path, BASE.replace("rotations = [0, -45]", "rotations = [22.5, 22.501]"))


def test_defaults_come_from_the_rig_and_the_thesis(tmp_path):
    plan = plan_from(tmp_path, f'rig = "{RIG}"\nsample = "x"\n')
    assert plan.leds == (5, 6, 7, 8, 9, 10, 11, 12)             # middle row (thesis 4.2.3)
    assert plan.repeats == 3 and plan.rotations == (-45.0, 0.0, 45.0, 90.0)
    assert plan.exposures_s == plan.rig.exposure_times_s and len(plan.exposures_s) == 18
    assert plan.overhead_s_per_shot == pytest.approx(THESIS_OVERHEAD_S)
    assert THESIS_OVERHEAD_S == pytest.approx((240 - 61.00725) / 18)


def test_rig_path_relative_to_the_repository(tmp_path):
    plan = plan_from(tmp_path, BASE.replace(str(RIG), "scenes/thesis_rig.toml"))
    assert plan.rig_path == RIG.resolve()


def test_estimate_and_dry_run_text(tmp_path):
    plan = plan_from(tmp_path, BASE.replace("rotations = [0, -45]", "rotations = [0]"))
    est = plan.estimate()
    floor = plan.rig.calibration_time_s + 2 * 2 * (0.01 + 0.02)
    assert est.exposure_s == pytest.approx(floor)
    assert est.estimate_s == pytest.approx(floor + 9 * THESIS_OVERHEAD_S)
    text = describe(plan)
    assert "images    9 (1 calibration, 8 sequence)" in text and "physical floor" in text


@pytest.mark.parametrize("change, message", [
    (("sample = \"s\"\n", ""), "missing key 'sample'"),
    (("repeats = 2", "repeats = 0"), "repeats must be an integer >= 1"),
    (("exposures_s = [0.01, 0.02]", "exposures_s = [0.01, -1]"), r"exposures_s\[1\] must be a positive number"),
    (("exposures_s = [0.01, 0.02]", "exposures_s = [0.01, 0.01]"), "lists an exposure time twice"),
    (("leds = [1, 2]", "leds = [1, 40]"), "LED id 40 is not in rig"),
    (("leds = [1, 2]", "leds = \"diagonal\""), "expected 'middle', 'all'"),
    (("rotations = [0, -45]", "rotations = []"), "rotations must be a non-empty list"),
    (("calibration = true", "calibration = 1"), "calibration must be true or false"),
    (("calibration = true", "calibration = true\nexposure = 3"), r"unknown key\(s\) \['exposure'\]"),
    (("calibration = true", "calibration = true\n[twin]\nscale = 2.0"), r"twin\.scale must be > 0 and <= 1"),
    (("calibration = true", "calibration = true\n[checkerboard]\nviews = -1"), "checkerboard.views must be"),
])
def test_bad_plans_are_refused_naming_the_file(tmp_path, change, message):
    old, new = change
    assert old in BASE
    with pytest.raises(InputError, match=message) as ei:
        plan_from(tmp_path, BASE.replace(old, new), name="bad_plan.toml")
    assert str(ei.value).startswith(str(tmp_path / "bad_plan.toml"))


def test_missing_or_broken_files(tmp_path):
    with pytest.raises(InputError, match="capture plan not found"):
        load_plan(tmp_path / "nope.toml")
    with pytest.raises(InputError, match="not valid TOML"):
        plan_from(tmp_path, "rig = [", name="broken.toml")
    with pytest.raises(InputError, match="rig file 'nowhere.toml' not found"):
        plan_from(tmp_path, BASE.replace(str(RIG), "nowhere.toml"))


def test_example_plans_load():
    for p in sorted((REPO_ROOT / "scenes" / "plans").glob("*.toml")):
        plan = load_plan(p)
        assert plan.shots()
    full = load_plan(REPO_ROOT / "scenes" / "plans" / "thesis_full.toml")
    assert len(full.shots()) == 1732
    cal = full.shots()[0]
    assert (cal.exposure_s, cal.iso, cal.aperture) == (30.0, 3200, 11.0)       # thesis table 4.1
