"""The extraction benchmark's captures (validation/extract_benchmark.py, issue 19): a twin
capture of the first LEDs of a list is extended to the whole list by simulating only the
added LEDs (validation.common.extend_leds), and the result is the capture a fresh simulation
of the whole list makes, image for image (the same bytes: every twin image has its own random
stream and its time on the plan's schedule, and the first LEDs keep theirs)."""
from __future__ import annotations

import importlib
import json
from pathlib import Path

import pytest

from glossrig.core.errors import InputError
from glossrig.twin.simulate import plan_sha256

ROOT = Path(__file__).resolve().parents[1]

ARGS = ("lambert:0.8", 0.05, 3, "0", 1)        # material, scale, seed, rotations, repeats
TIMES = ("started", "finished", "resumed")      # when each run happened: the only entries that may differ


def _images(folder: Path) -> list[tuple]:
    d = json.loads((folder / "capture.json").read_text())
    return [(i["file"], i["sha256"], i["time"], i["index"]) for i in d["images"]]


def _meta(folder: Path) -> dict:
    d = json.loads((folder / "capture.json").read_text())
    return {k: v for k, v in d.items() if k not in ("images", *TIMES)}


@pytest.fixture
def common(monkeypatch):
    """validation.common, imported as the studies import it (from the repository root)."""
    monkeypatch.syspath_prepend(str(ROOT))
    return importlib.import_module("validation.common")


@pytest.mark.mitsuba
def test_a_capture_extended_by_leds_is_the_fresh_capture_of_all_of_them(common, tmp_path):
    capture, extend_leds = common.capture, common.extend_leds
    ext, fresh = tmp_path / "extended", tmp_path / "fresh"
    capture(ext, *ARGS, leds="9")
    kept = {p.name: p.stat().st_mtime_ns for p in ext.glob("*.dng")}
    capture(ext, *ARGS, leds="9,10", mode="extend")
    capture(fresh, *ARGS, leds="9,10")
    assert _images(ext) == _images(fresh)
    assert len(_images(ext)) == 1 + 2 * 18                       # calibration image, 2 LEDs x 18 exposures
    assert _meta(ext) == _meta(fresh)                           # options, plan (its sha256, LEDs, images), complete
    assert json.loads((ext / "truth.json").read_text()) == json.loads((fresh / "truth.json").read_text())
    # the first LED's images were kept, not made again
    assert {p.name: p.stat().st_mtime_ns for p in ext.glob("*.dng") if p.name in kept} == kept
    # the capture of all of them: nothing to extend, reused as it is
    assert not extend_leds(ext, [9, 10])
    with pytest.raises(InputError, match="must be the first ones"):
        extend_leds(ext, [10, 9, 11])
    with pytest.raises(InputError, match="must be the first ones"):
        extend_leds(ext, [9])
    assert not extend_leds(tmp_path / "nothing", [9])
    # the options a simulate command line records, read by simulate_options, are the twin's own
    assert common.simulate_options(*_cli("9,10")) == json.loads((fresh / "capture.json").read_text())["simulate"]
    # a refused extension (another seed) changes nothing, not even the LED list
    one = tmp_path / "one"
    capture(one, *ARGS, leds="9")
    before = (one / "capture.json").read_bytes()
    material, scale, seed, rotations, repeats = ARGS
    with pytest.raises(InputError, match="seed: extended capture 3, command 4"):
        capture(one, material, scale, seed + 1, rotations, repeats, leds="9,10", mode="extend")
    assert (one / "capture.json").read_bytes() == before


def _cli(leds: str, seed: int = ARGS[2]) -> tuple:
    """The command line common.capture gives glossrig simulate for ARGS (but for LEDS and SEED)."""
    material, scale, _, rotations, repeats = ARGS
    return ("--material", material, "--leds", leds, f"--rotations={rotations}", "--repeats", repeats,
            "--scale", scale, "--seed", seed)


def _manifest_like_simulate(common, folder: Path, leds: str) -> bytes:
    """capture.json as glossrig simulate leaves a finished capture of ARGS with LEDS: its
    options, plan record (sha256 of the options; one calibration image and 18 exposures per
    LED) and finish time; no images (extend_leds reads none). Returns the file's bytes."""
    from glossrig.core.capture import Manifest
    from glossrig.core.rig import load_rig
    from glossrig.twin.simulate import OPTIONS_KEY

    opts = common.simulate_options(*_cli(leds))
    times = list(load_rig(common.RIG).exposure_times_s)
    plan = {"path": "glossrig simulate", "sha256": plan_sha256(opts), "sample": ARGS[0], "rotations": [0.0],
            "leds": opts["leds"], "repeats": 1, "exposures_s": times, "led_exposures_s": {}, "calibration": True,
            "checkerboard_views": 0, "planned_images": 1 + len(times) * len(opts["leds"])}
    folder.mkdir()
    Manifest(folder, "rig.toml", ARGS[0], complete=True,
             meta={OPTIONS_KEY: opts, "plan": plan, "finished": "2026-11-25T00:00:00+00:00"}).save()
    return (folder / "capture.json").read_bytes()


def test_a_refused_extension_leaves_the_manifest_as_it_was(common, tmp_path):
    """Every check comes before the one (atomic) write: another option of the completing
    command (seed, here also with nothing to extend), LEDs that do not begin with the
    capture's, a plan whose sha256 is not its options' - each refused, capture.json's bytes
    unchanged; and common.capture(mode="extend") with another seed is refused before
    anything is simulated or written. An accepted extension writes the plan of LEDs 9, 10."""
    cap = tmp_path / "cap"
    before = _manifest_like_simulate(common, cap, "9")
    for leds, seed, match in (("9,10", 4, "seed: extended capture 3, command 4"),
                              ("9", 4, "seed: extended capture 3, command 4"),
                              ("10,9", 3, "must be the first ones"), ("10", 3, "must be the first ones")):
        opts = common.simulate_options(*_cli(leds, seed))
        with pytest.raises(InputError, match=match):
            common.extend_leds(cap, opts["leds"], options=opts)
        assert (cap / "capture.json").read_bytes() == before
    with pytest.raises(InputError, match=r"leds: extended capture \[9, 10\], command \[9, 11\]"):
        common.extend_leds(cap, [9, 10], options=common.simulate_options(*_cli("9,11")))
    assert (cap / "capture.json").read_bytes() == before
    with pytest.raises(InputError, match="seed: extended capture 3, command 4"):
        common.capture(cap, ARGS[0], ARGS[1], 4, ARGS[3], ARGS[4], leds="9,10", mode="extend")
    assert (cap / "capture.json").read_bytes() == before and sorted(p.name for p in cap.iterdir()) == ["capture.json"]

    tampered = tmp_path / "tampered"
    tampered.mkdir()
    d = json.loads(before)
    d["plan"]["sha256"] = "0" * 64
    (tampered / "capture.json").write_text(json.dumps(d))
    raw = (tampered / "capture.json").read_bytes()
    with pytest.raises(InputError, match="plan sha256 is not that of its simulate options"):
        common.extend_leds(tampered, [9, 10], options=common.simulate_options(*_cli("9,10")))
    assert (tampered / "capture.json").read_bytes() == raw

    want = common.simulate_options(*_cli("9,10"))
    assert common.extend_leds(cap, [9, 10], options=want)
    d = json.loads((cap / "capture.json").read_text())
    assert d["simulate"] == want and d["plan"]["sha256"] == plan_sha256(want) and d["plan"]["leds"] == [9, 10]
    assert d["plan"]["planned_images"] == 1 + 2 * 18 and d["complete"] is False and "finished" not in d
