"""Capture orchestration (thesis 4.2.3) against the real GPIO and gphoto2 drivers on
simulated devices: the capture folder contract, resume, and faults - a camera that
disconnects, a relay that does not switch, a full disk, Ctrl-C. Every fault must end
with the LEDs off, a message that says what is safe, and nothing already captured lost.
"""
from __future__ import annotations

import errno
from collections import namedtuple
from pathlib import Path

import pytest
from gpiozero.pins.mock import MockFactory

from glossrig.core.capture import MANIFEST, REQUIRED, load_manifest
from glossrig.core.errors import InputError
from glossrig.core.rig import REPO_ROOT
from glossrig.hardware.camera import Gphoto2Camera
from glossrig.hardware.errors import CaptureError
from glossrig.hardware.fakes import DeadRelayPin, FakeCameraBody, FakeGphoto2
from glossrig.hardware.lights import GpioRelayLights, NumatoRelayLights
from glossrig.hardware.orchestrator import SET_ASIDE, run_capture
from glossrig.hardware.plan import load_plan
from glossrig.hardware.serial_sims import NumatoRelaySim

RIG = REPO_ROOT / "scenes" / "thesis_rig.toml"

PLAN = f"""
rig = "{RIG}"
sample = "test sample"
rotations = [0]
leds = [1, 2]
repeats = 2
exposures_s = [0.01, 0.02]
calibration = true
"""


class NoOperator:
    """The sample is mounted; asking the operator anything is a test failure."""

    def __init__(self):
        self.rotations = []

    def rotate_to(self, deg):
        self.rotations.append(deg)

    def place_checkerboard(self, view, views):
        raise AssertionError("no checkerboard in this plan")


Rigged = namedtuple("Rigged", "plan lights camera body factory operator")


def make(tmp_path, plan_text=PLAN, *, dead=(), **body_kw) -> Rigged:
    p = tmp_path / "plan.toml"
    if not p.exists():
        p.write_text(plan_text)
    plan = load_plan(p)
    factory = MockFactory()
    for led in dead:
        factory.pin(plan.rig.led(led).gpio, pin_class=DeadRelayPin)
    lights = GpioRelayLights(plan.rig, pin_factory=factory)
    body = FakeCameraBody(**body_kw)
    body.observe = lights.state
    camera = Gphoto2Camera(FakeGphoto2(body), extension=".dng", reconnect_wait_s=0.0, sleep=lambda s: None)
    return Rigged(plan, lights, camera, body, factory, NoOperator())


def capture(r: Rigged, out: Path, **kw):
    return run_capture(r.plan, out, lights=r.lights, camera=r.camera, operator=r.operator,
                       backends={"lights": "fake", "camera": "fake"}, show_progress=False, **kw)


def files_and_hashes(out: Path) -> dict:
    m = load_manifest(out)
    return {im.file: (im.sha256, (out / im.file).stat().st_ino) for im in m.images}


def leds_lit(r: Rigged) -> set:
    """Relays energised, from the pins themselves (active-low: low = on)."""
    return {led.id for led in r.plan.rig.leds if r.factory.pin(led.gpio).state == 0}


def test_complete_capture_writes_the_folder_contract(tmp_path):
    r = make(tmp_path)
    out = tmp_path / "cap"
    rep = capture(r, out)
    assert rep.complete and rep.taken == 9 and rep.planned == 9
    m = load_manifest(out)
    m.verify(check_hashes=True)
    assert m.complete and m.material == "test sample" and m.rig == "rig.toml"
    assert (out / "rig.toml").read_bytes() == RIG.read_bytes()
    raw = __import__("json").loads((out / MANIFEST).read_text())
    for d in raw["images"]:
        assert set(REQUIRED) <= set(d)
        assert not Path(d["file"]).is_absolute() and "/" not in d["file"]
    roles = [im.role for im in m.images]
    assert roles == ["calibration"] + ["sequence"] * 8
    assert m.images[0].leds == list(range(1, 17))
    # what the camera saw: the LEDs that were on and the settings it used, shot by shot
    for im, (_, _settings, lit) in zip(m.images, r.body.log):
        assert sorted(lit) == im.leds
        assert abs(im.extra["exposure_s_file"] - im.exposure_s) / im.exposure_s < 0.1
    assert [im.exposure_s for im in m.images[1:5]] == [0.01, 0.02, 0.01, 0.02]
    assert [im.repeat for im in m.images[1:5]] == [0, 0, 1, 1]
    assert not list(out.glob(".*.part"))
    assert leds_lit(r) == set()
    assert r.operator.rotations == [0.0]


def test_existing_capture_is_never_overwritten_without_resume(tmp_path):
    r = make(tmp_path)
    out = tmp_path / "cap"
    capture(r, out)
    before = files_and_hashes(out)
    with pytest.raises(InputError, match="already holds a capture"):
        capture(r, out)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="not empty"):
        capture(r, tmp_path / "other")
    assert files_and_hashes(out) == before


def test_camera_that_vanishes_stops_cleanly_and_resume_completes(tmp_path):
    r = make(tmp_path, disconnect_after=4, reconnect_after=None)
    out = tmp_path / "cap"
    with pytest.raises(CaptureError) as ei:
        capture(r, out)
    msg = str(ei.value)
    assert "camera lost" in msg and "4 of 9 images are safe" in msg and "--resume" in msg and "LEDs are off" in msg
    assert leds_lit(r) == set()
    before = files_and_hashes(out)
    assert len(before) == 4 and not load_manifest(out).complete
    assert not list(out.glob(".*.part"))

    r2 = make(tmp_path)             # the camera is back (a fresh connection)
    rep = capture(r2, out, resume=True)
    assert rep.complete and rep.kept == 4 and rep.taken == 5
    after = files_and_hashes(out)
    assert len(after) == 9
    for name, (digest, inode) in before.items():
        assert after[name] == (digest, inode)    # same content, same file: never rewritten
    load_manifest(out).verify()


def test_camera_that_drops_and_comes_back_is_reconnected_mid_sequence(tmp_path):
    r = make(tmp_path, disconnect_after=3, reconnect_after=2)
    out = tmp_path / "cap"
    rep = capture(r, out)
    assert rep.complete and rep.taken == 9
    assert r.camera.reconnects == 1
    m = load_manifest(out)
    assert len({im.file for im in m.images}) == 9
    m.verify()


def test_relay_that_does_not_switch(tmp_path):
    r = make(tmp_path, dead=[2])
    out = tmp_path / "cap"
    with pytest.raises(CaptureError) as ei:
        capture(r, out)
    msg = str(ei.value)
    # The calibration image needs LED 2 too: the dead relay is caught before the first shot.
    assert "LED 2 (30i, relay channel 2, GPIO27) did not switch on" in msg and "--resume" in msg
    assert leds_lit(r) == set()
    assert load_manifest(out).images == []


def test_relay_failing_mid_capture_keeps_what_was_shot(tmp_path):
    plan = PLAN.replace("calibration = true", "calibration = false")
    r = make(tmp_path, plan, dead=[2])
    out = tmp_path / "cap"
    with pytest.raises(CaptureError, match="LED 2 .* did not switch on"):
        capture(r, out)
    m = load_manifest(out)
    assert [im.leds for im in m.images] == [[1]] * 4
    m.verify()
    assert leds_lit(r) == set()


def test_wrong_exposure_is_caught_from_the_file_itself(tmp_path):
    r = make(tmp_path, ignore_settings=True)    # the body keeps its own 1/125 s (mode dial not on M)
    out = tmp_path / "cap"
    with pytest.raises(CaptureError) as ei:
        capture(r, out)
    assert "exposure 1/125 s instead of 1/60 s" in str(ei.value)
    assert load_manifest(out).images == []
    assert [p.name for p in out.iterdir() if p.suffix == ".dng"] == []
    assert not list(out.glob(".*.part"))
    assert leds_lit(r) == set()


class FillsDisk:
    """A camera whose download hits a full disk after ``ok`` good shots."""

    def __init__(self, inner, ok):
        self.inner, self.ok, self.extension = inner, ok, inner.extension

    def configure(self, **kw):
        self.inner.configure(**kw)

    def capture(self, path):
        if self.ok == 0:
            Path(path).write_bytes(b"half a raw fi")
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        self.ok -= 1
        return self.inner.capture(path)

    def close(self):
        self.inner.close()


def test_full_disk_during_a_write(tmp_path):
    r = make(tmp_path)
    r = r._replace(camera=FillsDisk(r.camera, ok=3))
    out = tmp_path / "cap"
    with pytest.raises(CaptureError) as ei:
        capture(r, out)
    msg = str(ei.value)
    assert "disk full" in msg and "3 of 9 images are safe" in msg and "LEDs are off" in msg
    assert not list(out.glob(".*.part"))
    load_manifest(out).verify()
    assert leds_lit(r) == set()


def test_disk_nearly_full_stops_before_shooting(tmp_path):
    r = make(tmp_path)
    out = tmp_path / "cap"
    Usage = namedtuple("Usage", "total used free")
    calls = {"n": 0}

    def usage(path):
        calls["n"] += 1
        return Usage(10**12, 10**12, 10**12 if calls["n"] <= 5 else 10 * 2**20)

    with pytest.raises(CaptureError, match=r"disk nearly full: 10 MiB free"):
        capture(r, out, disk_usage=usage)
    assert len(load_manifest(out).images) == 5
    assert leds_lit(r) == set()


class Interrupting:
    def __init__(self, inner, ok):
        self.inner, self.ok, self.extension = inner, ok, inner.extension

    def configure(self, **kw):
        self.inner.configure(**kw)

    def capture(self, path):
        if self.ok == 0:
            raise KeyboardInterrupt
        self.ok -= 1
        return self.inner.capture(path)

    def close(self):
        self.inner.close()


def test_ctrl_c_leaves_leds_off_and_a_resumable_folder(tmp_path, capsys):
    r = make(tmp_path)
    r = r._replace(camera=Interrupting(r.camera, ok=6))
    out = tmp_path / "cap"
    with pytest.raises(KeyboardInterrupt):
        capture(r, out)
    assert "6 of 9 images are safe" in capsys.readouterr().err
    assert leds_lit(r) == set()
    r2 = make(tmp_path)
    assert capture(r2, out, resume=True).taken == 3


def test_resume_retakes_damaged_missing_and_unrecorded_files_without_losing_them(tmp_path):
    r = make(tmp_path)
    out = tmp_path / "cap"
    capture(r, out)
    m = load_manifest(out)
    damaged, missing, unrecorded = m.images[2].file, m.images[5].file, m.images[8].file
    with open(out / damaged, "r+b") as f:      # a flipped byte
        f.seek(200)
        b = f.read(1)
        f.seek(200)
        f.write(bytes([b[0] ^ 0xFF]))
    (out / missing).unlink()
    # a crash between publishing a file and recording it, and a half-written download
    m.images = m.images[:8]
    m.complete = False
    m.save()
    (out / f".{missing}.part").write_bytes(b"partial")
    good_before = {im.file: im.sha256 for im in m.images if im.file not in (damaged, missing)}

    r2 = make(tmp_path)
    rep = capture(r2, out, resume=True)
    assert rep.complete and rep.taken == 3 and rep.kept == 6
    aside = sorted(p.name for p in (out / SET_ASIDE).iterdir())
    assert len(aside) == 2
    assert any(n.startswith(damaged + ".damaged-") for n in aside)
    assert any(n.startswith(unrecorded + ".unrecorded-") for n in aside)
    m2 = load_manifest(out)
    m2.verify()
    now = {im.file: im.sha256 for im in m2.images}
    for f, h in good_before.items():
        assert now[f] == h
    assert not list(out.glob(".*.part"))


def test_resume_refuses_another_plan_or_sample(tmp_path):
    r = make(tmp_path, disconnect_after=2, reconnect_after=None)
    out = tmp_path / "cap"
    with pytest.raises(CaptureError):
        capture(r, out)
    other = tmp_path / "o"
    other.mkdir()
    r2 = make(other, PLAN.replace("repeats = 2", "repeats = 3"))
    with pytest.raises(InputError, match="another plan"):
        capture(r2, out, resume=True)
    other2 = tmp_path / "o2"
    other2.mkdir()
    r3 = make(other2, PLAN.replace("test sample", "another sample"))
    with pytest.raises(InputError, match="refusing to mix samples"):
        capture(r3, out, resume=True)
    # the capture's copy of the rig description edited, then lost: the same rig file no longer matches it
    copy = out / load_manifest(out).rig
    kept = copy.read_bytes()
    copy.write_bytes(kept + b"\n# moved an LED\n")
    with pytest.raises(InputError, match="differs from the capture's copy .*refusing to mix rigs"):
        capture(make(tmp_path), out, resume=True)
    copy.unlink()
    with pytest.raises(InputError, match="or that copy is missing"):
        capture(make(tmp_path), out, resume=True)
    copy.write_bytes(kept)
    assert len(load_manifest(out).images) == 2
    assert capture(make(tmp_path), out, resume=True).complete


def test_resume_of_a_complete_capture_takes_nothing(tmp_path):
    r = make(tmp_path)
    out = tmp_path / "cap"
    capture(r, out)
    before = files_and_hashes(out)
    rep = capture(make(tmp_path), out, resume=True)
    assert rep.complete and rep.taken == 0 and rep.kept == 9
    assert files_and_hashes(out) == before


def test_rotations_and_checkerboard_ask_the_operator_with_leds_off(tmp_path):
    plan = PLAN.replace("rotations = [0]", "rotations = [0, 45]").replace("repeats = 2", "repeats = 1") + \
        "\n[checkerboard]\nviews = 2\nexposure_s = 0.5\niso = 800\naperture = 8.0\n"
    r = make(tmp_path, plan)
    asked = []

    class Op:
        def rotate_to(self, deg):
            asked.append(("rotate", deg, frozenset(leds_lit(r))))

        def place_checkerboard(self, view, views):
            asked.append(("board", view, frozenset(leds_lit(r))))

    r = r._replace(operator=Op())
    rep = capture(r, tmp_path / "cap")
    assert rep.complete and rep.taken == 2 + 2 * (1 + 2 * 2)
    assert [a[:2] for a in asked] == [("board", 0), ("board", 1), ("rotate", 0.0), ("rotate", 45.0)]
    assert all(a[2] == frozenset() for a in asked)
    m = load_manifest(tmp_path / "cap")
    boards = m.select("checkerboard")
    assert [im.extra["view"] for im in boards] == [0, 1] and boards[0].iso == 800
    assert sorted({im.rotation for im in m.select("sequence")}) == [0.0, 45.0]


def test_serial_relay_board_that_stops_answering_mid_capture(tmp_path):
    """A serial timeout on the relay board: the capture stops with the board named, what
    was shot is kept, and the LEDs end off once the board answers again."""
    r = make(tmp_path)
    # commands: ver, off (2) at start-up, off (2) when the run starts, off (2) before the rotation
    # prompt, calibration (2); replies to commands 11-13 are lost: the read-back after switching
    # LED 1 on fails twice, then the first attempt to switch everything off
    with NumatoRelaySim(16, mute_after=10, mute_count=3) as sim:
        lights = NumatoRelayLights(r.plan.rig, sim.port, timeout_s=0.1, retries=1)
        r = r._replace(lights=lights)
        out = tmp_path / "cap"
        with pytest.raises(CaptureError) as ei:
            capture(r, out)
        msg = str(ei.value)
        assert "LED switching failed" in msg and "no reply to 'relay readall'" in msg and "relay board on" in msg
        assert "1 of 9 images are safe" in msg and "The LEDs are off." in msg, msg
        assert sim.on_relays() == set()
        m = load_manifest(out)
        assert [im.role for im in m.images] == ["calibration"]
        m.verify()


def test_capture_complete_only_for_a_finished_manifest(tmp_path):
    from glossrig.core.capture import capture_complete

    assert not capture_complete(tmp_path / "missing")
    (tmp_path / "capture.json").write_text('{"rig": "r", "material": "m", "images": [], "complete": false}')
    assert not capture_complete(tmp_path)
    (tmp_path / "capture.json").write_text('{"rig": "r", "material": "m", "images": [], "complete": true}')
    assert capture_complete(tmp_path)
    (tmp_path / "capture.json").write_text('{"rig": "r", "complete": tr')      # cut off mid-write
    assert not capture_complete(tmp_path)
    (tmp_path / "capture.json").write_text('[1, 2]')                           # not a manifest
    assert not capture_complete(tmp_path)
