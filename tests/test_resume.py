"""Reuse only with matching inputs, and resumable demo / extract / diagnose (issue #16).

The shared mechanism is :mod:`glossrig.core.checkpoint`. The demo's step logic is
tested with its sub-verb dispatch replaced by a fake that records which steps run
(fast); extract and diagnose are interrupted for real on a small twin capture
(camera and lamps taken from the twin's truth, so no calibration captures are
rendered) and resumed, and their results compared with an uninterrupted run.
"""
from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest

from glossrig.cli.main import main
from glossrig.core.checkpoint import WorkStore, fingerprint, work_folder_for
from glossrig.core.errors import InputError

# ------------------------------------------------------------------ the work store


def test_work_store_reuses_units_only_when_resuming_with_the_same_inputs(tmp_path):
    f = tmp_path / "input.txt"
    f.write_text("a")
    fp = fingerprint(files={"in": f}, options={"k": 1})
    w = WorkStore(tmp_path / "out.partial", fp)
    w.save("unit-1", pd.DataFrame({"x": [1.5, 2.5]}))
    w.save("stage", {"v": [1, 2]})
    # resumed with the same inputs: both units are there, exactly
    w2 = WorkStore(tmp_path / "out.partial", fingerprint(files={"in": f}, options={"k": 1}), resume=True)
    assert sorted(w2.reused) == ["stage", "unit-1"]
    pd.testing.assert_frame_equal(w2.load("unit-1"), pd.DataFrame({"x": [1.5, 2.5]}))
    assert w2.get_or_compute("stage", lambda: pytest.fail("recomputed")) == {"v": [1, 2]}
    # an input file changed: its units are not reused
    f.write_text("b")
    w3 = WorkStore(tmp_path / "out.partial", fingerprint(files={"in": f}, options={"k": 1}), resume=True)
    assert w3.units() == [] and not w3.has("unit-1")
    w3.save("unit-1", pd.DataFrame({"x": [0.0]}))
    # another option, or no --resume: discarded as well
    assert WorkStore(tmp_path / "out.partial", fingerprint(files={"in": f}, options={"k": 2}), resume=True).units() == []
    fp4 = fingerprint(files={"in": f}, options={"k": 2})
    WorkStore(tmp_path / "out.partial", fp4).save("u", {"a": 1})
    assert WorkStore(tmp_path / "out.partial", fp4, resume=False).units() == []
    w.remove()
    assert not (tmp_path / "out.partial").exists()


def test_results_of_other_code_are_not_reused(tmp_path, monkeypatch):
    """The fingerprint holds the version and the source commit: a unit made by another
    commit of the code (same inputs, same options) is redone, not reused."""
    import glossrig.core.checkpoint as cp

    f = tmp_path / "input.txt"
    f.write_text("a")
    monkeypatch.setattr(cp, "source_commit", lambda: "1" * 40)
    WorkStore(tmp_path / "out.partial", fingerprint(files={"in": f})).save("u", {"a": 1})
    assert WorkStore(tmp_path / "out.partial", fingerprint(files={"in": f}), resume=True).units() == ["u"]
    monkeypatch.setattr(cp, "source_commit", lambda: "2" * 40)
    assert WorkStore(tmp_path / "out.partial", fingerprint(files={"in": f}), resume=True).units() == []
    monkeypatch.setattr(cp, "glossrig_version", lambda: "9.9.9")
    assert fingerprint(files={"in": f})["version"] == "9.9.9"


def test_work_store_never_removes_a_foreign_folder(tmp_path):
    d = tmp_path / "samples.parquet.partial"
    d.mkdir()
    (d / "mine.txt").write_text("keep")
    with pytest.raises(InputError, match="samples.parquet.partial"):
        WorkStore(d, fingerprint(options={}), resume=True)
    assert (d / "mine.txt").read_text() == "keep"


# ------------------------------------------------------------------ demo (fake steps)

WARD = {k: 0.1 for k in ("rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation")}


class FakeSteps:
    """Stands in for ``glossrig <verb>``: writes small outputs whose content changes on
    every run (as real renders and fits do) and records (output name, flag) per call."""

    def __init__(self):
        self.calls: list[tuple[str, str]] = []
        self.n = 0
        self.interrupt: str | None = None      # output name whose step is interrupted
        self.resume_fails = False

    def __call__(self, argv):
        argv = list(argv)
        out = Path(argv[argv.index("--out") + 1])
        flag = "--resume" if "--resume" in argv else "--force" if "--force" in argv else ""
        self.calls.append((out.name, flag))
        self.n += 1
        if flag == "--resume" and self.resume_fails and argv[0] != "measure":
            return 2
        if flag == "--force" and argv[0] != "measure":   # the demo clears a stale capture itself
            assert not out.exists(), f"{out} was not cleared before the step was redone"
        if argv[0] == "simulate":
            out.mkdir(parents=True, exist_ok=True)
            if self.interrupt == out.name:
                self.interrupt = None
                (out / "capture.json").write_text(json.dumps({"complete": False, "argv": argv}))
                (out / ".img_0001.dng.part").write_bytes(b"half")
                return 130
            mat = argv[argv.index("--material") + 1] if "--material" in argv else "checkerboard"
            (out / "capture.json").write_text(json.dumps({"complete": True, "argv": argv, "n": self.n}))
            (out / "truth.json").write_text(json.dumps({
                "material": {"label": mat}, "camera_matrix": [[1000.0, 0, 50.0], [0, 1000.0, 40.0], [0, 0, 1]],
                "led_positions_mm": {"5": [0.0, 0.0, 100.0]}}))
        elif argv[:2] == ["calibrate", "camera"]:
            out.write_text(json.dumps({"fx": 1000.0, "fy": 1000.0, "cx": 50.0, "cy": 40.0, "n": self.n}))
        elif argv[:2] == ["calibrate", "lamps"]:
            out.write_text(json.dumps({"lamps_mm": {"5": [0.0, 0.0, 100.0]}, "n": self.n}))
        elif argv[0] == "extract":
            out.write_text(f"samples {self.n}")
        elif argv[0] == "fit":
            out.write_text(json.dumps({"luminance": WARD, "n": self.n}))
        elif argv[0] == "measure":              # writes into the demo's folder, keeping its own step records
            sample = Path(argv[1])
            label = json.loads((sample / "truth.json").read_text())["material"]["label"]
            (out / "fit.json").write_text(json.dumps({"luminance": WARD, "n": self.n}))
            (out / "recovery.json").write_text(json.dumps({"format": "glossrig-recovery/1",
                                                           "material": {"label": label, "fitted": WARD}}))
        return 0

    def take(self):
        calls, self.calls = self.calls, []
        return calls


ALL = ["checker", "specular", "reference", "sample", "demo"]      # "demo": glossrig measure --out OUT
MEASURE = ("demo", "--resume")                                       # measure decides itself what to redo


@pytest.fixture
def fake(monkeypatch):
    from glossrig.cli.verbs import demo

    f = FakeSteps()
    monkeypatch.setattr(demo, "_dispatch", f)
    return f


def _demo(out, *extra):
    return main(["demo", "--out", str(out), "--scale", "0.1", "-q", *map(str, extra)])


def test_demo_redoes_exactly_the_steps_whose_inputs_changed(tmp_path, fake):
    out = tmp_path / "demo"
    assert _demo(out) == 0
    assert [c[0] for c in fake.take()] == ALL
    assert _demo(out, "--resume") == 0                                  # same inputs: no capture redone
    assert fake.take() == [MEASURE]
    assert _demo(out, "--resume", "--material", "lambert:0.3") == 0       # another material
    assert fake.take() == [("sample", "--force"), MEASURE]
    assert json.loads((out / "sample" / "truth.json").read_text())["material"]["label"] == "lambert:0.3"
    assert _demo(out, "--resume", "--material", "lambert:0.3", "--scale", 0.12) == 0   # another scale
    assert [c[0] for c in fake.take()] == ALL
    (out / "reference" / "capture.json").write_text("edited by hand")   # a step's output changed
    assert _demo(out, "--resume", "--material", "lambert:0.3", "--scale", 0.12) == 0
    assert fake.take() == [("reference", "--force"), MEASURE]
    assert _demo(out, "--force", "--material", "lambert:0.3", "--scale", 0.12) == 0    # start over
    assert fake.take() == [(n, "--force") for n in ALL]


def test_demo_refuses_an_existing_folder_without_resume_or_force(tmp_path, fake, capsys):
    out = tmp_path / "demo"
    assert _demo(out) == 0
    fake.take()
    capsys.readouterr()
    assert _demo(out, "--material", "lambert:0.3") == 2
    err = capsys.readouterr().err
    assert str(out) in err and "--resume" in err and "--force" in err and len(err.strip().splitlines()) == 1
    assert fake.take() == []
    assert _demo(out, "--resume", "--force") == 2


@pytest.mark.parametrize("resume_fails", [False, True])
def test_interrupted_demo_is_continued_not_a_dead_end(tmp_path, fake, resume_fails, capsys):
    out = tmp_path / "demo"
    fake.interrupt = "sample"
    assert _demo(out) == 130                                            # Ctrl-C during the sample capture
    assert "interrupted" in capsys.readouterr().err
    assert [c[0] for c in fake.take()] == ALL[:4]
    assert json.loads((out / "sample" / "capture.json").read_text())["complete"] is False
    fake.resume_fails = resume_fails
    assert _demo(out, "--resume") == 0
    calls = fake.take()
    if resume_fails:       # the verb could not continue it: the demo removes the half capture and redoes it
        assert calls == [("sample", "--resume"), ("sample", "--force"), MEASURE]
    else:                  # simulate's own --resume completes the capture
        assert calls == [("sample", "--resume"), MEASURE]
    assert json.loads((out / "sample" / "capture.json").read_text())["complete"] is True
    assert _demo(out, "--resume") == 0 and fake.take() == [MEASURE]


# ------------------------------------------------------------------ extract and diagnose (twin)


@pytest.fixture(scope="module")
def caps(tiny_captures):
    """One-LED sample and reference captures at scale 0.12; camera and lamps from the twin's truth
    (the shared fixture of conftest.py)."""
    return tiny_captures


def _inputs(d):
    return [d / "sample", "--reference", d / "ref", "--camera", d / "camera.json", "--lamps", d / "lamps.json"]


@pytest.mark.mitsuba
def test_extract_resumes_an_interrupted_run_and_equals_an_uninterrupted_one(caps, tmp_path, monkeypatch, capsys):
    import glossrig.core.extraction.extract as ex

    full, part = tmp_path / "full.parquet", tmp_path / "part.parquet"
    assert main(["extract", *map(str, _inputs(caps)), "--out", str(full), "--no-progress"]) == 0
    assert not work_folder_for(full).exists()                           # removed once the output is written
    real, calls = ex.led_values, []

    def interrupted(*a, **k):
        calls.append(a[3])
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(ex, "led_values", interrupted)
    # --workers 1: the patched led_values runs in this process only
    assert main(["extract", *map(str, _inputs(caps)), "--out", str(part), "--no-progress", "--workers", "1"]) == 130
    assert not part.exists() and len(list(work_folder_for(part).glob("*.parquet"))) == 1
    counted = []
    monkeypatch.setattr(ex, "led_values", lambda *a, **k: counted.append(a[3]) or real(*a, **k))
    assert main(["extract", *map(str, _inputs(caps)), "--out", str(part), "--no-progress", "--resume",
                 "--workers", "1"]) == 0
    assert len(counted) == 1                         # the sample's LED reused, the reference's measured
    pd.testing.assert_frame_equal(pd.read_parquet(part), pd.read_parquet(full), check_exact=True)
    assert not work_folder_for(part).exists()


@pytest.mark.slow
@pytest.mark.mitsuba
def test_diagnose_resumes_an_interrupted_run_and_writes_the_same_report(caps, tmp_path, monkeypatch):
    import glossrig.core.diagnose as dg

    args = [*map(str, _inputs(caps)), "--no-progress"]
    full, part = tmp_path / "full", tmp_path / "part"
    real_frames, real_brdf = dg.FrameStage, dg.brdf_causes

    class Interrupted:
        """The frame-space stage's worker, interrupted (Ctrl-C) while the BRDF-space causes finish."""

        def __init__(self, *a, **k):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def result(self):
            raise KeyboardInterrupt

    monkeypatch.setattr(dg, "FrameStage", Interrupted)
    assert main(["diagnose", *args, "--out", str(part)]) == 130
    assert not part.exists()
    assert {"brdf_causes", "material_fit"} <= {p.stem for p in work_folder_for(part).glob("*.pkl")}
    monkeypatch.setattr(dg, "FrameStage", real_frames)
    monkeypatch.setattr(dg, "brdf_causes", lambda m, log=None: pytest.fail("BRDF-space causes were recomputed"))
    assert main(["diagnose", *args, "--out", str(part), "--resume"]) == 0
    assert not work_folder_for(part).exists()
    monkeypatch.setattr(dg, "brdf_causes", real_brdf)
    assert main(["diagnose", *args, "--out", str(full)]) == 0
    a, b = (json.loads((p / "report.json").read_text()) for p in (part, full))
    a["meta"].pop("time_s"), b["meta"].pop("time_s")
    assert a == b
