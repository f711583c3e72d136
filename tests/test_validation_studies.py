"""The blind study's trial plan and the witness table read back from a study's reports
(validation/diagnose: blind_study.py, witness_check.py)."""
from __future__ import annotations

import json

import pytest

from validation.diagnose import blind_study, witness_check


def test_a_rotation_is_hidden_only_in_a_material_that_turns():
    """An isotropic real material turned about its normal is the same BRDF (the twin refuses the
    effect): the trial keeps the slot's other causes, with the magnitudes of every run."""
    m, hidden, absent = blind_study.draw(36)
    assert m == "sample_2_6" and set(hidden) == {"sample_rotation_offset"} and not absent
    for k in (37, 38):
        m, hidden, absent = blind_study.draw(k)
        assert m != "sample_2_6" and hidden == {} and set(absent) == {"sample_rotation_offset"}
    m, hidden, absent = blind_study.draw(58)
    assert set(hidden) == {"channel_response"} and set(absent) == {"sample_rotation_offset"}
    lo, hi, _ = blind_study.CAUSES["channel_response"]
    assert lo <= hidden["channel_response"] <= hi
    # the two-effect slot of the Ward material hides both
    assert set(blind_study.draw(57)[1]) == {"channel_response", "sample_rotation_offset"}


def test_a_reused_null_capture_keeps_the_code_it_was_made_with(tmp_path, monkeypatch):
    """--rediagnose diagnoses the kept null captures again: their records must still say which code
    made each capture (before, a reused null's capture version was written as unknown)."""
    from types import SimpleNamespace

    made = {"commit": "0123abc", "dirty": False}
    monkeypatch.setattr(blind_study, "has_raws", lambda cap: True)      # the capture is kept
    _kept_null(tmp_path / "n01", 1)
    a = SimpleNamespace(no_diagnose=True, diagnose_code={"commit": "fedcba9", "dirty": False})
    rec = blind_study.null_capture(1, tmp_path, a, {}, None, prev={"null": 1, "code": {"capture": made}})
    assert rec["capture_reused"] and rec["code"]["capture"] == made
    # no earlier record: the version is not known, and the record says so rather than guessing
    assert blind_study.null_capture(1, tmp_path, a, {}, None)["code"]["capture"] is None


def _kept_null(cap, j: int, seed: int | None = None) -> None:
    """WORK/nJJ as the study keeps it (--keep-raws), but for its images: the manifest the simulate
    command of null J (or of SEED) records, and the rig's copy."""
    from glossrig.core.capture import Manifest
    from glossrig.twin.simulate import OPTIONS_KEY
    from validation import common

    args, kw = blind_study.simulate_args(blind_study.MATERIALS[j % 3], blind_study.NULL_SEED + j if seed is None
                                         else seed)
    opts = common.simulate_options(*common.capture_argv(*args, leds=kw["leds"]), extra=kw["extra"])
    cap.mkdir(parents=True)
    Manifest(cap, "rig.toml", "sample", complete=True, meta={OPTIONS_KEY: opts}).save()
    (cap / "rig.toml").write_bytes(common.RIG.read_bytes())


def test_a_kept_capture_made_for_another_plan_is_not_diagnosed_again(tmp_path, monkeypatch):
    """--rediagnose diagnoses kept captures as what they were made as: a null capture of another seed,
    or a trial whose record hides other causes than the plan now draws, stops with an InputError
    naming the folder, before anything is diagnosed."""
    from types import SimpleNamespace

    from glossrig.core.errors import InputError

    monkeypatch.setattr(blind_study, "has_raws", lambda cap: True)
    _kept_null(tmp_path / "n02", 2, seed=blind_study.NULL_SEED + 7)
    a = SimpleNamespace(no_diagnose=True, diagnose_code=None)
    with pytest.raises(InputError, match=r"n02/capture\.json: .*other options \(seed: capture 5007, now 5002\)"):
        blind_study.null_capture(2, tmp_path, a, {}, None)

    material, hidden, absent = blind_study.draw(12)
    record = {"trial": 12, "material": material, "hidden": hidden, "not_hidden": absent}
    blind_study.check_kept_trial(tmp_path / "t012", record, material, hidden, absent)      # as made: accepted
    other = {**record, "hidden": {c: v * 2 for c, v in hidden.items()}}
    with pytest.raises(InputError, match=r"t012: the kept capture was made for another trial plan \(hidden: "):
        blind_study.check_kept_trial(tmp_path / "t012", other, material, hidden, absent)
    with pytest.raises(InputError, match="without its record"):
        blind_study.check_kept_trial(tmp_path / "t012", None, material, hidden, absent)
    bases = {m: (None, None) for m in blind_study.MATERIALS}
    with pytest.raises(InputError, match="another trial plan"):
        blind_study.trial(12, tmp_path, a, bases, None, reuse=True, prev=other)


def _report(folder, verdict, dr, se, sig):
    folder.mkdir(parents=True)
    (folder / "report.json").write_text(json.dumps({
        "verdict": verdict, "ranking": [verdict], "causes": [{"name": "sample_radius_error", "refuted": None}],
        "meta": {"sample_radius_silhouette": {"dr": dr, "se": se, "significant": sig, "why_not": None if sig else "x"},
                 "led_position_band": None}}))


def test_witness_table_reads_a_studys_reports(tmp_path, capsys):
    trials = [{"trial": 0, "material": "m", "hidden": {}, "true_magnitude": {}},
              {"trial": 1, "material": "m", "hidden": {"sample_radius_error": 0.5},
               "true_magnitude": {"sample_radius_error": 0.5}}]
    (tmp_path / "trials.json").write_text(json.dumps(trials))
    _report(tmp_path / "t000_report", "none", 0.01, 0.03, False)
    _report(tmp_path / "t001_report", "sample_radius_error", 0.52, 0.03, True)
    assert witness_check.main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "captures hiding no sample_radius_error: 1; a signature named in 0" in out
    assert "| t001 | m | sample_radius_error | +0.500 | +0.520 | 0.030 | yes | sample_radius_error |" in out
    dst = tmp_path / "w.md"
    dst.write_text("kept")
    with pytest.raises(SystemExit) as e:
        witness_check.main([str(tmp_path), "--out", str(dst)])
    assert e.value.code == 2 and dst.read_text() == "kept"


def test_a_twin_study_plan_or_capture_is_reused_only_for_what_it_was_made_for(tmp_path, monkeypatch):
    """validation.design.twin_study keeps each `glossrig design exposures` plan and its capture in
    WORK: run again with another scale (or seed, LEDs, ...) the kept plan is refused, naming the
    plan file; a complete capture not made with the kept plan is refused, naming its manifest."""
    import hashlib

    from glossrig.core.capture import Manifest
    from glossrig.core.errors import InputError
    from validation import common
    from validation.design import twin_study

    calls = []

    def run(*args, **kw):
        if args[0] == "design":
            return common.glossrig(*args, **kw)
        calls.append(args)            # the capture itself is not made here

    monkeypatch.setattr(twin_study, "glossrig", run)
    out = tmp_path / "sample_2_6_s1_plan"
    monkeypatch.setattr(twin_study, "needs_capture", lambda o: not common.capture_complete(o))
    twin_study.planned_capture(out, common.RIG, "sample_2_6", "6,10", "0", 0.1, 1)
    plan = out.with_suffix(".plan.toml")
    assert plan.is_file() and len(calls) == 1 and calls[0][0] == "capture"
    sha = hashlib.sha256(plan.read_bytes()).hexdigest()
    out.mkdir()
    Manifest(out, "rig.toml", "sample_2_6", complete=True, meta={"plan": {"sha256": sha}}).save()
    twin_study.planned_capture(out, common.RIG, "sample_2_6", "6,10", "0", 0.1, 1)       # reused as it is
    assert len(calls) == 1
    with pytest.raises(InputError, match=r"plan\.toml: the plan kept here was made for another capture "
                                         r"\(scale: plan 0\.1, now 0\.2\)"):
        twin_study.planned_capture(out, common.RIG, "sample_2_6", "6,10", "0", 0.2, 1)
    with pytest.raises(InputError, match=r"leds: plan \[6, 10\], now \[6, 9\]; seed: plan 1, now 2"):
        twin_study.planned_capture(out, common.RIG, "sample_2_6", "6,9", "0", 0.1, 2)
    Manifest(out, "rig.toml", "sample_2_6", complete=True, meta={"plan": {"sha256": "0" * 64}}).save()
    with pytest.raises(InputError, match="capture.json: the complete capture here was not made with the plan"):
        twin_study.planned_capture(out, common.RIG, "sample_2_6", "6,10", "0", 0.1, 1)
    assert len(calls) == 1


def test_a_work_folder_keeps_the_leds_of_its_study(tmp_path, monkeypatch):
    """blind_study.use_leds: a new WORK records its LEDs; a later run with other LEDs stops with a
    message naming the kept ones; a WORK made before leds.json is the two-LED study."""
    monkeypatch.setattr(blind_study, "LEDS", blind_study.LEDS)
    new = tmp_path / "new"
    new.mkdir()
    blind_study.use_leds(new, "middle")
    assert blind_study.study_leds(new) == (5, 6, 7, 8, 9, 10, 11, 12) == blind_study.LEDS
    with pytest.raises(SystemExit, match="holds a study of LEDs .5, 6, 7, 8, 9, 10, 11, 12., not .6, 9."):
        blind_study.use_leds(new, "6,9")
    old = tmp_path / "old"
    old.mkdir()
    (old / "trials.json").write_text("[]")
    assert blind_study.study_leds(old) == (6, 9)
    with pytest.raises(SystemExit, match="made before --leds"):
        blind_study.use_leds(old, "middle")
    blind_study.use_leds(old, "6,9")
    assert json.loads((old / "leds.json").read_text()) == [6, 9]
    assert blind_study.study_leds(tmp_path / "none") is None
