"""The gphoto2 camera driver against a fake python-gphoto2 binding (thesis 4.1.2, table
4.1): settings chosen from the camera's own tables, raw-only quality, each shot confirmed
from the file's metadata, a camera that drops off USB mid-sequence."""
from __future__ import annotations

import sys

import pytest

from glossrig.hardware.camera import Camera, Gphoto2Camera, ShotInfo, confirm_shot, import_gphoto2, parse_choice
from glossrig.hardware.errors import CameraDisconnected, CameraError
from glossrig.hardware.fakes import FakeCameraBody, FakeGphoto2, FakeGPhoto2Error
from glossrig.hardware.plan import THESIS_SEQUENCE_S


def camera(body=None, **kw) -> tuple[Gphoto2Camera, FakeCameraBody]:
    body = body or FakeCameraBody()
    kw.setdefault("reconnect_wait_s", 0.0)
    return Gphoto2Camera(FakeGphoto2(body), extension=".dng", **kw), body


def test_parse_choice():
    assert parse_choice("1/4000") == 0.00025 and parse_choice("10/25") == 0.4
    assert parse_choice("30") == 30 and parse_choice("0.0002s") == 0.0002 and parse_choice("2.5s") == 2.5
    assert parse_choice("f/5.6") == 5.6 and parse_choice("320") == 320
    assert parse_choice("Bulb") is None and parse_choice("Auto") is None


def test_connect_selects_raw_only_and_internal_ram():
    cam, body = camera()
    assert isinstance(cam, Camera)
    assert body.settings["imagequality"] == "NEF (Raw)" and body.settings["capturetarget"] == "Internal RAM"
    assert cam.model == "D750 (glossrig fake)"


def test_thesis_table_4_1_maps_onto_the_cameras_shutter_speeds():
    cam, body = camera()
    chosen = []
    for t in THESIS_SEQUENCE_S:
        cam.configure(exposure_s=t, iso=320, aperture=11.0)
        chosen.append(body.settings["shutterspeed"])
    assert chosen == ["1/4000", "1/2000", "1/1000", "1/500", "1/250", "1/125", "1/60", "1/30", "1/15", "1/8", "1/4",
                      "1/2", "1", "2", "4", "8", "15", "30"]
    assert body.settings["iso"] == "320" and body.settings["f-number"] == "f/11"


@pytest.mark.parametrize("kw, what", [
    (dict(exposure_s=45.0, iso=320, aperture=11.0), "no shutter speed setting near 45"),
    (dict(exposure_s=1.0, iso=333, aperture=11.0), "no ISO setting near 333"),
    (dict(exposure_s=1.0, iso=320, aperture=2.8), "no f-number setting near 2.8"),
])
def test_settings_the_camera_does_not_have_are_refused_before_shooting(kw, what):
    cam, body = camera()
    with pytest.raises(CameraError, match=what):
        cam.configure(**kw)
    assert body.captures == 0


def test_capture_writes_the_raw_file_and_confirms_it(tmp_path):
    cam, body = camera()
    cam.configure(exposure_s=0.0166, iso=320, aperture=11.0)
    info = cam.capture(tmp_path / "shot.dng")
    assert isinstance(info, ShotInfo)
    assert abs(info.exposure_s - 1 / 60) < 1e-6 and info.iso == 320 and info.aperture == 11.0
    assert (tmp_path / "shot.dng").stat().st_size > 1000
    assert body.card == {}                          # deleted from the camera after the download


def test_camera_that_drops_off_usb_is_reconnected_and_settings_reapplied(tmp_path):
    cam, body = camera(FakeCameraBody(disconnect_after=1, reconnect_after=3))
    cam.configure(exposure_s=0.5, iso=320, aperture=11.0)
    cam.capture(tmp_path / "a.dng")
    body.settings["shutterspeed"] = "1/125"         # while it was away someone turned the dial
    info = cam.capture(tmp_path / "b.dng")          # drops, comes back on the 3rd attempt, retakes
    assert cam.reconnects == 1 and body.failed_inits == 3
    assert abs(info.exposure_s - 0.5) < 1e-9


def test_camera_that_stays_away(tmp_path):
    waits = []
    cam, body = camera(FakeCameraBody(disconnect_after=0, reconnect_after=None), reconnect_attempts=4,
                       reconnect_wait_s=2.0, sleep=waits.append)
    cam.configure(exposure_s=0.5, iso=320, aperture=11.0)
    with pytest.raises(CameraDisconnected, match=r"dropped off USB .* did not come back after 4 attempts over 8 s"):
        cam.capture(tmp_path / "a.dng")
    assert waits == [2.0] * 4
    assert not (tmp_path / "a.dng").exists()


def test_no_camera_at_all():
    body = FakeCameraBody()
    body.connected, body.reconnect_after = False, None
    with pytest.raises(CameraDisconnected, match="no camera found on USB"):
        camera(body)


def test_other_libgphoto2_errors_are_not_mistaken_for_a_disconnect(tmp_path):
    cam, body = camera()
    cam.configure(exposure_s=0.5, iso=320, aperture=11.0)

    def broken():
        raise FakeGPhoto2Error(-6, "Unsupported operation")
    body.shoot = broken
    with pytest.raises(CameraError, match=r"libgphoto2 error: \[-6\] Unsupported operation") as ei:
        cam.capture(tmp_path / "a.dng")
    assert not isinstance(ei.value, CameraDisconnected) and cam.reconnects == 0


def test_camera_mode_dial_not_on_manual_is_caught_from_the_file(tmp_path):
    cam, body = camera(FakeCameraBody(ignore_settings=True))
    cam.configure(exposure_s=2.0, iso=320, aperture=11.0)
    with pytest.raises(CameraError, match=r"the camera shot exposure 1/125 s instead of 2 s"):
        cam.capture(tmp_path / "a.dng")


def test_a_jpeg_is_refused(tmp_path):
    cam, body = camera()
    cam.configure(exposure_s=2.0, iso=320, aperture=11.0)
    body.settings["imagequality"] = "JPEG Fine"
    with pytest.raises(CameraError, match=r"delivered 'DSC_0001\.JPG', not a \.dng raw file"):
        cam.capture(tmp_path / "a.dng")


def test_incomplete_download_is_refused(tmp_path):
    cam, body = camera()
    cam.configure(exposure_s=2.0, iso=320, aperture=11.0)
    real = body.shoot

    def truncating():
        name = real()
        body.card[name] = body.card[name][:-100]
        return name
    body.shoot = truncating
    cam._cam.file_get_info = lambda folder, name: type("I", (), {"file": type("F", (), {"size": 10 ** 6})})()
    with pytest.raises(CameraError, match=r"download of DSC_0001\.DNG is incomplete"):
        cam.capture(tmp_path / "a.dng")


def test_confirm_shot_needs_a_raw_file_with_metadata(tmp_path):
    p = tmp_path / "junk.nef"
    p.write_bytes(b"not a raw file at all" * 50)
    with pytest.raises(CameraError, match="cannot open|unreadable"):
        confirm_shot(p, exposure_s=1.0, iso=320, aperture=11.0)


def test_missing_binding_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "gphoto2", None)
    with pytest.raises(CameraError, match=r"pip install 'glossrig\[camera\]'"):
        import_gphoto2()
    with pytest.raises(CameraError, match="python-gphoto2 binding is not installed"):
        Gphoto2Camera()
