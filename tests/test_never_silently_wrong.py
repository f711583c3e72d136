"""Issue #16, "never silently wrong": inputs that used to be accepted and quietly give
wrong results - Ward values out of their physical range or in the wrong unit, capture
plans that saturate or render another material than they claim."""
from __future__ import annotations

import math

import pytest

from glossrig.core.errors import InputError


# ------------------------------------------------------- Ward parameter ranges

@pytest.mark.parametrize("spec,msg", [
    ("lobe_rotation=140", r"lobe_rotation=140 is beyond 2 pi radians: degrees\? .* write 140deg"),
    ("rho_d=5", r"rho_d=5 must lie in \[0, 1\]"),
    ("alpha_x=6", r"alpha_x=6 must lie in \(0, 0\.5\] \(thesis Table 4\.2\)"),
    ("alpha_y=0.7", r"alpha_y=0\.7 must lie in \(0, 0\.5\]"),
    ("rho_d=0.6,rho_s=0.5", r"rho_d \+ rho_s = 1\.1 exceeds 1"),
    ("lobe_rotation=east", r"lobe_rotation='east' is not an angle"),
])
def test_material_specs_out_of_range_are_refused(spec, msg):
    from glossrig.core.models.materials import parse_material

    base = dict(rho_d="0.05", rho_s="0.02", alpha_x="0.1", alpha_y="0.05")
    for part in spec.split(","):
        k, v = part.split("=")
        base[k] = v
    with pytest.raises(InputError, match=msg):
        parse_material("ward:" + ",".join(f"{k}={v}" for k, v in base.items()))


def test_lobe_rotation_takes_an_explicit_unit():
    from glossrig.core.models.materials import parse_material

    w = "ward:rho_d=0.05,rho_s=0.02,alpha_x=0.1,alpha_y=0.05,lobe_rotation="
    assert parse_material(w + "140deg").ward.lobe_rotation == pytest.approx(math.radians(140))
    assert parse_material(w + "2.44rad").ward.lobe_rotation == pytest.approx(2.44)
    assert parse_material(w + "2.44").ward.lobe_rotation == pytest.approx(2.44)
    assert parse_material(w + "-6.2").ward.lobe_rotation == pytest.approx(-6.2)


def test_material_file_out_of_range_names_the_file(tmp_path, monkeypatch):
    from glossrig.core.models import materials
    (tmp_path / "degrees.toml").write_text('type = "ward"\nrho_d = 0.05\nrho_s = 0.01\nalpha_x = 0.1\n'
                                           'alpha_y = 0.05\nlobe_rotation = 141.0\n')
    (tmp_path / "unit.toml").write_text('type = "ward"\nrho_d = 0.05\nrho_s = 0.01\nalpha_x = 0.1\n'
                                        'alpha_y = 0.05\nlobe_rotation = "141deg"\n')
    monkeypatch.setattr(materials, "MATERIALS_DIR", tmp_path)
    with pytest.raises(InputError, match=r"degrees\.toml: ward material: lobe_rotation=141 is beyond 2 pi"):
        materials.parse_material("degrees")
    assert materials.parse_material("unit").ward.lobe_rotation == pytest.approx(math.radians(141))


def test_every_shipped_material_is_in_range():
    from glossrig.core.models.materials import material_names, parse_material

    assert len(material_names()) > 5
    for name in material_names():
        parse_material(name)


def test_simulate_refuses_degrees_before_rendering(tmp_path, capsys):
    from glossrig.cli.main import main

    out = tmp_path / "cap"
    rc = main(["simulate", "--material", "ward:rho_d=0.05,rho_s=0.02,alpha_x=0.1,alpha_y=0.05,lobe_rotation=140",
               "--leds", "9", "--rotations", "0", "--repeats", "1", "--scale", "0.05", "--out", str(out),
               "--no-progress"])
    assert rc == 2
    assert "beyond 2 pi radians: degrees?" in capsys.readouterr().err
    assert not (out / "capture.json").exists()


# ------------------------------------------------------------- capture plans

ROOT = __import__("pathlib").Path(__file__).resolve().parent.parent
RIG = ROOT / "scenes" / "thesis_rig.toml"


def test_white_patch_check_flags_a_saturating_plan_and_passes_the_shipped_example(rig):
    """The README's twin_small plan used to expose 0.5 and 1.0 s: the white patch saturates
    at both under LED 10 (and at 0.5 s under LED 6), and extract refused the capture."""
    from glossrig.core.radiometry.exposure_plan import white_patch_exposures, white_patch_warnings
    from glossrig.hardware.plan import load_plan

    old = {6: [0.5, 1.0], 10: [0.5, 1.0]}
    msgs = white_patch_warnings(rig, old, where="old.toml")
    assert len(msgs) == 2 and msgs[1].startswith("old.toml: LED 10: the white patch saturates at every exposure")
    assert "add an exposure of at most 0.367 s" in msgs[1]
    # ISO and f-number count: two stops down (f/22) brings it back in range
    assert white_patch_warnings(rig, old, aperture=22.0) == []
    plan = load_plan(ROOT / "scenes" / "plans" / "twin_small.toml")
    shipped = {led: plan.exposures_for(led) for led in plan.leds}
    assert white_patch_warnings(rig, shipped, iso=plan.iso, aperture=plan.aperture) == []
    assert all(p.peak_dn < 0.9 * p.saturation_dn for p in white_patch_exposures(rig, shipped))


def test_design_exposures_writes_the_twin_table_and_warns_of_a_saturated_patch(tmp_path, capsys):
    from glossrig.cli.main import main
    from glossrig.hardware.plan import load_plan

    out = tmp_path / "dark.toml"
    rc = main(["design", "exposures", "--rig", str(RIG), "--material", "lambert:0.05", "--leds", "10",
               "--rotations=0", "--scale", "0.05", "--capture-scale", "0.1", "--seed", "7", "--out", str(out)])
    assert rc == 0
    err = capsys.readouterr().err
    assert f"warning: {out}: LED 10: the white patch saturates at every exposure" in err, err
    assert "extract will refuse this capture" in err
    plan = load_plan(out)
    assert plan.twin == {"material": "lambert:0.05", "scale": 0.1, "seed": 7}
    assert plan.sample == "lambert:0.05"


def _twin_plan(path, sample, twin):
    path.write_text(f'rig = "{RIG}"\nsample = "{sample}"\nrotations = [0]\nleds = [10]\nrepeats = 1\n'
                    f'exposures_s = [0.125]\n{twin}')
    return path


@pytest.mark.parametrize("sample,twin,msg", [
    ("sample_2_6", "", "the plan has no [twin] key 'material'"),
    ("sample_2_6", "[twin]\nscale = 0.05\n", "the plan has no [twin] key 'material'"),
    ("sample_2_6", '[twin]\nmaterial = "lambert:0.8"\nscale = 0.05\n',
     "the plan's sample 'sample_2_6' (the manifest's material label) is not the material the twin would render"),
])
def test_twin_capture_never_renders_another_material_than_the_plan_says(tmp_path, capsys, sample, twin, msg):
    """A design-exposures plan captured on the twin used to render lambert:0.8 at scale 0.25
    while its manifest said sample_2_6."""
    from glossrig.cli.main import main

    plan = _twin_plan(tmp_path / "plan.toml", sample, twin)
    out = tmp_path / "cap"
    rc = main(["capture", "--plan", str(plan), "--lights", "twin", "--camera", "twin", "--out", str(out),
               "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert f"{plan}: " in err and msg in err, err
    assert not (out / "capture.json").exists()


def test_twin_plan_with_a_free_text_or_agreeing_label_is_accepted(tmp_path):
    from glossrig.hardware.backends_twin import _check_sample_label
    from glossrig.core.models.materials import parse_material
    from glossrig.hardware.plan import load_plan

    for sample in ("white paper, batch 3", "lambert:0.80", "lambert:0.8"):
        plan = load_plan(_twin_plan(tmp_path / "p.toml", sample, '[twin]\nmaterial = "lambert:0.8"\n'))
        _check_sample_label(plan, parse_material("lambert:0.8"))        # no error
