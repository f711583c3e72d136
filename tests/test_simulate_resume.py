"""``glossrig simulate`` resumed after an interruption is byte-identical to an uninterrupted
run (design.md's output policy; issue #16), and simulate and the twin-backed ``capture``
write the same folder with the same file names (one naming scheme,
:func:`glossrig.core.capture.image_stem`)."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from glossrig.core.capture import MANIFEST, TRUTH, check_rotation_tags, image_stem, load_manifest, rotation_tag
from glossrig.core.errors import InputError
from glossrig.core.rig import REPO_ROOT

RIG = REPO_ROOT / "scenes" / "thesis_rig.toml"
# fluctuations on (not ideal): led_jitter + led_drift + hot pixels all draw random numbers
OPTS = dict(rig_path=RIG, material_spec="lambert:0.6", leds_spec="6", rotations=[0.0, -0.4], repeats=1, scale=0.05,
            seed=3, effects_text="hot_pixels=0.001", ideal=False, spp=1, progress=False)


def test_rotation_tags_are_unique_to_a_hundredth_of_a_degree():
    assert [rotation_tag(r) for r in (22, 22.5, -0.4, 0, -0.0, 359.99, -45)] == \
        ["p022.00", "p022.50", "m000.40", "p000.00", "p000.00", "p359.99", "m045.00"]
    grid = [k / 100 for k in range(-36000, 36001)]
    assert len({rotation_tag(r) for r in grid}) == len(grid)      # no two distinct rotations collide
    with pytest.raises(InputError, match="closer than 0.01 degree"):
        check_rotation_tags([22.5, 22.501])
    assert image_stem("sequence", rotation=-0.4, leds=[6], repeat=1, exposure_index=3) == "rotm000.40_led06_rep1_exp03"
    assert image_stem("calibration", rotation=22.5) == "rotp022.50_calibration"
    assert image_stem("checkerboard", view=2) == "checkerboard_view02"


def _simulate(out, **kw):
    from glossrig.twin.simulate import simulate

    return simulate(out=out, **{**OPTS, **kw})


def _images(folder):
    return [(im["file"], im["sha256"], im["time"]) for im in json.loads((folder / MANIFEST).read_text())["images"]]


@pytest.mark.mitsuba
def test_resumed_simulation_is_byte_identical(tmp_path, monkeypatch):
    from glossrig.hardware import backends_twin

    a, b = tmp_path / "a", tmp_path / "b"
    _simulate(a)
    real = backends_twin.TwinCamera.capture
    calls = {"n": 0}

    def interrupted(self, path):
        if calls["n"] == 23:      # into the second rotation: a calibration image and a sequence are done
            raise KeyboardInterrupt
        calls["n"] += 1
        return real(self, path)

    monkeypatch.setattr(backends_twin.TwinCamera, "capture", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _simulate(b)
    monkeypatch.setattr(backends_twin.TwinCamera, "capture", real)
    part = load_manifest(b)
    assert not part.complete and len(part.images) == 23
    # a damaged recorded image and a leftover half-written file are dealt with on resume
    victim = b / part.images[5].file
    victim.write_bytes(victim.read_bytes()[:-10] + b"0123456789")
    (b / f".{part.images[23 - 1].file}.x.part").write_bytes(b"half")

    with pytest.raises(InputError, match=r"other options \(seed: capture 3, now 4\)"):
        _simulate(b, seed=4, resume=True)
    with pytest.raises(InputError, match="not empty"):
        _simulate(b)                      # without --resume a partial capture is never overwritten
    _simulate(b, resume=True)

    ma, mb = load_manifest(a), load_manifest(b)
    assert ma.complete and mb.complete
    assert _images(a) == _images(b)       # names, checksums and the twin's schedule times
    assert len(ma.images) == 2 * (1 + 18)
    for im in ma.images:
        assert (a / im.file).read_bytes() == (b / im.file).read_bytes(), im.file
    assert (a / TRUTH).read_bytes() == (b / TRUTH).read_bytes()
    assert sorted(p.name for p in a.iterdir()) == sorted(p.name for p in b.iterdir() if p.name != "set_aside")
    assert {im.file for im in ma.images} >= {"rotp000.00_calibration.dng", "rotm000.40_led06_rep0_exp17.dng"}


@pytest.mark.mitsuba
def test_a_capture_records_its_renderer_and_a_resume_by_another_says_so(tmp_path, monkeypatch, capsys):
    """The manifest records what made the images besides the plan (Mitsuba's variant and version,
    Dr.Jit's, the sensor model's path): the same seed is the same bytes only with those. A resume
    by a camera made otherwise (here: the record says another variant) goes on - same statistics -
    but warns, and the manifest keeps both records."""
    from glossrig.hardware import backends_twin
    from glossrig.twin import sensor_drjit
    from glossrig.twin.mitsuba_env import mitsuba

    out = tmp_path / "cap"
    real = backends_twin.TwinCamera.capture
    calls = {"n": 0}

    def interrupted(self, path):
        if calls["n"] == 5:
            raise KeyboardInterrupt
        calls["n"] += 1
        return real(self, path)

    monkeypatch.setattr(backends_twin.TwinCamera, "capture", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _simulate(out, rotations=[0.0])
    monkeypatch.setattr(backends_twin.TwinCamera, "capture", real)
    d = json.loads((out / MANIFEST).read_text())
    prov = d["camera_provenance"]
    assert prov["mitsuba_variant"] == mitsuba().variant() and prov["mitsuba"] and prov["drjit"]
    assert prov["sensor_model"] == ("drjit-llvm" if sensor_drjit.available() else "numpy-reference")
    d["camera_provenance"] = {**prov, "mitsuba_variant": "cuda_ad_rgb"}
    (out / MANIFEST).write_text(json.dumps(d))
    _simulate(out, rotations=[0.0], resume=True)
    assert "the capture was started by a camera made otherwise" in capsys.readouterr().err
    m = load_manifest(out)
    assert m.complete and m.meta["camera_provenance"]["mitsuba_variant"] == "cuda_ad_rgb"
    assert m.meta["resumed_camera_provenance"] == [prov]


@pytest.mark.mitsuba
def test_simulate_and_twin_capture_write_the_same_folder(tmp_path):
    """The same capture through ``glossrig simulate`` and ``glossrig capture --lights twin
    --camera twin``: the same files (rig.toml and truth.json included), the same names."""
    sim, cap = tmp_path / "sim", tmp_path / "cap"
    opts = {**OPTS, "rotations": [22.5]}
    _simulate(sim, **{k: v for k, v in opts.items() if k != "rotations"}, rotations=[22.5])
    plan = tmp_path / "plan.toml"
    plan.write_text(f'rig = "{RIG}"\nsample = "lambert 0.6"\nrotations = [22.5]\nleds = [6]\nrepeats = 1\n'
                    f'[twin]\nmaterial = "lambert:0.6"\nscale = 0.05\nseed = 3\nspp = 1\neffects = "hot_pixels=0.001"\n')
    r = subprocess.run([sys.executable, "-m", "glossrig.cli.main", "capture", "--plan", str(plan), "--lights", "twin",
                        "--camera", "twin", "--out", str(cap), "--no-progress"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in sim.iterdir()) == sorted(p.name for p in cap.iterdir())
    ms, mc = load_manifest(sim), load_manifest(cap)
    assert [im.file for im in ms.images] == [im.file for im in mc.images]
    assert [(im.sha256, im.time) for im in ms.images] == [(im.sha256, im.time) for im in mc.images]  # same bytes


def test_resume_refuses_a_folder_without_a_simulated_capture(tmp_path):
    out = tmp_path / "cap"
    out.mkdir()
    (out / MANIFEST).write_text(json.dumps({"rig": "rig.toml", "material": "x", "complete": False, "images": []}))
    r = subprocess.run([sys.executable, "-m", "glossrig.cli.main", "simulate", "--no-progress", "--rig", str(RIG),
                        "--leds", "6", "--scale", "0.05", "--out", str(out), "--resume"], capture_output=True, text=True)
    assert r.returncode == 2
    assert "capture.json: --resume: this capture was not made by glossrig simulate" in r.stderr


def test_resume_refuses_a_capture_whose_material_file_was_edited(tmp_path):
    """An interrupted capture of a ``measured:`` file resumed after the file was edited in place
    would finish with another material: ``glossrig simulate --resume`` refuses, naming the
    material's sha256, and changes nothing."""
    from glossrig.core.capture import Manifest
    from glossrig.core.rig import load_rig
    from glossrig.twin.simulate import OPTIONS_KEY, sample_options, twin_effects

    bsdf = tmp_path / "m.bsdf"
    bsdf.write_bytes(b"first version")
    rig = load_rig(RIG)
    opts = sample_options(rig, f"measured:{bsdf}", "6", [0.0], 1, 0.05, 3, twin_effects(rig, None, True), 1)
    out = tmp_path / "cap"
    out.mkdir()
    Manifest(out, "rig.toml", "m", complete=False, meta={OPTIONS_KEY: opts}).save()
    before = (out / MANIFEST).read_bytes()
    bsdf.write_bytes(b"second version")
    r = subprocess.run([sys.executable, "-m", "glossrig.cli.main", "simulate", "--no-progress", "--rig", str(RIG),
                        "--material", f"measured:{bsdf}", "--leds", "6", "--rotations", "0", "--scale", "0.05",
                        "--seed", "3", "--ideal", "--spp", "1", "--out", str(out), "--resume"],
                       capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert "other options (material_sha256: capture '" in r.stderr and "Traceback" not in r.stderr
    assert (out / MANIFEST).read_bytes() == before and sorted(p.name for p in out.iterdir()) == [MANIFEST]


@pytest.mark.mitsuba
def test_resumed_checkerboard_views_are_byte_identical(tmp_path, monkeypatch):
    from glossrig.twin import dng
    from glossrig.twin.simulate import simulate

    def run(out, **kw):
        return simulate(RIG, "lambert:0.5", "6", [0.0], 1, 0.1, 2, None, out, target="checkerboard", views=3, spp=1,
                        progress=False, **kw)

    a, b = tmp_path / "a", tmp_path / "b"
    run(a)
    real = dng.write_dng
    calls = {"n": 0}

    def interrupted(*args, **kw):
        if calls["n"] == 1:
            raise KeyboardInterrupt
        calls["n"] += 1
        return real(*args, **kw)

    monkeypatch.setattr(dng, "write_dng", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run(b)
    monkeypatch.setattr(dng, "write_dng", real)
    assert [im.file for im in load_manifest(b).images] == ["checkerboard_view00.dng"]
    with pytest.raises(InputError, match=r"other options \(views: capture 3, now 4\)"):
        simulate(RIG, "lambert:0.5", "6", [0.0], 1, 0.1, 2, None, b, target="checkerboard", views=4, spp=1,
                 progress=False, resume=True)
    kept = (b / "rig.toml").read_bytes()
    (b / "rig.toml").write_bytes(kept.replace(b"thesis", b"edited", 1))
    with pytest.raises(InputError, match="refusing to mix rigs"):
        run(b, resume=True)
    (b / "rig.toml").write_bytes(kept)
    run(b, resume=True)
    assert _images(a) == _images(b) and load_manifest(b).complete
    assert sorted(p.name for p in a.iterdir()) == sorted(p.name for p in b.iterdir())
    for p in a.iterdir():
        assert p.read_bytes() == (b / p.name).read_bytes(), p.name
