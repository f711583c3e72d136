"""Coverage of the fit's uncertainty budget on the twin (issue 15, "What it must show", first bullet).

    nice -n 10 python -m validation.uncertainty_coverage --work /tmp/h-d/coverage

Twin measurements of :data:`MATERIALS` (Table 9.1 materials and anisotropic lobes at
several lobe rotations), in rounds: round ``r`` measures every material once at scale
``--scales[r]`` with its own seeds and its own **calibration** - a twin calibration made
for that round (``validation.common.calibrate``: the camera from 12 simulated
checkerboard views, the lamps from a simulated transparency sheet, both with their
own seed), so each round's calibration errors against the twin's truth are real
calibration errors, reused by the round's materials as a real lab reuses its
calibration. Each capture has the twin's default non-idealities (the thesis's LED
fluctuations and sensor noise). The white reference (``lambert:0.8``, one capture per
scale) is stated to ``glossrig extract`` with an error drawn for each measurement,
``--reference-albedo 0.8 (1 + u z)``, ``u`` = :data:`~glossrig.core.fitting.calibration_uncertainty.ALBEDO_U_REL`,
``z ~ N(0, 1)`` (the albedo of a real reference is known to that), so the reference's
calibration error is real too.

Per measurement: ``glossrig extract`` -> the luminance fit (``fit_samples``, footprint
model, LED aperture 0: the twin's LEDs are points) -> the calibration component
(:func:`glossrig.core.fitting.calibration_uncertainty.calibration_component`, the same
call ``glossrig fit`` makes, ``--draws`` draws, the reference's angular variation
stated as 0: the twin's reference is exactly Lambertian) -> the budget with and
without it against the twin's truth. One JSON per measurement under WORK/results/
(a rerun reuses the finished ones, and the captures, calibrations and extractions; a finished
one whose calibration component used other lamp uncertainties than its round's lamps.json
states now gets that component computed again, its fit kept: :func:`stale`).

Report, per parameter (all measurements): how often the 95 % interval holds the truth
(target 90-98 %) and the median half-width of the interval over the RMS of the actual
errors (target <= 3; honest, not inflated), with and without the calibration
component. ``--report-only`` prints the report from WORK/results/.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from glossrig.twin.render import DEFAULT_SPP
from validation.common import calibrate, capture, extract

PARAMS = ("rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation")
#: Table 9.1 materials (scenes/materials) and anisotropic lobes at three lobe rotations.
MATERIALS = ("sample_0_6", "sample_2_6", "sample_4_10", "sample_5_6", "polyethylene", "sanded_original",
             "brushed_original",
             "ward:rho_d=0.05,rho_s=0.012,alpha_x=0.09,alpha_y=0.035,lobe_rotation=0.4",
             "ward:rho_d=0.05,rho_s=0.012,alpha_x=0.09,alpha_y=0.035,lobe_rotation=1.2",
             "ward:rho_d=0.05,rho_s=0.012,alpha_x=0.09,alpha_y=0.035,lobe_rotation=2.0")
REFERENCE_ALBEDO = 0.8


def render_spp(material: str, scale: float) -> int:
    """Samples per pixel of the material's captures: the twin's default, or more where its
    lobe is narrow against a pixel (:func:`glossrig.twin.render.lobe_resolving_spp`): the twin's
    Monte Carlo estimate of each pixel's integral is otherwise an error the real rig has not
    (brushed_original at scale 0.1: alpha_y -14.1 % with 4, -2.1 % with 64; section 3). Of the
    study's materials only brushed_original at scale 0.1 gets more (64). A result made before
    the spec recorded ``spp`` was made with :data:`DEFAULT_SPP`."""
    from glossrig.core.design.placement import parse_materials
    from glossrig.core.rig import default_rig_path, load_rig
    from glossrig.twin.render import lobe_resolving_spp

    (_, p), = parse_materials(material)
    return lobe_resolving_spp(load_rig(default_rig_path()), scale, min(p.alpha_x, p.alpha_y), DEFAULT_SPP)


def plan(scales: list[float], materials=MATERIALS, seed: int = 0) -> list[dict]:
    """The measurements: round ``r`` (its scale ``scales[r]`` and calibration ``r``) x material."""
    from glossrig.core.fitting.calibration_uncertainty import ALBEDO_U_REL

    out = []
    for r, s in enumerate(scales):
        for k, m in enumerate(materials):
            i = r * len(materials) + k
            z = float(np.random.default_rng([seed, i]).standard_normal())
            out.append({"id": f"r{r}_m{k}", "round": r, "material": m, "scale": float(s), "seed": 1000 + 37 * i + seed,
                        "albedo_stated": REFERENCE_ALBEDO * (1 + ALBEDO_U_REL * z), "spp": render_spp(m, float(s))})
    return out


@contextmanager
def _locked(path: Path):
    """An exclusive lock (fcntl) on PATH while the block runs: a calibration or reference
    that several processes of one study need is made by one of them."""
    import fcntl

    with open(path, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _claim(work: Path, name: str) -> bool:
    """Take the measurement NAME for this process (a claim file made atomically); False when
    another process of the study has it. A claim left by an interrupted run is taken over
    when its process is gone."""
    import os

    d = work / "claims"
    d.mkdir(exist_ok=True)
    path = d / name
    try:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        try:
            pid = int(path.read_text() or 0)
            os.kill(pid, 0)
            return False                    # its process is alive
        except (ValueError, ProcessLookupError):
            path.write_text(str(os.getpid()))
            return True
        except PermissionError:
            return False
    with os.fdopen(fd, "w") as f:
        f.write(str(os.getpid()))
    return True


def _slug(s: float) -> str:
    return f"{s:g}".replace(".", "p")


def calibration_errors(cal_dir: Path, truth_capture: Path) -> dict:
    """The round's calibration against the twin's truth (focal lengths in %, principal
    point in px, lamp positions in mm)."""
    from glossrig.core.capture import read_truth
    from glossrig.core.fitting.calibration_uncertainty import lamp_std

    t = read_truth(truth_capture)
    cam = json.loads((cal_dir / "camera.json").read_text())
    K = np.array(t["camera_matrix"])
    doc = json.loads((cal_dir / "lamps.json").read_text())
    lam = doc["lamps_mm"]
    xyz = {k: np.subtract(p, t["led_positions_mm"][k]).tolist() for k, p in lam.items() if k in t["led_positions_mm"]}
    std = {str(k): v.tolist() for k, v in lamp_std(doc).items()}
    return {"fx_percent": 100 * (cam["fx"] / K[0, 0] - 1), "fy_percent": 100 * (cam["fy"] / K[1, 1] - 1),
            "cx_px": cam["cx"] - K[0, 2], "cy_px": cam["cy"] - K[1, 2],
            "lamp_error_mm": {k: float(np.linalg.norm(v)) for k, v in xyz.items()},
            "lamp_error_xyz_mm": xyz, "lamp_std_mm": {k: std[k] for k in xyz}}


def stale(previous: dict, work: Path) -> bool:
    """Whether a finished measurement's calibration component was computed with lamp
    uncertainties other than its round's lamps.json states now (lamps.json remade, e.g.
    by a ``calibrate lamps`` that states each lamp's own uncertainty) or with another
    model of the lamps' draws (:data:`~glossrig.core.fitting.calibration_uncertainty.LAMP_DRAW`;
    a result without one was drawn independently per LED), or with lamps drawn independently of
    the camera where lamps.json now records the draws that let the fit draw them together
    (:class:`~glossrig.core.fitting.calibration_uncertainty.LampDraws`): its component is computed
    again (:func:`measure` with ``previous``)."""
    from glossrig.core.fitting.calibration_uncertainty import LAMP_DRAW, lamp_std

    doc = json.loads((work / f"cal_round{previous['spec']['round']}" / "lamps.json").read_text())
    now = lamp_std(doc)
    stated = previous.get("calibration_meta", {}).get("stated", {})
    used = stated.get("lamps_std_mm") or {}
    joint = str(stated.get("lamps_with_camera", "")).startswith("drawn with the camera draws")
    return ((stated.get("lamps_draw") != LAMP_DRAW and not joint) or ("geometry_draws" in doc and "lamps_with_camera"
                                                                       not in stated)
            or set(used) != {str(k) for k in now} or any(not np.allclose(used[str(k)], v) for k, v in now.items()))


def measure(spec: dict, work: Path, leds: str, rotations: str, draws: int, previous: dict | None = None) -> dict:
    """One measurement (module docstring). ``previous``: its earlier result, whose fit (the
    parameters and the budget without the calibration component: same samples, same fit)
    is kept and whose calibration component is computed again (:func:`stale`)."""
    from glossrig.core.capture import read_truth
    from glossrig.core.fitting import calibration_uncertainty as cu
    from glossrig.core.fitting.fit import fit_samples, parameter_errors
    from glossrig.core.fitting.uncertainty import coverage
    from glossrig.core.models.ward import WardParams
    from glossrig.core.samples import read_samples

    s = spec["scale"]
    cal_dir = work / f"cal_round{spec['round']}"
    with _locked(work / f".cal_round{spec['round']}.lock"):      # shared with the other --part processes
        cam, lamps = calibrate(cal_dir, s, 500 + 11 * spec["round"], lamp_rotations="0", leds=leds)
    with _locked(work / f".reference_{_slug(s)}.lock"):
        ref = capture(work / f"reference_{_slug(s)}", f"lambert:{REFERENCE_ALBEDO}", s, 7 + int(1000 * s),
                      rotations, leds=leds)
    spp = spec.get("spp", DEFAULT_SPP)
    name = spec["id"] + ("" if spp == DEFAULT_SPP else f"_spp{spp}")
    cap = capture(work / "captures" / name, spec["material"], s, spec["seed"], rotations, leds=leds,
                  extra=() if spp == DEFAULT_SPP else ("--spp", str(spp)))
    sp = extract(cap, ref, cam, lamps, work / "samples" / f"{name}.parquet",
                 "--reference-albedo", f"{spec['albedo_stated']:.9g}")
    truth = read_truth(cap)["material"]["ward"]
    df = read_samples(sp)
    t0 = time.perf_counter()
    if previous is None:
        f = fit_samples(df, channels=["luminance"], led_aperture=0.0).fits["luminance"]
        assert f.uncertainty is not None            # fit_samples states the budget
        params, unc, t_fit = f.params, f.uncertainty, time.perf_counter() - t0
    else:
        params, unc, t_fit = (WardParams(**previous["params"]), previous["without_calibration"]["uncertainty"],
                              previous["fit_s"])
    t0 = time.perf_counter()
    cal = cu.load_inputs(cam, lamps, cap, sorted(df["rotation"].unique()))
    cal.angular_u = 0.0             # the twin's reference is exactly Lambertian (module docstring)
    comp = cu.calibration_component(df, {"luminance": params}, cal, n_draws=draws, seed=spec["seed"])
    t_cal = time.perf_counter() - t0
    with_cal = cu.add_calibration(unc, comp["luminance"])
    return {"spec": spec, "truth": truth, "params": params.as_dict(), "rows": len(df),
            "rel_err": parameter_errors(params, truth), "fit_s": t_fit, "calibration_s": t_cal,
            "fit_reused": previous is not None,
            "calibration_meta": {k: v for k, v in comp["_meta"].items() if k != "files"},
            "calibration_errors": calibration_errors(cal_dir, cap),
            "without_calibration": {"uncertainty": unc, "coverage": coverage(unc, truth)},
            "with_calibration": {"uncertainty": with_cal, "coverage": coverage(with_cal, truth)}}


def summarise(results: list[dict], key: str = "with_calibration") -> dict:
    """Per parameter: ``n``, ``covered`` (count), ``coverage``, ``median_half_width`` over
    ``rms_error`` (relative to the truth for albedos and alphas, radians for the rotation)."""
    out = {}
    for p in PARAMS:
        cov, hw, err = [], [], []
        for r in results:
            e, c = r[key]["uncertainty"][p], r[key]["coverage"][p]
            if c["covered"] is None or e["interval95"] is None:
                continue
            norm = 1.0 if p == "lobe_rotation" else abs(_canonical_truth(r["truth"])[p])
            cov.append(bool(c["covered"]))
            hw.append(e["coverage_factor"] * e["combined"] / norm)
            err.append(c["error"] / norm)
        n = len(cov)
        rms = math.sqrt(float(np.mean(np.square(err)))) if n else math.nan
        med = float(np.median(hw)) if n else math.nan
        out[p] = {"n": n, "covered": int(sum(cov)), "coverage": sum(cov) / n if n else math.nan,
                  "median_half_width": med, "rms_error": rms, "ratio": med / rms if rms > 0 else math.inf}
    return out


def _canonical_truth(truth: dict) -> dict:
    from glossrig.core.fitting.fit import canonical
    from glossrig.core.models.ward import WardParams

    t, _ = canonical(WardParams(**{k: float(truth[k]) for k in PARAMS}))
    return t.as_dict()


def sampling_band(n: int, p: float = 0.95, level: float = 0.95) -> tuple[float, float, float, float]:
    """How far the coverage of ``n`` independent 95 % intervals strays from 95 % by chance:
    the central ``level`` range ``[lo, hi]`` of covered / n for covered ~ Binomial(n, p)
    (exact quantiles), and the two one-sided tail probabilities of a count ``c`` are
    given by :func:`binomial_tails`. Returns ``(lo, hi, mean, sd)`` as shares of n."""
    from scipy.stats import binom

    a = (1 - level) / 2
    return (float(binom.ppf(a, n, p)) / n, float(binom.ppf(1 - a, n, p)) / n, p, math.sqrt(p * (1 - p) / n))


def binomial_tails(c: int, n: int, p: float = 0.95) -> tuple[float, float]:
    """P(covered <= c) and P(covered >= c) for covered ~ Binomial(n, p)."""
    from scipy.stats import binom

    return float(binom.cdf(c, n, p)), float(binom.sf(c - 1, n, p))


def _band_cell(c: int, n: int) -> str:
    lo, hi, _, _ = sampling_band(n)
    below, above = binomial_tails(c, n)
    inside = lo <= c / n <= hi
    return (f"{100 * lo:.1f}-{100 * hi:.1f} % | {'inside' if inside else 'OUTSIDE'} "
            f"(P(<= {c}) {below:.3g}, P(>= {c}) {above:.3g})")


def _coverage_table(results: list[dict], key: str) -> list[str]:
    s = summarise(results, key)
    lines = ["| parameter | n | 95 % covers | coverage | median half-width (rel.; rot: rad) | RMS error | "
             "half-width / RMS | binomial 95 % band of the coverage for a true 95 % | the coverage |",
             "|---|---|---|---|---|---|---|---|---|"]
    for p, v in s.items():
        lines.append(f"| {p} | {v['n']} | {v['covered']} | {100 * v['coverage']:.1f} % | "
                     f"{v['median_half_width']:.3g} | {v['rms_error']:.3g} | {v['ratio']:.2f} | "
                     f"{_band_cell(v['covered'], v['n']) if v['n'] else '- | -'} |")
    tot = sum(v["covered"] for v in s.values()), sum(v["n"] for v in s.values())
    band = ""
    if tot[1]:
        lo, hi, _, sd = sampling_band(tot[1])
        below, above = binomial_tails(tot[0], tot[1])
        band = (f"; binomial 95 % band for a true 95 % on {tot[1]} independent estimates {100 * lo:.1f}-"
                f"{100 * hi:.1f} % (sd {100 * sd:.2f} %), P(<= {tot[0]}) {below:.3g}, P(>= {tot[0]}) {above:.3g}")
    return lines + ["", f"all parameters: {tot[0]} of {tot[1]} ({100 * tot[0] / max(tot[1], 1):.1f} %){band}", ""]


def clustering(results: list[dict], key: str = "with_calibration") -> dict:
    """How far the estimates' misses cluster: the five parameters of one measurement share
    its fit and calibration draw, and a round's measurements share a calibration, so the
    260 estimates are not independent. The design effect (Kish 1965) from the
    measurements as clusters: the variance of the misses per measurement over the
    binomial variance at the observed miss rate; ``n_eff = n / deff`` and the binomial
    95 % band of the coverage for a true 95 % on ``n_eff`` estimates."""
    per = []
    for r in results:
        cov = [r[key]["coverage"][p]["covered"] for p in PARAMS]
        cov = [c for c in cov if c is not None]
        per.append((len(cov), sum(not c for c in cov)))
    n = sum(k for k, _ in per)
    misses = np.array([m for _, m in per], float)
    q = misses.sum() / n
    m = n / len(per)
    deff = float(misses.var(ddof=1) / (m * q * (1 - q))) if 0 < q < 1 and len(per) > 1 else math.nan
    n_eff = int(round(n / deff)) if deff and math.isfinite(deff) and deff > 0 else n
    lo, hi, _, _ = sampling_band(n_eff)
    return {"n": n, "measurements": len(per), "with_misses": int((misses > 0).sum()), "deff": deff,
            "n_eff": n_eff, "band": (lo, hi)}


def component_table(results: list[dict], key: str = "with_calibration") -> list[str]:
    """Per parameter, what the stated uncertainty is made of and how it compares with the
    actual errors: the RMS and the 95th percentile of ``z = error / combined u`` (1.0 and
    ~2 for an honest normal budget; the RMS of n independent such z lies within
    ``sqrt(chi2_n / n)``'s central 95 % - below it the budget over-covers, above it
    under-covers), and the median share of each component in the combined variance
    (u_c^2 / u^2, GUM JCGM 100 eq. 10), over the measurements; for the misses, the
    component with the largest share."""
    from scipy.stats import chi2

    lines = ["| parameter | n | RMS of error / u (its 95 % band for an honest u: sqrt(chi2_n / n)) | 95th pct of "
             "abs(error / u) | median variance share: noise / model / footprint / calibration | misses: |z|, "
             "largest component |",
             "|---|---|---|---|---|---|"]
    for p in PARAMS:
        z, shares, miss = [], [], []
        for r in results:
            e, c = r[key]["uncertainty"][p], r[key]["coverage"][p]
            if c["covered"] is None or not e["combined"]:
                continue
            z.append(c["error"] / e["combined"])
            comp = {k: (v or 0.0) ** 2 / e["combined"] ** 2 for k, v in e["components"].items()}
            shares.append([comp.get(k, 0.0) for k in ("noise", "model", "footprint", "calibration")])
            if not c["covered"]:
                miss.append(f"{r['spec']['id']} {abs(z[-1]):.1f}, {max(comp, key=comp.get)}")
        if not z:
            continue
        za = np.abs(z)
        med = np.median(np.array(shares), axis=0)
        n = len(z)
        band = f"{math.sqrt(chi2.ppf(0.025, n) / n):.2f}-{math.sqrt(chi2.ppf(0.975, n) / n):.2f}"
        lines.append(f"| {p} | {n} | {math.sqrt(float(np.mean(np.square(z)))):.2f} ({band}) | "
                     f"{float(np.percentile(za, 95)):.2f} | {' / '.join(f'{x:.2f}' for x in med)} | "
                     f"{'; '.join(miss) or '-'} |")
    return lines + [""]


def albedo_out_table(results: list[dict], key: str = "with_calibration") -> list[str]:
    """rho_d and rho_s against the reference-albedo draw: the fitted albedos scale exactly
    with the stated reference albedo (eq. 4.79 is linear in them and the samples are
    ratios to the reference), so each relative error is the study's known draw ``d =
    albedo_stated / 0.8 - 1`` plus the rest. Per parameter: the RMS of the relative
    errors, of ``d`` and of the rest, and the median stated combined u (relative), of
    which the albedo's stated share is ``u_albedo`` (the share is not split out of the
    Monte Carlo component, whose 24 draws estimate it to ~15 %, so the rest is not
    divided by a stated u here). Also the draws' RMS over ``u_albedo`` with its band."""
    from scipy.stats import chi2

    lines = ["| parameter | n | RMS rel. error | RMS of the albedo draws d | RMS of (rel. error - d) | median "
             "stated u (rel.), of which the albedo's |", "|---|---|---|---|---|---|"]
    d_all, u_alb = [], math.nan
    for p in ("rho_d", "rho_s"):
        err, ds, us = [], [], []
        for r in results:
            e, c = r[key]["uncertainty"][p], r[key]["coverage"][p]
            alb = r.get("calibration_meta", {}).get("stated", {}).get("albedo_u_rel")
            if c["covered"] is None or not e["combined"] or alb is None:
                continue
            u_alb = alb
            t = abs(_canonical_truth(r["truth"])[p])
            err.append(c["error"] / t)
            ds.append(r["spec"]["albedo_stated"] / REFERENCE_ALBEDO - 1)
            us.append(e["combined"] / t)
        if p == "rho_d":
            d_all = ds
        if err:
            rms = [math.sqrt(float(np.mean(np.square(x)))) for x in (err, ds, np.subtract(err, ds))]
            lines.append(f"| {p} | {len(err)} | " + " | ".join(f"{100 * x:.2f} %" for x in rms)
                         + f" | {100 * float(np.median(us)):.2f} %, {100 * u_alb:.0f} % |")
    if d_all:
        n = len(d_all)
        ratio = math.sqrt(float(np.mean(np.square(d_all)))) / u_alb
        lines += ["", f"the {n} drawn reference-albedo errors: RMS / stated {ratio:.2f} (95 % band for n = {n}: "
                  f"{math.sqrt(chi2.ppf(0.025, n) / n):.2f}-{math.sqrt(chi2.ppf(0.975, n) / n):.2f})"]
    return lines + [""]


def lamp_check(results: list[dict]) -> dict:
    """The rounds' lamp calibrations against the twin's truth: per round and holder axis the
    errors over the stated standard uncertainties (``z``), and over all rounds the RMS of
    ``z`` and the share of ``|z| <= 2`` (an honest statement: RMS near 1, ~95 %)."""
    rounds: dict = {}
    for r in results:
        e = r["calibration_errors"]
        if "lamp_error_xyz_mm" in e:
            rounds.setdefault(r["spec"]["round"], (r["spec"]["scale"], e))
    out, zs = {}, []
    for k, (scale, e) in sorted(rounds.items()):
        z = np.array([np.divide(e["lamp_error_xyz_mm"][i], e["lamp_std_mm"][i]) for i in sorted(e["lamp_error_xyz_mm"])])
        std = np.array([e["lamp_std_mm"][i] for i in sorted(e["lamp_std_mm"])])
        err = np.array([e["lamp_error_xyz_mm"][i] for i in sorted(e["lamp_error_xyz_mm"])])
        out[k] = {"scale": scale, "std_mm": std, "error_mm": err, "z": z}
        zs.append(z.ravel())
    allz = np.concatenate(zs) if zs else np.array([])
    return {"rounds": out, "z_rms": float(np.sqrt(np.mean(allz ** 2))) if allz.size else math.nan,
            "within_2": float(np.mean(np.abs(allz) <= 2)) if allz.size else math.nan, "n": int(allz.size)}


def report(results: list[dict], command: str) -> str:
    scales = sorted({r["spec"]["scale"] for r in results})
    lines = [f"Command: `{command}`", "", f"{len(results)} measurements, "
             f"{len({r['spec']['material'] for r in results})} materials, scales "
             f"{', '.join(f'{x:g}' for x in scales)}.", ""]
    for key, title in (("with_calibration", "budget with the calibration component"),
                       ("without_calibration", "budget without the calibration component (noise, model, footprint)")):
        lines += [f"**{title}**, all scales", ""] + _coverage_table(results, key)
        if len(scales) > 1:
            for sc in scales:
                sub = [r for r in results if r["spec"]["scale"] == sc]
                lines += [f"*{title}, scale {sc:g}* ({len(sub)} measurements)", ""] + _coverage_table(sub, key)
    cl = clustering(results)
    lines += [f"Clustering of the misses (with the calibration component): {cl['with_misses']} of "
              f"{cl['measurements']} measurements hold a miss; design effect {cl['deff']:.2f} (variance of the misses "
              f"per measurement over the binomial one), effective n {cl['n_eff']} of {cl['n']}: binomial 95 % band "
              f"of the coverage for a true 95 % {100 * cl['band'][0]:.1f}-{100 * cl['band'][1]:.1f} %", ""]
    lines += ["**What the budget (with the calibration component) is made of, against the actual errors**, all "
              "scales", ""] + component_table(results)
    for sc in scales if len(scales) > 1 else []:
        sub = [r for r in results if r["spec"]["scale"] == sc]
        lines += [f"*scale {sc:g}* ({len(sub)} measurements)", ""] + component_table(sub)
    lines += ["**rho_d and rho_s against the drawn reference-albedo error** (`albedo_out_table`), all scales", ""]
    lines += albedo_out_table(results)
    rounds: dict = {}
    for r in results:
        rounds.setdefault(r["spec"]["round"], r)
    lines += ["| round | scale | fx error | fy error | cx error (px) | cy error (px) | lamp errors (mm, 3-D) |",
              "|---|---|---|---|---|---|---|"]
    for k, r in sorted(rounds.items()):
        e = r["calibration_errors"]
        lines.append(f"| {k} | {r['spec']['scale']:g} | {e['fx_percent']:+.3f} % | {e['fy_percent']:+.3f} % | "
                     f"{e['cx_px']:+.2f} | {e['cy_px']:+.2f} | "
                     f"{min(e['lamp_error_mm'].values()):.2f}-{max(e['lamp_error_mm'].values()):.2f} |")
    lc = lamp_check(results)
    if lc["rounds"]:
        lines += ["", "Lamp positions (`calibrate lamps`' stated standard uncertainty per holder axis against the "
                  "actual error; ranges over the round's LEDs):", "",
                  "| round | scale | stated std x / y / z (mm) | actual error x / y / z (mm) | max abs(error / std) |",
                  "|---|---|---|---|---|"]
        for k, v in lc["rounds"].items():
            rng_ = " / ".join(f"{a:.2f}-{b:.2f}" for a, b in zip(v["std_mm"].min(0), v["std_mm"].max(0)))
            err = " / ".join(f"{a:+.2f}..{b:+.2f}" for a, b in zip(v["error_mm"].min(0), v["error_mm"].max(0)))
            lines.append(f"| {k} | {v['scale']:g} | {rng_} | {err} | {np.abs(v['z']).max():.2f} |")
        lines += ["", f"lamp coordinates: {lc['n']}, RMS of error / stated std {lc['z_rms']:.2f}, "
                  f"within 2 std: {100 * lc['within_2']:.1f} %"]
    return "\n".join(lines)


def design_comparison(results: list[dict], leds: str, rotations: str, scale: float = 0.1,
                      camera: Path | dict[int, Path] | None = None) -> tuple[str, dict]:
    """``glossrig design errors``' combined uncertainty (:func:`glossrig.core.design.error_budget.design_budget`,
    the study's LEDs and rotations, LED aperture 0 as the twin's, the reference's angular
    variation 0 as the study states it to the fit, and with ``camera`` the intrinsics drawn as
    the fit draws them) against the RMS of the actual errors of the study's measurements at
    ``scale``, for the Table 9.1 materials (the named ones of :data:`MATERIALS`): per material
    and parameter the ratio predicted / actual RMS, and per parameter over the materials
    pooled (root mean square of the predictions against that of the errors).

    ``camera``: one camera.json (its views) for every measurement, or a camera.json per
    round, ``{round: path}``. With one per round, each measurement's prediction is the one
    ``glossrig design errors --camera`` gives for the calibration that measurement was made
    with - what a user who designs with their own calibration gets - and the prediction set
    against the RMS of a material's errors over the rounds is the RMS of its measurements'
    predictions: the rounds' calibrations differ in quality (their views are drawn afresh),
    and the errors' RMS spans them all.

    How far a right prediction may lie from 1: the RMS of ``n`` errors drawn with standard
    deviation ``u`` is ``u sqrt(chi2_n / n)``, so predicted / RMS lies in
    ``[sqrt(n / chi2_n(0.975)), sqrt(n / chi2_n(0.025))]`` 95 % of the time ([0.60, 2.87]
    for n = 4): the report counts the ratios inside that band beside those inside [0.5, 2].
    A second table takes the reference-albedo draw out of rho_d and rho_s: the study knows
    each measurement's stated albedo, whose relative error scales both exactly, so the
    prediction without its albedo term is set against the RMS of the errors minus the draw."""
    from scipy.stats import chi2

    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.design.error_budget import design_budget
    from glossrig.core.fitting.calibration_uncertainty import CameraViews
    from glossrig.core.design.placement import parse_materials
    from glossrig.core.rig import default_rig_path, load_rig

    from glossrig.core.fitting.fit import canonical

    named = [m for m in MATERIALS if not m.startswith("ward:")]
    rig = load_rig(default_rig_path())
    # in canonical form (alpha_x >= alpha_y), as the fit reports and the errors are taken: the same
    # BRDF, so the same budget, its alpha_x and alpha_y named as the errors' (sample_0_6 has them swapped)
    materials = [(label, canonical(p)[0]) for label, p in parse_materials(",".join(named))]

    def predict(cam: Path | None) -> dict:
        return design_budget(rig, materials, rotations=[float(r) for r in rotations.split(",")],
                             led_ids=[int(i) for i in leds.split(",")], scale=scale, led_aperture=0.0,
                             angular_u=0.0,    # as the study states it for the fit: the twin's reference is Lambertian
                             camera_views=None if cam is None else CameraViews.from_camera_doc(load_camera(cam).meta))

    rounds = sorted({r["spec"]["round"] for r in results if r["spec"]["scale"] == scale})
    if isinstance(camera, dict):
        missing = [r for r in rounds if r not in camera]
        if missing:
            raise ValueError(f"no camera.json for rounds {missing}")
        by_round = {r: predict(camera[r]) for r in rounds}
    else:
        one = predict(camera)
        by_round = {r: one for r in rounds}
    lines: list[str] = []
    summary = {}
    for without_albedo in (False, True):
        params = ("rho_d", "rho_s") if without_albedo else PARAMS
        lines += ["", "**reference-albedo draw taken out (rho_d, rho_s)**" if without_albedo else
                  "**combined uncertainty against the actual errors**", "",
                  "| material | n | " + " | ".join(f"{p}: predicted / RMS" for p in params) + " |",
                  "|---|---|" + "---|" * len(params)]
        pooled: dict = {p: [[], []] for p in params}
        inside = {"2x": 0, "band": 0, "all": 0}
        bands: dict[int, tuple[float, float]] = {}
        for m in named:
            rs = [r for r in results if r["spec"]["material"] == m and r["spec"]["scale"] == scale]
            if not rs:
                continue
            n = len(rs)
            band = (math.sqrt(n / chi2.ppf(0.975, n)), math.sqrt(n / chi2.ppf(0.025, n)))
            bands[n] = band
            cells = []
            for p in params:
                t = _canonical_truth(rs[0]["truth"])
                norm = 1.0 if p == "lobe_rotation" else abs(t[p])
                err = np.array([r["with_calibration"]["coverage"][p]["error"] / norm for r in rs])
                us = [by_round[r["spec"]["round"]][m]["combined"][p] for r in rs]
                u = None if any(x is None for x in us) else math.sqrt(float(np.mean(np.square(us))))
                if without_albedo and u is not None:
                    # the fitted albedos scale with the stated reference albedo
                    err = err - np.array([r["spec"]["albedo_stated"] / REFERENCE_ALBEDO - 1 for r in rs])
                    alb = by_round[rs[0]["spec"]["round"]][m]["stated"]["albedo_u_rel"] * abs(t[p])
                    u = math.sqrt(max(u ** 2 - alb ** 2, 0.0))
                rms = math.sqrt(float(np.mean(np.square(err))))
                u = None if u is None else u / norm
                pooled[p][0].append(rms ** 2)
                pooled[p][1].append(np.nan if u is None else u ** 2)
                if u is None:
                    cells.append("-")
                    continue
                ratio = u / rms
                inside["all"] += 1
                inside["2x"] += 0.5 <= ratio <= 2
                inside["band"] += band[0] <= ratio <= band[1]
                cells.append(f"{u:.3g} / {rms:.3g} = {ratio:.2f}")
            lines.append(f"| {m} | {len(rs)} | " + " | ".join(cells) + " |")
        pool = {p: math.sqrt(float(np.nanmean(u2))) / math.sqrt(float(np.mean(e2)))
                for p, (e2, u2) in pooled.items() if e2}
        if not without_albedo:
            summary = pool
        lines += ["", "pooled over the materials (RMS prediction / RMS error): "
                  + ", ".join(f"{p} {v:.2f}" for p, v in pool.items()),
                  f"ratios within [0.5, 2]: {inside['2x']} of {inside['all']}; within the 95 % sampling band of an "
                  "RMS of n errors (" + "; ".join(f"n = {k}: [{b[0]:.2f}, {b[1]:.2f}]" for k, b in sorted(bands.items()))
                  + f"): {inside['band']} of {inside['all']}"]
    return "\n".join(lines), summary


def load_results(work: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted((work / "results").glob("*.json"))]


def main(argv=None) -> list[dict]:
    from glossrig.core.atomic import atomic_write_json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True, help="working folder (captures, calibrations, results/*.json)")
    ap.add_argument("--scales", default="0.1,0.1,0.1,0.1", help="one scale per round (default 0.1,0.1,0.1,0.1)")
    ap.add_argument("--leds", default="8,9,10,11")
    ap.add_argument("--rotations", default="0")
    ap.add_argument("--draws", type=int, default=24, help="calibration draws per measurement (default 24)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--limit", type=int, default=None, help="measure at most this many (in plan order)")
    ap.add_argument("--rounds", default=None,
                    help="measure only these rounds (comma-separated indices; to share the work between processes, "
                         "each round's calibration made by one of them)")
    ap.add_argument("--materials", default=None,
                    help="measure only these materials (comma-separated indices into MATERIALS; fewer materials "
                         "per round where a scale's measurements cost more)")
    ap.add_argument("--part", default=None, metavar="K/N",
                    help="measure only every N-th measurement from the K-th (0-based): N processes share the study")
    ap.add_argument("--reverse", action="store_true", help="measure in the reverse order")
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--design", action="store_true",
                    help="also compare glossrig design errors' combined uncertainty with the actual errors")
    a = ap.parse_args(argv)
    work = Path(a.work)
    for sub in ("results", "samples", "captures"):
        (work / sub).mkdir(parents=True, exist_ok=True)
    command = ("python -m validation.uncertainty_coverage --work " + str(work) + f" --scales {a.scales} "
               f"--leds {a.leds} --rotations={a.rotations} --draws {a.draws} --seed {a.seed}")
    if not a.report_only:
        specs = plan([float(s) for s in a.scales.split(",")], seed=a.seed)
        if a.rounds:
            keep = {int(r) for r in a.rounds.split(",")}
            specs = [s for s in specs if s["round"] in keep]
        if a.materials:
            mats = {int(m) for m in a.materials.split(",")}
            specs = [s for s in specs if int(s["id"].split("_m")[1]) in mats]
        # material by material across the rounds: an interrupted study is balanced over the
        # rounds, and every round's calibration is made at the start
        specs.sort(key=lambda s: (int(s["id"].split("_m")[1]), s["round"]))
        if a.part:
            k, n = (int(x) for x in a.part.split("/"))
            specs = specs[k::n]
        if a.reverse:
            specs = specs[::-1]
        specs = specs[:a.limit]
        for k, spec in enumerate(specs):
            out = work / "results" / f"{spec['id']}.json"
            previous = json.loads(out.read_text()) if out.exists() else None
            if previous is not None and {"spp": DEFAULT_SPP, **previous["spec"]} != spec:
                previous = None                 # another plan (seeds, albedo): measured anew
            elif previous is not None and not stale(previous, work):
                continue
            if not _claim(work, spec["id"] + ("-refresh" if previous else "")):
                continue
            t0 = time.perf_counter()
            res = measure(spec, work, a.leds, a.rotations, a.draws, previous)
            res["wall_s"] = time.perf_counter() - t0
            atomic_write_json(out, res)
            print(f"[{k + 1}/{len(specs)}] {spec['id']} {spec['material']} scale {spec['scale']:g}: "
                  f"{res['wall_s']:.0f} s", flush=True)
    results = load_results(work)
    print(report(results, command))
    if a.design:
        # each measurement's prediction from the calibration it was made with (design_comparison)
        cams = {r: work / f"cal_round{r}" / "camera.json" for r in range(len(a.scales.split(",")))}
        cam = {r: c for r, c in cams.items() if c.is_file()} or None
        text, _ = design_comparison(results, a.leds, a.rotations, camera=cam)
        print("\n`glossrig design errors` (combined) against the actual errors at scale 0.1:\n")
        print(text)
    return results


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
