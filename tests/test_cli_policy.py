"""One policy for outputs and the conventions a user expects, across every verb (issue #16).

Every verb that writes refuses an existing output unless --force, and checks that it
can write before doing any work: the cases below give each verb inputs that do not
exist, so an error about the *output* proves the check came first, and an error about
an *input* (with --force) proves the output check passed. -v/-q exist on every verb
and sub-verb; messages go through the glossrig logger; progress bars need a terminal.
"""
from __future__ import annotations

import argparse
import io
import json
import logging
import re
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from glossrig.cli.main import build_parser, main
from glossrig.core.progress import progress_enabled

ROOT = Path(__file__).resolve().parent.parent


def _cases(t: Path) -> dict:
    """verb -> (argv builder taking OUT, output kind, path of the missing input the verb reads first)."""
    rig, cam, lamps = t / "no_rig.toml", t / "no_camera.json", t / "no_lamps.json"
    cap, ref = t / "no_capture", t / "no_reference"
    return {
        "simulate": (lambda o: ["simulate", "--rig", rig, "--out", o], "folder", rig),
        "calibrate camera": (lambda o: ["calibrate", "camera", cap, "--out", o], "file", cap),
        "calibrate camera --plot": (lambda o: ["calibrate", "camera", cap, "--out", t / "c.json", "--plot", o],
                                    "file", cap),
        "calibrate geometry": (lambda o: ["calibrate", "geometry", cap, "--camera", cam, "--out", o], "file", None),
        "calibrate lamps": (lambda o: ["calibrate", "lamps", cap, "--camera", cam, "--out", o], "file", cam),
        "extract": (lambda o: ["extract", cap, "--reference", ref, "--camera", cam, "--lamps", lamps, "--out", o],
                    "file", cam),
        "extract --plots": (lambda o: ["extract", cap, "--reference", ref, "--camera", cam, "--lamps", lamps,
                                       "--out", t / "s.parquet", "--plots", o], "folder", cam),
        "fit": (lambda o: ["fit", t / "no.parquet", "--out", o], "file", t / "no.parquet"),
        "fit --mitsuba": (lambda o: ["fit", t / "no.parquet", "--out", t / "f.json", "--mitsuba", o], "file",
                          t / "no.parquet"),
        "fit --plots": (lambda o: ["fit", t / "no.parquet", "--out", t / "f.json", "--plots", o], "folder",
                        t / "no.parquet"),
        "model crossval": (lambda o: ["model", "crossval", "--ward", t / "w.csv", "--coverages", t / "c.csv",
                                      "--out", o], "file", t / "w.csv"),
        "model fit": (lambda o: ["model", "fit", "--ward", t / "w.csv", "--coverages", t / "c.csv", "--out", o],
                      "file", t / "w.csv"),
        "fabricate": (lambda o: ["fabricate", t / "no.png", "--width-mm", "5", "--out", o], "fabricate",
                      t / "no.png"),
        "design coverage": (lambda o: ["design", "coverage", "--rig", rig, "--out", o], "folder", rig),
        "design optimise": (lambda o: ["design", "optimise", "--rig", rig, "--leds", "8", "--out", o], "file", rig),
        "design optimise --report": (lambda o: ["design", "optimise", "--rig", rig, "--leds", "8", "--out",
                                                t / "r.toml", "--report", o], "folder", rig),
        "design errors": (lambda o: ["design", "errors", "--rig", rig, "--out", o], "file", rig),
        "design exposures": (lambda o: ["design", "exposures", "--rig", rig, "--material", "lambert:0.8",
                                        "--out", o], "file", rig),
        "design exposures --report": (lambda o: ["design", "exposures", "--rig", rig, "--material", "lambert:0.8",
                                                 "--out", t / "p.toml", "--report", o], "file", rig),
        "diagnose": (lambda o: ["diagnose", cap, "--reference", ref, "--camera", cam, "--lamps", lamps, "--out", o],
                     "folder", None),
        "capture": (lambda o: ["capture", "--plan", t / "no_plan.toml", "--lights", "fake", "--camera", "fake",
                               "--out", o], "capture", t / "no_plan.toml"),
        "demo": (lambda o: ["demo", "--out", o], "demo", None),
    }


CASES = sorted(_cases(Path("/x")))


def _run(capsys, argv):
    t0 = time.monotonic()
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    return rc, err, time.monotonic() - t0


def _make_existing(out: Path, kind: str) -> None:
    if kind in ("file",):
        out.write_text("earlier result\n")
    elif kind == "fabricate":
        out.mkdir()
        (out / "summary.json").write_text("{}\n")
    elif kind == "capture":
        out.mkdir()
        (out / "capture.json").write_text("{}\n")
    else:
        out.mkdir()
        (out / "earlier.txt").write_text("earlier result\n")


@pytest.mark.parametrize("name", [c for c in CASES if _cases(Path("/x"))[c][1] != "demo"])
def test_existing_output_is_refused_without_force_before_any_work(tmp_path, capsys, name):
    build, kind, _ = _cases(tmp_path)[name]
    out = tmp_path / ("out" if kind != "file" else "out.json")
    _make_existing(out, kind)
    before = {p.name: p.read_bytes() for p in out.iterdir()} if out.is_dir() else out.read_bytes()
    rc, err, _ = _run(capsys, build(out))
    assert rc == 2, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert str(out) in err
    assert ("--resume" if kind == "capture" else "--force") in err
    after = {p.name: p.read_bytes() for p in out.iterdir()} if out.is_dir() else out.read_bytes()
    assert after == before                                   # nothing touched


@pytest.mark.parametrize("name", [c for c in CASES if _cases(Path("/x"))[c][1] not in ("demo", "capture")])
def test_force_passes_the_output_check(tmp_path, capsys, name):
    build, kind, missing = _cases(tmp_path)[name]
    out = tmp_path / ("out" if kind != "file" else "out.json")
    if name == "simulate":       # --force replaces only simulate's own captures: fake one
        out.mkdir()
        (out / "capture.json").write_text(json.dumps({"source": "glossrig twin", "images": [{"file": "a.dng"}]}))
        (out / "a.dng").write_bytes(b"x")
        (out / "truth.json").write_text("{}")
    else:
        _make_existing(out, kind)
    rc, err, _ = _run(capsys, [*build(out), "--force"])
    assert rc == 2 and "Traceback" not in err                 # fails later, on a missing input
    assert "--force" not in err and "exists" not in err.replace("does not exist", "")
    if missing is not None:
        assert missing.name in err, err
    if name == "simulate":      # a bad input is found before the earlier capture is removed
        assert sorted(p.name for p in out.iterdir()) == ["a.dng", "capture.json", "truth.json"]


def _manifest(out, source: str, files=()) -> None:
    """A capture.json (written as every capture writes it) listing ``files``, made by ``source``."""
    from glossrig.core.capture import ImageEntry, Manifest

    images = [ImageEntry(file=f, role="calibration", leds=[], rotation=0.0, repeat=0, exposure_s=0.01, iso=100,
                         aperture=8.0, time="2024-01-01T00:00:00+00:00", sha256="0" * 64) for f in files]
    Manifest(folder=out, rig="rig.toml", material="x", images=images, meta={"source": source}).save()


def test_simulate_force_clears_its_own_earlier_capture(tmp_path):
    from glossrig.cli.verbs.simulate import _clear_own_capture

    out = tmp_path / "cap"
    (out / "linear").mkdir(parents=True)
    (out / "linear" / "led01_r0.exr").write_bytes(b"x")
    _manifest(out, "glossrig twin", ["a.dng"])
    (out / "a.dng").write_bytes(b"x")
    (out / "truth.json").write_text("{}")
    (out / ".b.dng.123.part").write_bytes(b"x")
    _clear_own_capture(out)
    assert out.is_dir() and list(out.iterdir()) == []


def test_simulate_force_never_deletes_files_it_did_not_write(tmp_path, capsys):
    out = tmp_path / "cap"
    out.mkdir()
    _manifest(out, "glossrig twin", ["a.dng"])
    (out / "a.dng").write_bytes(b"x")
    (out / "notes.txt").write_text("mine")
    rig = ROOT / "scenes" / "thesis_rig.toml"
    rc, err, _ = _run(capsys, ["simulate", "--rig", rig, "--out", out, "--force"])
    assert rc == 2 and "notes.txt" in err
    assert sorted(p.name for p in out.iterdir()) == ["a.dng", "capture.json", "notes.txt"]
    real = tmp_path / "real"
    real.mkdir()
    _manifest(real, "camera")
    rc, err, _ = _run(capsys, ["simulate", "--rig", rig, "--out", real, "--force"])
    assert rc == 2 and "glossrig simulate" in err and (real / "capture.json").exists()


@pytest.mark.parametrize("name", CASES)
def test_unwritable_output_is_one_line_exit_2_before_any_work(tmp_path, capsys, name):
    build, kind, _ = _cases(tmp_path)[name]
    blocker = tmp_path / "blocker.txt"        # a path under a regular file: unwritable even for root
    blocker.write_text("a file, not a folder\n")
    out = blocker / ("out" if kind != "file" else "out.json")
    rc, err, dt = _run(capsys, build(out))
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"glossrig {name.split()[0]}: error: ") and str(blocker) in lines[0]
    assert "not a folder" in lines[0]
    assert dt < 10                                 # module imports only; no work was done


def test_unforeseen_oserror_is_one_line_exit_2(tmp_path, capsys, monkeypatch):
    import glossrig.core.fabrication as fab

    def boom(*a, **k):
        raise PermissionError(13, "Permission denied", str(tmp_path / "out" / "halftone.png"))

    monkeypatch.setattr(fab, "fabricate", boom)
    img = tmp_path / "g.png"
    Image.fromarray(np.full((20, 20), 100, np.uint8)).save(img)
    rc, err, _ = _run(capsys, ["fabricate", img, "--width-mm", "5", "--out", tmp_path / "out"])
    assert rc == 2
    assert err.strip() == f"glossrig fabricate: error: {tmp_path / 'out' / 'halftone.png'}: Permission denied"


def test_fabricate_force_replaces_and_overwrite_is_a_deprecated_alias(tmp_path, capsys):
    img = tmp_path / "g.png"
    Image.fromarray(np.full((40, 50), 100, np.uint8)).save(img)
    out = tmp_path / "o"
    argv = ["fabricate", img, "--width-mm", "4", "--out", out]
    rc, err, _ = _run(capsys, argv)
    assert rc == 0 and (out / "summary.json").exists()
    assert re.search(r"^glossrig fabricate: wrote .*summary\.json", err, re.M)          # logged, prefixed
    rc, err, _ = _run(capsys, argv)
    assert rc == 2 and "use --force to overwrite" in err and "summary.json" in err
    assert _run(capsys, [*argv, "--force"])[0] == 0
    rc, err, _ = _run(capsys, [*argv, "--overwrite"])
    assert rc == 0 and "glossrig fabricate: warning: --overwrite is deprecated; use --force" in err
    helptext = build_parser()._subparsers._group_actions[0].choices["fabricate"].format_help()
    assert not re.search(r"^\s+--overwrite", helptext, re.M)                             # hidden
    rc, err, _ = _run(capsys, [*argv, "--force", "-q"])
    assert rc == 0 and "wrote" not in err                                 # -q: no progress messages
    assert all("warning:" in line for line in err.splitlines())           # (warnings still shown)


def test_fabricate_into_a_folder_of_other_files_is_allowed(tmp_path, capsys):
    img = tmp_path / "g.png"
    Image.fromarray(np.full((40, 50), 100, np.uint8)).save(img)
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "notes.txt").write_text("x")
    assert _run(capsys, ["fabricate", img, "--width-mm", "4", "--out", tmp_path / "o"])[0] == 0


def _leaf_parsers(p: argparse.ArgumentParser, path=()):
    subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, p
    for a in subs:
        for name, child in a.choices.items():
            yield from _leaf_parsers(child, (*path, name))


def test_every_verb_and_sub_verb_takes_v_and_q():
    leaves = list(_leaf_parsers(build_parser()))
    assert len(leaves) >= 15
    for path, p in leaves:
        for opt in ("-v", "--verbose", "-q", "--quiet"):
            assert opt in p._option_string_actions, (path, opt)
    parser = build_parser()
    for argv in (["calibrate", "-q", "camera", "d", "--out", "o"], ["calibrate", "camera", "d", "--out", "o", "-q"],
                 ["fit", "s.parquet", "--quiet"], ["design", "coverage", "--rig", "r", "--out", "o", "-q"]):
        assert parser.parse_args(argv).quiet is True
    assert parser.parse_args(["design", "coverage", "--rig", "r", "--out", "o"]).quiet is False
    assert parser.parse_args(["simulate", "--out", "o", "-v"]).verbose is True


WRITERS = {("simulate",), ("calibrate", "camera"), ("calibrate", "geometry"), ("calibrate", "lamps"), ("extract",),
           ("fit",), ("model", "crossval"), ("model", "fit"), ("fabricate",), ("design", "coverage"),
           ("design", "optimise"), ("design", "errors"), ("design", "exposures"), ("diagnose",), ("demo",)}


def test_every_writing_verb_has_force():
    leaves = dict(_leaf_parsers(build_parser()))
    for path in WRITERS:
        assert "--force" in leaves[path]._option_string_actions, path
    assert "--force" not in leaves[("capture",)]._option_string_actions      # a capture is never replaced


def test_progress_bars_need_a_terminal_and_no_q(monkeypatch):
    class Tty(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr("sys.stderr", io.StringIO())
    assert progress_enabled(True) is False
    monkeypatch.setattr("sys.stderr", Tty())
    assert progress_enabled(True) is True and progress_enabled(False) is False
    log = logging.getLogger("glossrig")
    monkeypatch.setattr(log, "level", logging.WARNING)          # what -q sets
    assert progress_enabled(True) is False


def test_hardware_progress_bar_is_off_without_a_terminal(monkeypatch):
    from glossrig.hardware.progress import Progress

    monkeypatch.setattr("sys.stderr", io.StringIO())
    bar = Progress(10.0, 3)
    assert bar._bar.disable
    bar.close()


def test_every_tqdm_call_site_asks_progress_enabled():
    """Each bar in the package goes through glossrig.core.progress (grep over the sources)."""
    sites = []
    for folder in ("core", "twin", "hardware", "cli"):
        for f in (ROOT / folder).rglob("*.py"):
            text = f.read_text()
            for m in re.finditer(r"\btqdm\(", text):
                sites.append((f.name, text[m.end():m.end() + 300]))
    assert len(sites) >= 6
    for name, call in sites:
        assert "progress_enabled(" in call, (name, call)


def test_no_hand_made_message_prefixes_in_the_verbs():
    for f in (ROOT / "cli" / "verbs").glob("*.py"):
        text = f.read_text()
        assert not re.search(r"\[(fit|demo|design)\]", text), f.name
        assert "file=sys.stderr" not in text, f.name


def test_logging_restores_after_a_verb(capsys):
    log = logging.getLogger("glossrig")
    before = (log.level, log.propagate, list(log.handlers))
    main(["fit", "/nonexistent/x.parquet", "-q"])
    capsys.readouterr()
    assert (log.level, log.propagate, list(log.handlers)) == before

def test_logged_store_says_each_measured_unit_from_the_capture_s_own_units():
    """Units are known as data (capture_units' (rotation, LED) pairs, by extract's unit_name):
    every unit saved is said once with its count of the capture's units; other entries of the
    work store (a unit's inputs, a stage) are not; a unit of a rotation with a fraction keeps it."""
    from glossrig.cli.verbs.diagnose import logged_store
    from glossrig.core.extraction.extract import unit_name
    from glossrig.core.progress import Elapsed

    class Store:
        def __init__(self):
            self.saved = []

        def save(self, name, value):
            self.saved.append(name)

    lines = []
    units = {"sample": [(0.0, 5), (0.0, 9), (-22.5, 5)], "reference": [(0.0, 5)]}
    store = logged_store(Store, lines.append, Elapsed(), units)()
    names = [unit_name("sample-", 0.0, 9), "sample-rot0-led9-inputs", "material_fit",
             unit_name("reference-", 0.0, 5), unit_name("sample-", -22.5, 5)]
    for n in names:
        store.save(n, None)
    assert store.saved == names                      # the store's own save still runs
    assert [re.sub(r" \(\d+ s, CPU \d+ s\)$", "", s) for s in lines] == [
        "measured sample LED 9 at rotation 0 (1 of 3)", "measured reference LED 5 at rotation 0 (1 of 1)",
        "measured sample LED 5 at rotation -22.5 (2 of 3)"]
    assert all(re.search(r" \(\d+ s, CPU \d+ s\)$", s) for s in lines)


def test_elapsed_counts_wall_and_this_process_s_cpu():
    from glossrig.core.progress import Elapsed

    e = Elapsed()
    t = time.process_time()
    while time.process_time() - t < 0.3:            # busy: CPU time grows with wall time
        pass
    time.sleep(0.3)                                 # idle: wall time only
    wall, cpu = e.seconds()
    assert 0.6 <= wall and 0.3 <= cpu < wall
    assert re.fullmatch(r"\d+ s, CPU \d+ s", str(e))
