"""``glossrig capture`` as a user runs it: help, dry run, and a capture killed with
SIGKILL part-way (as by a power cut) then resumed: the manifest ends complete and every
file written before the kill keeps its checksum and its inode."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from glossrig.cli.main import main
from glossrig.core.capture import MANIFEST, load_manifest, sha256_file
from glossrig.core.rig import REPO_ROOT
from glossrig.hardware.plan import THESIS_OVERHEAD_S, load_plan

RIG = REPO_ROOT / "scenes" / "thesis_rig.toml"
PLAN = f"""
rig = "{RIG}"
sample = "killed"
rotations = [0]
leds = [1, 2]
repeats = 2
exposures_s = [0.01, 0.02, 0.04]
calibration = true
"""


def cli(*args, env_extra=None, **kw):
    env = dict(os.environ)
    env.pop("GLOSSRIG_FAKE_CAMERA", None)
    env.pop("GLOSSRIG_FAKE_LIGHTS", None)
    env.update(env_extra or {})
    return subprocess.Popen([sys.executable, "-m", "glossrig.cli.main", "capture", "--min-free-mb", "1", *args], env=env,
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            **kw)


def wait_for_images(out: Path, n: int, proc, timeout=30.0) -> None:
    """Wait until the running capture ``proc`` has recorded ``n`` images in ``out``; fail
    (killing it) if it exits first or after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    have = 0
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate(timeout=10)
        try:
            have = len(load_manifest(out).images)
            if have >= n:
                return
        except Exception:   # noqa: BLE001 - the folder may not exist yet
            pass
        time.sleep(0.02)
    proc.kill()
    _, err = proc.communicate(timeout=10)
    raise AssertionError(f"capture made no progress: {have} of {n} images after {timeout:g} s\n{err[-2000:]}")


def test_help_documents_the_plan_file(capsys):
    with pytest.raises(SystemExit) as ei:
        main(["capture", "--help"])
    assert ei.value.code == 0
    text = capsys.readouterr().out
    for key in ("rig =", "sample =", "rotations =", "leds =", "repeats =", "exposures_s =", "calibration =",
                "overhead_s_per_shot", "[checkerboard]", "[twin]", "--resume", "--dry-run", "serial-relay",
                "TEST ONLY"):
        assert key in text, key


def test_dry_run_prints_plan_and_time_of_the_thesis_plan(capsys, tmp_path):
    plan = REPO_ROOT / "scenes" / "plans" / "thesis_full.toml"
    rc = main(["capture", "--plan", str(plan), "--lights", "gpio", "--camera", "gphoto2", "--out",
               str(tmp_path / "x"), "--dry-run"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "images    1732 (4 calibration, 1728 sequence)" in out
    p = load_plan(plan)
    floor = 4 * (30.0 + 8 * 3 * sum(p.exposures_s))
    assert abs(p.estimate().exposure_s - floor) < 1e-6
    assert "exposures alone (physical floor): 1 h 39 min" in out
    # thesis 4.2.3: 4 minutes per 18-exposure sequence, by construction of the overhead
    assert "per 18-exposure sequence 4 min 00 s" in out
    assert abs(sum(p.exposures_s) + 18 * THESIS_OVERHEAD_S - 240.0) < 1e-9
    assert not (tmp_path / "x").exists()


def test_sigkill_then_resume_keeps_every_file(tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN)
    out = tmp_path / "cap"
    args = ["--plan", str(plan), "--lights", "fake", "--camera", "fake", "--out", str(out), "--sample-ready",
            "--no-progress"]
    proc = cli(*args, env_extra={"GLOSSRIG_FAKE_CAMERA": "delay_s=0.15"})
    wait_for_images(out, 4, proc)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    assert proc.returncode == -signal.SIGKILL

    m = load_manifest(out)
    assert not m.complete and 4 <= len(m.images) < 13
    before = {}
    for im in m.images:
        f = out / im.file
        assert sha256_file(f) == im.sha256
        before[im.file] = (im.sha256, f.stat().st_ino)

    # the plan still says 13 images; resuming without --resume is refused
    refused = cli(*args)
    _, err = refused.communicate(timeout=60)
    assert refused.returncode == 2 and "already holds a capture" in err

    proc = cli(*args, "--resume")
    stdout, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert "capture complete: 13 images" in stdout
    m2 = load_manifest(out)
    assert m2.complete and len(m2.images) == 13
    m2.verify(check_hashes=True)
    now = {im.file: im for im in m2.images}
    for name, (digest, inode) in before.items():
        assert now[name].sha256 == digest
        assert (out / name).stat().st_ino == inode
    assert len({im.key() for im in m2.images}) == 13
    assert not list(out.glob(".*.part"))


def test_sigterm_stops_with_leds_off_and_a_resume_hint(tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN)
    out = tmp_path / "cap"
    proc = cli("--plan", str(plan), "--lights", "fake", "--camera", "fake", "--out", str(out), "--sample-ready",
               "--no-progress", env_extra={"GLOSSRIG_FAKE_CAMERA": "delay_s=0.15"})
    wait_for_images(out, 2, proc)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130
    assert "rerun with --resume" in err and "The LEDs are off." in err
    load_manifest(out).verify()


def test_operator_prompt_without_a_terminal_is_a_clear_error(tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN)
    proc = cli("--plan", str(plan), "--lights", "fake", "--camera", "fake", "--out", str(tmp_path / "cap"),
               "--no-progress")
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    assert "ROTATE THE SAMPLE TO 0 DEGREES" in err and "input is closed" in err and "--sample-ready" in err
    assert "The LEDs are off." in err


def test_dry_run_of_a_partial_capture_shows_what_is_left(tmp_path, capsys):
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN)
    out = tmp_path / "cap"
    proc = cli("--plan", str(plan), "--lights", "fake", "--camera", "fake", "--out", str(out), "--sample-ready",
               "--no-progress", env_extra={"GLOSSRIG_FAKE_CAMERA": "disconnect_after=5,reconnect_after=none"})
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2 and "camera lost" in err and "5 of 13 images are safe" in err
    rc = main(["capture", "--plan", str(plan), "--lights", "fake", "--camera", "fake", "--out", str(out),
               "--dry-run"])
    assert rc == 0
    assert "resume    8 of 13 images still to take" in capsys.readouterr().out
    assert (out / MANIFEST).is_file()
