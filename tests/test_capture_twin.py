"""The capture orchestrator on the twin backends (one virtual rig behind lights, camera and
operator): the plan of the issue - two LEDs, two exposures, two repeats - gives a
complete capture folder whose every raw file the pipeline's reader accepts with the
manifest's exposure metadata, plus the twin's truth.json."""
from __future__ import annotations

import json

import pytest

from glossrig.core.capture import TRUTH, load_manifest
from glossrig.core.calibration.raw import read_raw
from glossrig.core.rig import REPO_ROOT
from glossrig.hardware.backends import make_backends
from glossrig.hardware.orchestrator import run_capture
from glossrig.hardware.plan import load_plan

pytestmark = pytest.mark.mitsuba

PLAN = f"""
rig = "{REPO_ROOT / 'scenes' / 'thesis_rig.toml'}"
sample = "lambert 0.8 on the twin"
rotations = [0, 45]
leds = [6, 10]
repeats = 2
exposures_s = [0.5, 1.0]
calibration = true

[twin]
material = "lambert:0.8"
scale = 0.06
seed = 1
spp = 2
"""


def test_twin_capture_is_complete_and_readable(tmp_path):
    (tmp_path / "plan.toml").write_text(PLAN)
    plan = load_plan(tmp_path / "plan.toml")
    dev = make_backends(plan, "twin", "twin")
    out = tmp_path / "cap"
    try:
        rep = run_capture(plan, out, lights=dev.lights, camera=dev.camera, operator=dev.operator,
                          backends=dev.names, show_progress=False)
    finally:
        dev.close()
    assert rep.complete and rep.taken == 2 * (1 + 2 * 2 * 2)
    m = load_manifest(out)
    m.verify(check_hashes=True)
    assert m.complete and m.meta["backends"] == {"lights": "twin", "camera": "twin"}
    assert m.meta["twin"]["material"] == "lambert:0.8"
    times = [im.time for im in m.images]
    assert times == sorted(times) and times[0].startswith("2026-01-01T09:00:00")    # the twin's capture clock
    for im in m.images:
        frame = read_raw(out / im.file, exposure_s=im.exposure_s, iso=im.iso, aperture=im.aperture)
        assert frame.mosaic.shape == (242, 362)
    cal = m.select("calibration", rotation=45.0)[0]
    seq = m.select("sequence", rotation=45.0, leds=[6])
    assert cal.leds == list(range(1, 17)) and len(seq) == 4
    truth = json.loads((out / TRUTH).read_text())
    assert truth["leds"] == [6, 10] and truth["rotations"] == [0.0, 45.0] and truth["scale"] == 0.06
    assert dev.lights.state() == frozenset()


def test_twin_refuses_checkerboard_views_and_bad_materials(tmp_path):
    from glossrig.core.errors import InputError

    (tmp_path / "a.toml").write_text(PLAN + "\n[checkerboard]\nviews = 2\n")
    with pytest.raises(InputError, match="take no checkerboard views"):
        make_backends(load_plan(tmp_path / "a.toml"), "twin", "twin")
    (tmp_path / "b.toml").write_text(PLAN.replace("lambert:0.8", "lambert:7"))
    with pytest.raises(InputError, match=r"b\.toml: \[twin\]: Lambertian albedo must lie in \[0, 1\]"):
        make_backends(load_plan(tmp_path / "b.toml"), "twin", "twin")
    with pytest.raises(InputError, match="one simulated rig"):
        make_backends(load_plan(tmp_path / "b.toml"), "twin", "gphoto2")
