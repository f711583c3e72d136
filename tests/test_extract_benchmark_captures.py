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
