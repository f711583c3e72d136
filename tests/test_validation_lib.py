"""The studies' small library (validation/common.py): the ``glossrig`` command runner
passes a command through and, when it fails, raises with the command's error output in
the message; the capture helpers build the ``glossrig simulate`` command the studies ran."""
from __future__ import annotations

import importlib
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def common(monkeypatch):
    """validation.common, imported as the studies import it (from the repository root)."""
    monkeypatch.syspath_prepend(str(ROOT))
    return importlib.import_module("validation.common")


def test_runner_passes_a_command_through(common):
    from glossrig import __version__

    r = common.glossrig("--version", stdout=False)
    assert r.returncode == 0
    assert r.stdout.strip() == f"glossrig {__version__}"


def test_failing_command_raises_with_its_error_output(common, tmp_path):
    missing = tmp_path / "no_such_capture"
    with pytest.raises(common.GlossrigFailed) as info:
        common.glossrig("calibrate", "camera", missing, "--out", tmp_path / "camera.json", stderr=False)
    e = info.value
    assert isinstance(e, subprocess.CalledProcessError)       # what studies that go on after a failure catch
    assert e.returncode != 0 and e.verb == "calibrate"
    assert "capture folder not found" in e.stderr
    msg = str(e)
    assert msg.startswith(f"glossrig calibrate failed (exit {e.returncode}): ")
    assert "capture folder not found" in msg and str(missing) in msg        # the command's stderr
    assert "glossrig.cli.main calibrate camera" in msg                      # and the command
    assert not (tmp_path / "camera.json").exists()


def test_failure_with_shown_output_names_the_command(common, tmp_path, capfd):
    with pytest.raises(common.GlossrigFailed) as info:
        common.glossrig("calibrate", "camera", tmp_path / "none", "--out", tmp_path / "c.json")
    assert "capture folder not found" in capfd.readouterr().err        # shown, not captured
    assert info.value.stderr is None and "its error output is above" in str(info.value)


def test_capture_builds_the_simulate_command_and_reuses_complete_captures(common, tmp_path, monkeypatch):
    calls, complete = [], {"value": False}
    monkeypatch.setattr(common, "glossrig", lambda *a, **kw: calls.append((a, kw)))
    monkeypatch.setattr(common, "capture_complete", lambda folder: complete["value"])
    out = tmp_path / "cap"
    common.capture(out, "lambert:0.8", 0.25, 3, "-45,0", 2, leds="6,9", extra=("--ideal",), stdout=False)
    (a, kw), = calls
    assert [str(x) for x in a] == ["simulate", "--rig", str(common.RIG), "--material", "lambert:0.8", "--leds", "6,9",
                                   "--rotations=-45,0", "--repeats", "2", "--scale", "0.25", "--seed", "3",
                                   "--no-progress", "--out", str(out), "--ideal"]
    assert kw == {"stdout": False}
    # a partial capture is removed and made again, or finished with --resume
    (out / "part").mkdir(parents=True)
    common.capture(out, "lambert:0.8", 0.25, 3, mode="resume")
    assert calls[-1][0][-1] == "--resume" and out.exists()
    common.capture(out, "lambert:0.8", 0.25, 3)
    assert len(calls) == 3 and not out.exists()
    # a complete one is kept, unless every capture is to be made anew
    (out / "part").mkdir(parents=True)
    complete["value"] = True
    common.capture(out, "lambert:0.8", 0.25, 3)
    common.capture(out, "lambert:0.8", 0.25, 3, mode="resume")
    assert len(calls) == 3 and out.exists()
    common.capture(out, "lambert:0.8", 0.25, 3, mode="fresh")
    assert len(calls) == 4 and not out.exists()
