"""The studies' small library (validation/common.py): the ``glossrig`` command runner
passes a command through and, when it fails, raises with the command's error output in
the message; the capture helpers build the ``glossrig simulate`` command the studies ran."""
from __future__ import annotations

import hashlib
import importlib
import json
import subprocess
from pathlib import Path

import pytest

from glossrig.core.errors import InputError
from glossrig.twin.simulate import plan_sha256

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
    # a complete one made by the same command is kept, unless every capture is to be made anew
    monkeypatch.undo()
    monkeypatch.syspath_prepend(str(ROOT))
    monkeypatch.setattr(common, "glossrig", lambda *a, **kw: calls.append((a, kw)))
    _made_by(common, out, *_args("lambert:0.8", 3))
    common.capture(out, "lambert:0.8", 0.25, 3)
    common.capture(out, "lambert:0.8", 0.25, 3, mode="resume")
    assert len(calls) == 3 and out.exists()
    common.capture(out, "lambert:0.8", 0.25, 3, mode="fresh")
    assert len(calls) == 4 and not out.exists()


def _args(material: str, seed: int, scale: float = 0.25) -> tuple:
    """The simulate arguments common.capture gives for MATERIAL, SEED (LEDs middle, rotation 0)."""
    return ("--material", material, "--leds", "middle", "--rotations=0", "--repeats", 1, "--scale", scale,
            "--seed", seed)


def _made_by(common, out: Path, *args, options: dict | None = None) -> dict:
    """A complete capture in OUT as ``glossrig simulate ARGS`` leaves it, but for its images:
    capture.json with the command's recorded options (or OPTIONS), rig.toml the rig's copy."""
    from glossrig.core.capture import Manifest
    from glossrig.twin.simulate import OPTIONS_KEY

    opts = common.simulate_options(*args) if options is None else options
    out.mkdir(parents=True, exist_ok=True)
    Manifest(out, "rig.toml", "sample", complete=True, meta={OPTIONS_KEY: opts}).save()
    (out / "rig.toml").write_bytes(common.RIG.read_bytes())
    return opts


def test_a_complete_capture_is_reused_only_when_the_same_command_made_it(common, tmp_path, monkeypatch, capsys):
    """A study run again into its work folder with another seed, an edited material file at the
    same path or another rig stops with an InputError naming the folder and the difference,
    and nothing is removed or simulated; the same command reuses the capture silently. A
    capture whose record lacks the material's sha256 (made before it was recorded) is reused
    with a warning naming what was not checked."""
    calls = []
    monkeypatch.setattr(common, "glossrig", lambda *a, **kw: calls.append(a))
    xml = tmp_path / "copper.xml"
    xml.write_text('<bsdf type="roughconductor"><string name="material" value="Cu"/></bsdf>\n')
    material = f"mitsuba:{xml}"
    out = tmp_path / "cap"
    opts = _made_by(common, out, *_args(material, 3))
    assert opts["material_sha256"] == hashlib.sha256(xml.read_bytes()).hexdigest()
    before = sorted((p.name, p.read_bytes()) for p in out.iterdir())

    for mode in ("reuse", "resume"):
        assert common.capture(out, material, 0.25, 3, mode=mode) == out
    assert calls == [] and capsys.readouterr().err == ""

    def refused(match: str, *args, **kw):
        with pytest.raises(InputError, match=match) as info:
            common.capture(out, *args, **kw)
        assert str(out / "capture.json") in str(info.value) and "nothing was changed" in str(info.value)
        assert calls == [] and sorted((p.name, p.read_bytes()) for p in out.iterdir()) == before

    refused(r"other options \(seed: capture 3, now 4\)", material, 0.25, 4)
    refused(r"scale: capture 0\.25, now 0\.3", material, 0.3, 3, mode="resume")
    xml.write_text('<bsdf type="roughconductor"><string name="material" value="Au"/></bsdf>\n')
    refused(r"other options \(material_sha256: capture '[0-9a-f]{64}', now '[0-9a-f]{64}'\)", material, 0.25, 3)
    xml.write_text('<bsdf type="roughconductor"><string name="material" value="Cu"/></bsdf>\n')
    assert common.capture(out, material, 0.25, 3) == out
    (out / "rig.toml").write_text((out / "rig.toml").read_text() + "\n# edited\n")
    before = sorted((p.name, p.read_bytes()) for p in out.iterdir())
    refused("another rig description", material, 0.25, 3)

    # the same file content reached by another path (a moved checkout) is the same material
    moved = tmp_path / "elsewhere" / "copper.xml"
    moved.parent.mkdir()
    moved.write_bytes(xml.read_bytes())
    there = tmp_path / "there"
    _made_by(common, there, *_args(f"mitsuba:{moved}", 3))
    assert common.capture(there, material, 0.25, 3) == there and calls == []
    assert plan_sha256(common.simulate_options(*_args(f"mitsuba:{moved}", 3))) == plan_sha256(opts)

    old = tmp_path / "old"
    unrecorded = {k: v for k, v in opts.items() if k != "material_sha256"}
    # a record without the sha256 keeps the plan sha256 it was made with (extend_leds checks it)
    assert plan_sha256(unrecorded) == hashlib.sha256(json.dumps(unrecorded, sort_keys=True).encode()).hexdigest()
    _made_by(common, old, options=unrecorded)
    assert common.capture(old, material, 0.25, 3) == old and calls == []
    err = capsys.readouterr().err
    assert "warning" in err and "material_sha256: not recorded by the glossrig that made the capture" in err
    assert str(old / "capture.json") in err


def test_material_sha256_follows_the_files_a_material_is_read_from(tmp_path):
    from glossrig.core.capture import sha256_file
    from glossrig.core.models.materials import MATERIALS_DIR, material_sha256

    f = tmp_path / "m.bsdf"
    f.write_bytes(b"not read here")
    assert material_sha256(f"measured:{f}") == hashlib.sha256(b"not read here").hexdigest()
    assert material_sha256("sample_2_6") == sha256_file(MATERIALS_DIR / "sample_2_6.toml")
    assert material_sha256("ward:rho_d=0.1,rho_s=0.05,alpha_x=0.1,alpha_y=0.1") is None and material_sha256("lambert:0.8") is None


def test_a_study_stopped_by_bad_input_exits_2_without_a_traceback(common, tmp_path):
    """validation.common.run_main, as every study's __main__ runs it: here the speed benchmark
    finds its reference capture made with another seed in --work."""
    import os
    import sys

    w = tmp_path / "w"
    (w / "calibration").mkdir(parents=True)
    for name in ("camera.json", "lamps.json"):          # a calibration found in WORK is kept as it is
        (w / "calibration" / name).write_text("{}")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    _made_by(common, w / "reference", *_args("lambert:0.8", 7))
    r = subprocess.run([sys.executable, "-m", "validation.diagnose.speed_benchmark", "--work", str(w)], cwd=ROOT,
                       env=env, capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert r.stderr.startswith("error: ") and "seed: capture 7, now 42" in r.stderr
    assert str(w / "reference" / "capture.json") in r.stderr


def test_every_study_runs_its_main_through_run_main():
    """Every validation script's __main__ block ends in run_main (bad input: exit 2, one line)."""
    import re

    scripts = [p for p in (ROOT / "validation").rglob("*.py") if '__name__ == "__main__"' in p.read_text()]
    assert len(scripts) >= 20
    for p in scripts:
        block = p.read_text().split('if __name__ == "__main__":', 1)[1]
        assert re.search(r"raise SystemExit\(run_main\(main(, sys\.argv\[1:\])?\)\)", block), p
