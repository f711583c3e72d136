"""Blind study of glossrig diagnose (issues 7 and 14): hidden causes at seeded random magnitudes,
on the twin's Ward material and on two real measured materials, one or two causes at a time.

    nice -n 5 python -m validation.diagnose.blind_study --work WORK --trials 60

WORK is a folder that outlives the run (the study resumes from it; one LED set per folder); a
folder in /tmp is lost with the machine.

Materials (MATERIALS): ``sample_2_6`` (Table 9.1, the twin's Ward model) and two real RGL
measurements of ../shared/data/rgl rendered by Mitsuba's ``measured`` plugin
(``satin_rosaline_rgb``, a glossy satin; ``ilm_l3_37_matte_rgb``, a matte paint), so that what is
hidden sits on materials no one here wrote.

Calibration (first run, in WORK/calibration, unless --camera, --lamps and --reference
name one of the nominal rig at scale 0.25): camera and lamps by
``validation.common.calibrate`` (12 checkerboard views, seed 1; a
transparency-sheet capture of LEDs 6 and 9, seed 2) and a lambert:0.8 reference capture
(LEDs 6 and 9, rotation 0, seed 3), all ``--ideal`` like the trials; reused by every
trial, the reference measured once. Set-up per material (first run): one null capture
(seed 999, 998, 997) whose Ward fit becomes the material fit passed as --fit to its
trials (a fit from another capture of the material, so a rotation offset is testable),
and whose DNGs are rewritten outside the twin for the sensor effects of
``glossrig.twin.rewrite_raw`` (black level offset, non-linearity, shutter error, per-channel
response, and ``axis_step``, an effect outside diagnose's catalogue); sample_2_6's null capture
gives the holder and cylinder poses every trial reuses (the rig and its poses are the same
for every material).

Trial k (``plan(k)``): material ``MATERIALS[k mod 3]``, slot ``(k div 3) mod len(SLOTS)``: no
effect, one cause of the catalogue, ``axis_step`` (answer: "unexplained" with the axis
position as the variable carrying the structure) or two causes at once (PAIRS; answer: both
among the two first causes of report.json's "ranking", :func:`glossrig.core.diagnose.report.ranking`). Magnitudes are drawn from the trial's seed in
each cause's range (CAUSES). Captures: LEDs 6, 9, rotation 0, scale 0.25, ``--ideal``, seed
1000 + k; twin effects by ``--effects``, rewritten ones afterwards. A sample rotation is not hidden
in an isotropic real material (NOT_IN: the same BRDF turned about its normal gives the same images,
and the twin refuses it); its slot counts by the causes it does hide (a null, or a single effect), and
the trial records the drawn rotation as ``not_hidden``. Then diagnose runs blind.
Budget per trial: BRDF rows capped at ``ROWS``, frame pixels at ``PIXELS``, rows of the
geometry causes' non-linear fits at ``FIT_ROWS``. Resumable: finished trials are kept in
WORK/trials.json; rerunning continues. After the trials, --nulls independent null captures
(seeds 5000+, WORK/nulls.json; materials in turn) measure each cause's null spread apart from
the trials. Each trial records the commit (and whether core/ or twin/ had uncommitted
changes) its capture and its diagnosis ran with. Writes validation/diagnose/blind_study.md.
With ``--keep-raws`` the trials' raw files stay (about 110 MB a trial); ``--rediagnose``
diagnoses every finished trial and null again whose diagnosis ran with other code than this
checkout's - on the kept raws, else on the capture made again from the same seed (the twin is
deterministic, so it is the same capture) - so a change to diagnose is measured on the same
trials. A kept capture is diagnosed again only as what it was made as: a trial's record must
hide what this checkout's plan draws (:func:`check_kept_trial`), a null capture must be the
one its simulate command makes (:func:`validation.common.check_capture`); else the run stops
with a message naming the folder (exit status 2).

What counts (issue 14): top-1 on single effects (the verdict is the hidden cause, or
"unexplained" for axis_step); two-effect trials: both hidden causes among the first two of
the ranking; a false alarm is a null capture whose verdict is not "none" (twin material) or
names an instrument cause or "unexplained" (real materials, whose departures from Ward are
material causes, reported apart).
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import time
from datetime import datetime
from pathlib import Path

import numpy as np

from glossrig.core.capture import load_manifest, read_truth
from glossrig.core.errors import InputError
from validation.common import calibrate, capture, check_capture
from validation.paths import rgl_dir
from validation.provenance import code_version

OUT = Path(__file__).parent / "blind_study.md"
LEDS = (6, 9)
ROWS, PIXELS, FIT_ROWS = 12_000, 3_000, 3_000
#: the twin's Ward material and two real measurements (module docstring); the first gives the poses
MATERIALS = ("sample_2_6", "satin_rosaline_rgb", "ilm_l3_37_matte_rgb")
#: materials whose BRDF is the model diagnose fits (a null verdict other than "none" is a false alarm)
WARD_MATERIALS = ("sample_2_6",)
#: causes a material cannot carry: the RGL measurements are isotropic, and an isotropic BRDF turned about
#: its normal is the same BRDF (f(R wi, R wo) = f(wi, wo)) - the twin does not turn them and refuses the
#: effect; a slot's such cause is drawn (the other magnitudes stay as they were) but not hidden
NOT_IN = {"sample_rotation_offset": set(MATERIALS) - set(WARD_MATERIALS)}
# cause -> (low, high) of the drawn magnitude (the twin catalogue's unit, or rewrite_raw's), how it is hidden
CAUSES = {"black_level_offset": (3, 15, "rewrite"), "sensor_nonlinearity": (0.01, 0.05, "rewrite"),
          "shutter_error": (2e-5, 8e-5, "rewrite"), "channel_response": (0.03, 0.06, "rewrite"),
          "stray_light": (0.002, 0.01, "twin"), "vignetting": (0.1, 0.3, "twin"), "hot_pixels": (1e-4, 1e-3, "twin"),
          "led_drift": (0.01, 0.05, "twin"), "led_emission": (5.0, 30.0, "twin"),
          "led_position_error": (1.0, 4.0, "twin"), "sample_radius_error": (0.2, 1.0, "twin"),
          "sample_rotation_offset": (1.0, 5.0, "twin"),
          "axis_step": (0.03, 0.08, "rewrite")}
SIGNED = {"sample_radius_error", "sample_rotation_offset", "axis_step"}
#: effects outside diagnose's catalogue -> the variable the "unexplained" structure must follow
OPEN_WORLD = {"axis_step": "axis_position"}
#: two causes hidden at once: a sensor effect with a light or geometry effect, and two of the same space
PAIRS = (("black_level_offset", "vignetting"), ("sensor_nonlinearity", "stray_light"),
         ("hot_pixels", "led_position_error"), ("shutter_error", "sample_radius_error"),
         ("led_emission", "vignetting"), ("channel_response", "sample_rotation_offset"))
SLOTS: tuple[tuple[str, ...], ...] = ((),) + tuple((c,) for c in CAUSES) + PAIRS
#: the rewritten captures' shortest nominal exposure is 1/4000 s (Table 4.1): shutter errors of 8-32 % of it
NULL_SEED = 5000      # independent null captures: seeds 5000 + j (trials use 1000 + k, the fits 999 - m)


def use_leds(work: Path, spec: str) -> None:
    """Set LEDS (every capture's LEDs) from ``spec`` (ids or a row name of the thesis rig), kept in
    WORK/leds.json: a work folder's trials, nulls and calibration share one LED set, so a later run on it
    with other LEDs stops with a message."""
    global LEDS
    from glossrig.core.rig import load_rig
    from validation.common import RIG

    leds = tuple(load_rig(RIG).select_leds(spec))
    kept, f = study_leds(work), work / "leds.json"
    if kept is not None and kept != leds:
        raise SystemExit(f"{work} holds a study of LEDs {kept}, not {leds}: give --leds {','.join(map(str, kept))} "
                         f"or another --work" if f.exists() else
                         f"{work} holds a study made before --leds (LEDs 6, 9): give --leds 6,9 or another --work")
    if not f.exists():
        f.write_text(json.dumps(list(leds)))
    LEDS = leds


def study_leds(work: Path) -> tuple[int, ...] | None:
    """The LEDs of the study in WORK: WORK/leds.json, or (6, 9) for a study made before it was kept
    (trials.json without it); None for a new work folder."""
    f = work / "leds.json"
    if f.exists():
        return tuple(json.loads(f.read_text()))
    return (6, 9) if (work / "trials.json").exists() else None


def material_spec(m: str) -> str:
    """The ``--material`` of a study material: a Table 9.1 name or an RGL measurement."""
    return m if m in WARD_MATERIALS else f"measured:{rgl_dir() / (m + '.bsdf')}"


def plan(k: int) -> tuple[str, tuple[str, ...]]:
    """Trial k's material and hidden causes (module docstring)."""
    return MATERIALS[k % len(MATERIALS)], SLOTS[(k // len(MATERIALS)) % len(SLOTS)]


def simulate_args(material: str, seed: int, effects: str | None = None) -> tuple[tuple, dict]:
    """The arguments of :func:`validation.common.capture` for a study capture of MATERIAL."""
    return ((material_spec(material), 0.25, seed, "0", 1),
            {"leds": ",".join(map(str, LEDS)), "extra": ("--ideal", *(["--effects", effects] if effects else []))})


def simulate(out: Path, material: str, seed: int, effects: str | None = None):
    """A fresh capture of MATERIAL (LEDS, rotation 0, scale 0.25, --ideal), output captured."""
    args, kw = simulate_args(material, seed, effects)
    capture(out, *args, **kw, mode="fresh", stdout=False, stderr=False)


def check_kept_trial(cap: Path, prev: dict | None, material: str, hidden: dict, absent: dict) -> None:
    """A trial's kept capture is diagnosed again (``--rediagnose``) only as what it was made as: its
    earlier record's material and hidden (and drawn but not hidden) causes must be what this
    checkout's plan draws for the trial (:func:`draw`), else an InputError names the folder and
    the difference - a changed plan would otherwise score an old capture against new truth."""
    now = json.loads(json.dumps({"material": material, "hidden": hidden, "not_hidden": absent}))
    if prev is None:
        raise InputError("a kept trial capture without its record in trials.json: what it hides is not known; "
                         "remove the folder to make it again", path=cap)
    diff = [f"{k}: capture {prev.get(k)!r}, plan now {v!r}" for k, v in now.items() if prev.get(k, {}) != v]
    if diff:
        raise InputError(f"the kept capture was made for another trial plan ({'; '.join(diff)}); remove it to "
                         "make it again, or use another --work (nothing was changed)", path=cap)


def calibration(work: Path, a) -> tuple[str, str, str]:
    """Camera, lamps and reference: the given ones, or the study's own calibration of the
    nominal rig in WORK/calibration (resumable)."""
    given = [a.camera, a.lamps, a.reference]
    if all(given):
        return a.camera, a.lamps, a.reference
    if any(given):
        raise SystemExit("give all of --camera, --lamps and --reference, or none")
    out = work / "calibration"
    out.mkdir(parents=True, exist_ok=True)
    leds = ",".join(map(str, LEDS))
    cam, lamps = calibrate(out, 0.25, 1, leds=leds, extra=("--ideal",))
    ref = capture(out / "reference", "lambert:0.8", 0.25, 3, "0", 1, leds=leds, extra=("--ideal",))
    return str(cam), str(lamps), str(ref)


def setup(work: Path, a, material: str) -> tuple[Path, Path]:
    """The material's shared null capture and its material fit (resumable)."""
    m = MATERIALS.index(material)
    null = work / ("null_base" if m == 0 else f"null_base_{material}")
    fit = work / ("fit.json" if m == 0 else f"fit_{material}.json")
    if not fit.exists():
        from glossrig.core.diagnose.data import load_brdf
        from glossrig.core.fitting.fit import fit_samples
        from glossrig.core.calibration.intrinsics import load_camera
        from glossrig.core.calibration.lamps import load_lamps

        simulate(null, material, 999 - m)
        d = load_brdf(null, a.reference, load_camera(a.camera), load_lamps(a.lamps))
        from glossrig.core.fitting.export import write_fit_json

        mf = fit_samples(d.table, channels=["luminance"], footprint=False, budget=False)
        write_fit_json(mf, fit, provenance={"source": str(null)})
    return null, fit


def one_calibration(null: Path, camera):
    """Every trial's capture is measured with the first material's null capture's geometric
    calibration (holder and cylinder poses; the same camera and rig in every trial), computed
    once: the pose refinement is ~40 s a capture, more than the rest of a trial's diagnosis."""
    import glossrig.core.calibration.poses as poses

    original = poses.calibrate_capture
    cache = {}

    def calibrate_capture(capture_dir, camera_json, rotation=None, **kw):
        key = (str(camera_json), rotation)
        if key not in cache:
            cache[key] = original(null, camera_json, rotation=rotation, **kw)
        return cache[key]

    poses.calibrate_capture = calibrate_capture


def true_magnitude(cause: str, value: float, cap: Path) -> float:
    """The hidden magnitude in the unit diagnose reports it in."""
    if cause == "black_level_offset":   # raw files hold integers: a rewrite adds round(value) DN
        return float(round(value))
    t = read_truth(cap) if (cap / "truth.json").exists() else {}
    if cause == "led_position_error":
        off = t["effects"]["detail"]["led_offset_mm"]
        return float(np.sqrt(np.mean([np.square(off[str(k)]) for k in LEDS])))
    if cause == "led_drift":   # largest |gain slope| (1/min) at the middle of an LED's sequence
        det = t["effects"]["detail"]
        man = load_manifest(cap)
        t0 = datetime.fromisoformat(t["clock_start"])
        out = []
        for k in LEDS:
            ts = [(datetime.fromisoformat(im.time) - t0).total_seconds() for im in man.images
                  if im.role == "sequence" and im.leds == [k]]
            tm = 0.5 * (min(ts) + max(ts))
            P, ph = det["drift_period_s"][str(k)], det["drift_phase"][str(k)]
            out.append(abs(value * 2 * math.pi / P * 60 * math.cos(2 * math.pi * tm / P + ph)))
        return float(max(out))
    return value


def run_diagnose(cap: Path, out: Path, a, fit: Path, ref) -> dict:
    """glossrig diagnose on one capture with the study's budget; a capture the pipeline
    refuses is a failed trial, kept as such."""
    import glossrig.core.diagnose.catalogue as catalogue
    import glossrig.core.diagnose.frames as frames
    import glossrig.core.diagnose.geometry as geometry
    from glossrig.core.diagnose import diagnose
    from glossrig.core.errors import InputError

    catalogue.MAX_BRDF_ROWS, frames.MAX_PIXELS, geometry.FIT_ROWS = ROWS, PIXELS, FIT_ROWS
    if out.exists():
        shutil.rmtree(out)
    try:
        return diagnose(cap, a.reference, a.camera, a.lamps, out, fit=fit, log=lambda *x: None,
                        reference_measured=ref, plots=False)
    except InputError as e:
        return {"verdict": "refused", "causes": [], "error": str(e)}


def hide(cap: Path, material: str, seed: int, hidden: dict[str, float], null: Path, fresh: bool = False) -> None:
    """A capture of MATERIAL with the ``hidden`` causes: the twin's ones by ``--effects`` in a
    fresh capture (or the material's null capture when there are none and not ``fresh``), then the
    rewritten ones one after the other (glossrig.twin.rewrite_raw). ``fresh``: the slot held a twin
    cause the material cannot carry (NOT_IN); its capture is still the fresh one at the trial's seed,
    the capture the twin made when it ignored the cause."""
    from glossrig.twin.rewrite_raw import rewrite_capture

    if cap.exists():
        shutil.rmtree(cap)
    twin = {c: v for c, v in hidden.items() if CAUSES[c][2] == "twin"}
    rewrite = [(c, v) for c, v in hidden.items() if CAUSES[c][2] == "rewrite"]
    if twin or fresh or not rewrite:
        src = cap if not rewrite else cap.with_name(cap.name + ".twin")
        if src.exists():
            shutil.rmtree(src)
        simulate(src, material, seed, ",".join(f"{c}={v:.6g}" for c, v in twin.items()) or None)
    else:
        src = null
    for i, (c, v) in enumerate(rewrite):
        dst = cap if i == len(rewrite) - 1 else cap.with_name(f"{cap.name}.r{i}")
        if dst.exists():
            shutil.rmtree(dst)
        rewrite_capture(src, dst, c, v)
        if src != null:
            shutil.rmtree(src)
        src = dst


def draw(k: int) -> tuple[str, dict[str, float], dict[str, float]]:
    """Trial k's material, the causes hidden in its capture with their magnitudes (drawn from the seed
    [2026, k] in each cause's range, signed ones with a random sign), and the drawn causes its material
    cannot carry (NOT_IN; drawn all the same, so that the other magnitudes are those of every run)."""
    rng = np.random.default_rng([2026, k])
    material, causes = plan(k)
    drawn = {}
    for cause in causes:
        lo, hi, _ = CAUSES[cause]
        v = float(rng.uniform(lo, hi))
        drawn[cause] = -v if cause in SIGNED and rng.random() < 0.5 else v
    hidden = {c: v for c, v in drawn.items() if material not in NOT_IN.get(c, ())}
    return material, hidden, {c: v for c, v in drawn.items() if c not in hidden}


def trial(k: int, work: Path, a, bases: dict, ref, reuse: bool = False, prev: dict | None = None) -> dict:
    """Trial k (``plan(k)``, magnitudes from the seed [2026, k]): the capture with its hidden causes,
    then diagnose. ``reuse``: diagnose the capture already in WORK/tNNN (its raws kept by
    ``--keep-raws``) instead of making it again; the same seed makes the same capture either way.
    ``prev``: the trial's earlier record (a reused capture keeps its recorded code version)."""
    material, hidden, absent = draw(k)
    null, fit = bases[material]
    cap = work / f"t{k:03d}"
    t0 = time.time()
    code = record_code(a, reuse, prev)
    if reuse:
        check_kept_trial(cap, prev, material, hidden, absent)
    else:
        hide(cap, material, 1000 + k, hidden, null, fresh=any(CAUSES[c][2] == "twin" for c in absent))
    if getattr(a, "no_diagnose", False):        # the capture alone; --rediagnose diagnoses it later
        return {"trial": k, "material": material, "hidden": hidden, "not_hidden": absent, "verdict": None, "ranking": [],
                "true_magnitude": {c: true_magnitude(c, v, cap) for c, v in hidden.items()},
                "time_s": time.time() - t0, "code": dict(code, diagnose=None), "capture_reused": reuse}
    rep = run_diagnose(cap, work / f"t{k:03d}_report", a, fit, ref)
    by = {c["name"]: c for c in rep["causes"]}
    # the report's own order of the variables it found structure along (strongest held-out gain first); a report
    # written before it kept that order: its significant entries by effect
    sig_unexpl = [{"variable": v} for v in rep.get("unexplained_variables", [])] or sorted(
        (e for e in rep.get("unexplained", []) if e.get("significant")), key=lambda e: -e["effect"])
    res = {"trial": k, "material": material, "hidden": hidden, "not_hidden": absent,
           "true_magnitude": {c: true_magnitude(c, v, cap) for c, v in hidden.items()},
           "verdict": rep["verdict"], "ranking": rep.get("ranking", []),
           "estimate": {c: by[c]["magnitude"] for c in hidden if c in by},
           "gain": {c: by[c]["gain"] for c in hidden if c in by},
           "significant": {c: by[c]["significant"] for c in hidden if c in by},
           "unexplained_variable": sig_unexpl[0]["variable"] if sig_unexpl else None,
           "top": [(x["name"], round(x["gain"], 4), x["significant"]) for x in rep["causes"][:4]],
           "time_s": time.time() - t0, "code": code, "capture_reused": reuse,
           **({"error": rep["error"]} if "error" in rep else {})}
    if not a.keep_raws:
        for f in cap.glob("*.dng"):      # keep truth and manifest, drop the raw files
            f.unlink()
    return res


def record_code(a, reuse: bool, prev: dict | None) -> dict:
    """The code versions a trial's or null's record names: a reused capture keeps the version its
    earlier record ``prev`` names (None when there is none: not known, and not guessed), a new one is
    made by this checkout; the diagnosis runs with this checkout's (``a.diagnose_code``)."""
    return {"capture": (prev or {}).get("code", {}).get("capture") if reuse else code_version(),
            "diagnose": a.diagnose_code}


def null_capture(j: int, work: Path, a, bases: dict, ref, prev: dict | None = None) -> dict:
    """Independent null capture j (material j mod 3, seed NULL_SEED + j, no trial's seed): the null
    spread of every cause's gain and fitted magnitude, measured apart from the trials. ``prev``: the
    null's earlier record (a reused capture keeps the code version recorded when it was made; None
    when there is no earlier record)."""
    material = MATERIALS[j % len(MATERIALS)]
    cap = work / f"n{j:02d}"
    t0 = time.time()
    reuse = has_raws(cap)
    code = record_code(a, reuse, prev)
    if reuse:       # made by the same simulate command (material, seed, LEDs, ...), or stop
        args, kw = simulate_args(material, NULL_SEED + j)
        check_capture(cap, *args, **kw)
    else:
        simulate(cap, material, NULL_SEED + j)
    if getattr(a, "no_diagnose", False):
        return {"null": j, "material": material, "seed": NULL_SEED + j, "verdict": None, "capture_reused": reuse,
                "time_s": time.time() - t0, "code": dict(code, diagnose=None), "causes": {}}
    rep = run_diagnose(cap, work / f"n{j:02d}_report", a, bases[material][1], ref)
    if not a.keep_raws:
        for f in cap.glob("*.dng"):
            f.unlink()
    return {"null": j, "material": material, "seed": NULL_SEED + j, "verdict": rep["verdict"], "capture_reused": reuse,
            "time_s": time.time() - t0, "code": code,
            "causes": {c["name"]: {"gain": c["gain"], "magnitude": c["magnitude"], "significant": c["significant"],
                                   "threshold": c["threshold"], "kind": c.get("kind")} for c in rep["causes"]}}


def has_raws(cap: Path) -> bool:
    """Whether the capture folder still holds its raw files (a complete capture kept by --keep-raws)."""
    from glossrig.core.capture import capture_complete

    return cap.is_dir() and any(cap.glob("*.dng")) and capture_complete(cap)


def stale(record: dict, current: dict | None) -> bool:
    """With --rediagnose: a trial or null whose diagnosis ran with other code than this
    checkout's, with code that was not recorded (a run outside a git checkout) or with
    uncommitted changes."""
    ran = record.get("code", {}).get("diagnose")
    # uncommitted changes: two different edits on one commit look alike, so they count as other code
    return current is None or ran is None or ran != current or bool(ran.get("dirty"))


# ------------------------------------------------------------------ scoring and the report

def instrument_names(trials: list[dict]) -> set[str]:
    """Names of instrument causes (everything of the catalogue that is not a material model)."""
    from glossrig.core.diagnose.catalogue import KINDS

    return {t["verdict"] for t in trials} - set(KINDS) - {"none", "unexplained", "refused"}


def correct(t: dict) -> bool:
    """A trial's success (module docstring)."""
    hidden = list(t["hidden"])
    if not hidden:
        return not false_alarm(t)
    if len(hidden) == 1:
        c = hidden[0]
        if c in OPEN_WORLD:
            return t["verdict"] == "unexplained" and t.get("unexplained_variable") == OPEN_WORLD[c]
        return t["verdict"] == c
    return set(hidden) <= set(t["ranking"][:2])


def false_alarm(t: dict) -> bool:
    """A null capture's verdict names what is not there (module docstring)."""
    from glossrig.core.diagnose.catalogue import KINDS

    if t["material"] in WARD_MATERIALS:
        return t["verdict"] != "none"
    return t["verdict"] not in ("none", *KINDS)


def label(t: dict) -> str:
    return " + ".join(t["hidden"]) or "none"


def provenance(trials: list[dict]) -> str:
    """Which code the captures and diagnoses ran with (trials.json records it per trial)."""
    def fmt(key):
        seen: dict[str, list[int]] = {}
        for t in trials:
            c = t.get("code", {}).get(key)
            lab = "unrecorded" if c is None else c["commit"] + (" + uncommitted core/twin changes" if c["dirty"] else "")
            seen.setdefault(lab, []).append(t["trial"])
        return "; ".join(f"{lab} ({len(ks)} trials, {min(ks)}-{max(ks)})" for lab, ks in seen.items())
    return f"Code: captures at {fmt('capture')}; diagnoses at {fmt('diagnose')}."


def _rate(ts: list[dict], f) -> str:
    return f"{sum(map(f, ts))}/{len(ts)} ({np.mean([f(t) for t in ts]):.1%})" if ts else "-"


def summarise(trials: list[dict], work: Path | None = None) -> str:
    trials = [t for t in trials if t.get("verdict") is not None]        # captured but not yet diagnosed: left out
    singles = [t for t in trials if len(t["hidden"]) == 1]
    catalogued = [t for t in singles if next(iter(t["hidden"])) not in OPEN_WORLD]
    openw = [t for t in singles if next(iter(t["hidden"])) in OPEN_WORLD]
    pairs = [t for t in trials if len(t["hidden"]) == 2]
    nulls = [t for t in trials if not t["hidden"]]
    ind = json.loads((work / "nulls.json").read_text()) if work and (work / "nulls.json").exists() else []
    ind = [n for n in ind if n.get("verdict") is not None]
    L = ["# diagnose blind study", "",
         "Regenerate everything - calibration, per-material null captures and fits, trials, independent null "
         "captures, this file (resumable):", "",
         f"    nice -n 5 python -m validation.diagnose.blind_study --work WORK --trials {len(trials)}"
         + ("" if LEDS == (6, 9) else f" --leds {','.join(map(str, LEDS))}"), "",
         f"Set-up: materials {', '.join(MATERIALS)} ({', '.join(WARD_MATERIALS)} is the twin's Ward model, the "
         "others real RGL measurements) on the thesis rig, "
         f"LEDs {LEDS}, rotation 0, scale 0.25, `--ideal`; one nominal camera/lamp calibration and lambert:0.8 "
         "reference for all trials; each material's fit from its own null capture (--fit); the first null "
         "capture's poses reused by every trial; sensor effects and the axis step rewritten into the DNGs "
         f"outside the twin. Budget: BRDF rows <= {ROWS}, frame pixels <= {PIXELS}, geometry-fit rows <= "
         f"{FIT_ROWS}. Trial plan: `plan(k)` (material k mod 3, slot k div 3 over {len(SLOTS)} slots: no effect, "
         f"{len(CAUSES)} single causes, {len(PAIRS)} pairs). A cause a material cannot carry is drawn but not "
         "hidden (`NOT_IN`: a sample rotation in the isotropic real materials, whose images it does not change); "
         f"such a slot counts by the causes it hides ({sum(bool(t.get('not_hidden')) for t in trials)} trials).", "",
         provenance(trials), "",
         f"trials completed: {len(trials)} ({len(singles)} single effects, {len(pairs)} with two effects, "
         f"{len(nulls)} null)  ",
         f"top-1 on single catalogued effects: {_rate(catalogued, correct)} (target >= 90 %)  ",
         f"effects outside the catalogue (axis step) -> 'unexplained' along the axis: {_rate(openw, correct)}  ",
         f"two effects, both in the top two: {_rate(pairs, correct)} (target >= 75 %)  ",
         f"false alarms on the trials' null captures: {_rate(nulls, false_alarm)}; on independent null captures: "
         f"{_rate(ind, false_alarm)} (target <= 5 %)  ",
         "", "## Per material", "", "| material | single top-1 | open world | two effects | null false alarms |",
         "|---|---|---|---|---|"]
    for m in MATERIALS:
        def of(ts, m=m):
            return [t for t in ts if t["material"] == m]
        L.append(f"| {m} | {_rate(of(catalogued), correct)} | {_rate(of(openw), correct)} | "
                 f"{_rate(of(pairs), correct)} | {_rate(of(nulls) + of(ind), false_alarm)} |")
    names = ["none"] + list(CAUSES)
    verdicts = names + sorted({t["verdict"] for t in singles + nulls} - set(names))
    M = {(a, v): 0 for a in names for v in verdicts}
    for t in singles + nulls:
        M[(label(t), t["verdict"])] += 1
    L += ["", "## Confusion matrix, single effects and nulls (rows: hidden cause, columns: verdict)", "",
          "truth \\ verdict | " + " | ".join(verdicts), "|".join(["---"] * (len(verdicts) + 1))]
    for a in names:
        if any(M[(a, v)] for v in verdicts):
            L.append(f"{a} | " + " | ".join(str(M[(a, v)]) for v in verdicts))
    L += ["", "## Trials", "",
          "| trial | material | hidden (magnitude) | recovered | gain of the hidden cause | verdict | ranking | ok |",
          "|---|---|---|---|---|---|---|---|"]
    for t in sorted(trials, key=lambda t: (label(t), t["material"], t["trial"])):
        hid = ", ".join(f"{c} {t['true_magnitude'][c]:.4g}" for c in t["hidden"]) or "none"
        hid += "".join(f" ({c} {v:.3g} drawn, not hidden: the material is isotropic)" for c, v in t.get("not_hidden", {}).items())
        est = ", ".join(f"{t['estimate'][c]:.4g}" for c in t["hidden"] if t["estimate"].get(c) is not None)
        g = ", ".join(f"{t['gain'][c]:.2%}{'*' if t['significant'][c] else ''}" for c in t["hidden"] if c in t["gain"])
        v = t["verdict"] + (f" ({t['unexplained_variable']})" if t["verdict"] == "unexplained" else "")
        L.append(f"| {t['trial']} | {t['material']} | {hid} | {est} | {g} | {v} | {', '.join(t['ranking'][:3])} | "
                 f"{'yes' if correct(t) else 'NO'} |")
    L += ["", "`*` = significant (held-out gain above threshold + penalty in every fold). Ranking: the eligible "
          "causes in the verdict's order (sensor-level first, then by gain)."]
    if ind:
        L += ["", "## Independent null captures", "", "| seed | material | verdict | false alarm |", "|---|---|---|---|"]
        L += [f"| {n['seed']} | {n['material']} | {n['verdict']} | {'yes' if false_alarm(n) else 'no'} |" for n in ind]
    return "\n".join(L) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True)
    ap.add_argument("--trials", type=int, default=3 * len(SLOTS))
    ap.add_argument("--camera", help="camera.json of the nominal rig at scale 0.25 (default: the study's own)")
    ap.add_argument("--lamps", help="lamps.json of the same calibration")
    ap.add_argument("--reference", help="lambert:0.8 reference capture (LEDs 6 and 9 at rotation 0 or a superset)")
    ap.add_argument("--nulls", type=int, default=6, help="independent null captures after the trials")
    ap.add_argument("--report", default=str(OUT), help="the Markdown report written (default: %(default)s)")
    ap.add_argument("--no-diagnose", action="store_true",
                    help="make the captures only (with --keep-raws): a later run with --rediagnose diagnoses them")
    ap.add_argument("--leds", default=",".join(map(str, LEDS)),
                    help="LEDs of every capture: ids or a row name (default: %(default)s; a work folder keeps the LEDs "
                         "it was started with, WORK/leds.json)")
    ap.add_argument("--only", help="trial numbers (e.g. 24,25,26): make, or with --rediagnose diagnose again, only "
                                   "these (with --nulls 0 no null captures); the report summarises every trial in WORK")
    ap.add_argument("--summary-only", action="store_true", help="rewrite the Markdown from WORK/trials.json")
    ap.add_argument("--keep-raws", action="store_true",
                    help="keep each trial's raw files (about 110 MB a trial) so --rediagnose need not simulate again")
    ap.add_argument("--rediagnose", action="store_true",
                    help="diagnose again, with this checkout's code, every finished trial and null whose "
                         "diagnosis ran with other code (on its kept raws, else on the capture made again "
                         "from the same seed)")
    a = ap.parse_args(argv)
    try:
        only = None if a.only is None else {int(x) for x in a.only.split(",") if x.strip()}
    except ValueError:
        raise InputError(f"--only: expected trial numbers separated by commas, got {a.only!r}") from None
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    use_leds(work, a.leds)
    store = work / "trials.json"
    done = json.loads(store.read_text()) if store.exists() else []
    if not a.summary_only:
        # import every diagnosis module now: the study runs for hours and must use one version
        import glossrig.core.diagnose.geometry  # noqa: F401
        import glossrig.core.diagnose.material_models  # noqa: F401
        from glossrig.core.extraction.extract import measure_capture
        from glossrig.core.calibration.intrinsics import load_camera
        from glossrig.core.calibration.lamps import load_lamps

        a.camera, a.lamps, a.reference = calibration(work, a)
        a.diagnose_code = code_version()      # the diagnosis modules are imported once, now
        bases = {m: setup(work, a, m) for m in MATERIALS}
        ref = measure_capture(a.reference, load_camera(a.camera), load_lamps(a.lamps))
        one_calibration(bases[MATERIALS[0]][0], a.camera)
        if a.rediagnose:
            for i, t in enumerate(done):
                if stale(t, a.diagnose_code) and (only is None or t["trial"] in only):
                    k = t["trial"]
                    done[i] = trial(k, work, a, bases, ref, reuse=has_raws(work / f"t{k:03d}"), prev=t)
                    store.write_text(json.dumps(done, indent=1))
                    print(json.dumps({x: done[i][x] for x in ("trial", "material", "hidden", "verdict", "ranking")}),
                          flush=True)
        have = {t["trial"] for t in done}
        for k in range(a.trials):
            if k in have or (only is not None and k not in only):
                continue
            done.append(trial(k, work, a, bases, ref))
            store.write_text(json.dumps(done, indent=1))
            Path(a.report).write_text(summarise(done, work))
            print(json.dumps({x: done[-1][x] for x in ("trial", "material", "hidden", "verdict", "ranking")}),
                  flush=True)
        nstore = work / "nulls.json"
        nulls = json.loads(nstore.read_text()) if nstore.exists() else []
        earlier = {n["null"]: n for n in nulls}
        if a.rediagnose:
            nulls = [n for n in nulls if not stale(n, a.diagnose_code)]     # made again below
        for j in range(a.nulls):
            if j in {n["null"] for n in nulls}:
                continue
            nulls.append(null_capture(j, work, a, bases, ref, prev=earlier.get(j)))
            nstore.write_text(json.dumps(nulls, indent=1))
            print(json.dumps({k: v for k, v in nulls[-1].items() if k != "causes"}), flush=True)
    Path(a.report).write_text(summarise(done, work))


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
