"""Reproduction model against the thesis (issue 4; thesis ch. 6, 7.2.1, appendix Tables 9.1-9.2).

Regenerates, next to this script: ``cv.json`` (what ``glossrig model crossval`` writes),
``model.json`` (what ``glossrig model fit`` writes), ``results.json`` (every figure of
the report), ``etn.png``, ``cv_folds.png`` and ``README.md``::

    .venv/bin/python -m validation.reproduction.run

Inputs are the thesis's own tables in ``../shared/data/thesis``: the samples' fitted
Ward parameters (Table 9.1), nominal coverages (Table 6.2) and, for comparison only,
Table 6.4's effective coverages, Table 7.1's errors and Table 9.2's fold bases.
Besides Table 7.1 it measures why our figures differ from the thesis's: whether the
clip of eq. 6.5 can bite, the eq. 6.6 cost of the thesis's base 2 on our angles, the
cross-validation with base 2 frozen at the thesis's value, clip levels that do bite,
and the angle sampling.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from glossrig.core.reproduction import model as R  # noqa: E402
from glossrig.core.models.ward import WardParams  # noqa: E402

from validation.paths import thesis_dir  # noqa: E402

HERE = Path(__file__).resolve().parent
THESIS = thesis_dir()
T0 = time.monotonic()


def say(msg: str) -> None:
    print(f"[{time.monotonic() - T0:6.1f} s] {msg}", file=sys.stderr, flush=True)


def thesis_tables() -> dict:
    read = lambda name: pd.read_csv(THESIS / name, comment="#")  # noqa: E731
    ward = read("ward_params.csv").set_index("name")
    cov = read("coverages.csv").set_index("sample")
    cv = read("cross_validation.csv").set_index("method")
    b2 = read("cv_base2.csv").set_index("excluded_sample")
    cols = ["rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation"]
    return {"ward": ward, "cov": cov, "cv": cv, "cv_base2": b2,
            "base2": WardParams(*(float(ward.loc["base_2", c]) for c in cols)), "cols": cols}


def eq66_cost(samples: R.SampleSet, angles: R.AngleSet, base2: WardParams, clip=R.CLIP_LEVEL):
    """Eq. 6.6 cost of a given base 2 with every sample's best effective coverage."""
    fb1 = R.ward_values(samples.ward[samples.index(samples.base1_name)], angles)
    fb2 = R.ward_values(base2, angles)
    T = R.clip_values(np.array([R.ward_values(p, angles) for p in samples.ward]), clip)
    ce = R.best_mix(T, fb1, fb2, clip)
    mix = R.clip_values(fb1[None] + ce[:, None] * (fb2 - fb1)[None], clip)
    return float(np.sum((mix - T) ** 2) / len(samples)), ce


def loo_fixed_base2(samples: R.SampleSet, angles: R.AngleSet, base2: WardParams) -> list[dict]:
    """Leave-one-out as in 7.2.1 but with base 2 frozen (only the effective
    coverages and the ETN are refitted per fold): isolates the effect of base 2."""
    out = []
    fb1 = R.ward_values(samples.ward[samples.index(samples.base1_name)], angles)
    fb2 = R.ward_values(base2, angles)
    for name in samples.interior():
        train = samples.without([name])
        T = R.clip_values(np.array([R.ward_values(p, angles) for p in train.ward]), R.CLIP_LEVEL)
        etn = R.fit_etn(R.best_mix(T, fb1, fb2, R.CLIP_LEVEL), train.nominal_b2)
        i = samples.index(name)
        t = R.clip_values(R.ward_values(samples.ward[i], angles), R.CLIP_LEVEL)
        pred = float(etn(R.best_mix(t[None], fb1, fb2, R.CLIP_LEVEL)[0]))
        out.append({"left_out": name, "nominal_b2": samples.nominal_b2[i], "predicted_nominal_b2": pred,
                    "error": abs(pred - samples.nominal_b2[i])})
    return out


def stats(errors) -> dict:
    e = np.asarray(errors, dtype=float)
    return {"error_mean": float(e.mean()), "error_std": float(e.std()), "error_std_ddof1": float(e.std(ddof=1))}


def plots(model: R.ReproductionModel, cv: dict, th: dict) -> None:
    fig, ax = plt.subplots(figsize=(5.2, 4.2))
    x = np.linspace(0, 1, 201)
    ax.plot(x, model.etn(x), "C0-", label="ours: ETN fitted (eq. 6.7-6.8)")
    tr = model.training
    ax.plot([t["effective_b2"] for t in tr], [t["nominal_b2"] for t in tr], "C0o", label="ours: samples")
    cov = th["cov"].dropna(subset=["effective_b2"])
    ax.plot(cov["effective_b2"], cov["nominal_b2"], "C3s", mfc="none", label="thesis Table 6.4")
    ax.set_xlabel("effective coverage of base 2")
    ax.set_ylabel("nominal coverage of base 2")
    ax.set_title("Effective-to-nominal (cf. thesis fig. 7.3a)")
    ax.legend(loc="upper left", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(HERE / "etn.png", dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(5.2, 4.2))
    for m, style in zip(cv["methods"][:2], ("C0o", "C1^")):
        f = m["folds"]
        ax.plot([g["nominal_b2"] for g in f], [g["predicted_nominal_b2"] for g in f], style,
                label=f"method {m['method']} ({'all' if not m['excluded'] else 'all but ' + ', '.join(m['excluded'])})")
        for g in f:
            if g["error"] > 0.2:
                ax.annotate(g["left_out"], (g["nominal_b2"], g["predicted_nominal_b2"]), fontsize=8,
                            xytext=(4, -10), textcoords="offset points")
    ax.plot([0, 1], [0, 1], "k:", lw=1)
    ax.set_xlabel("true nominal coverage (left out)")
    ax.set_ylabel("predicted nominal coverage")
    ax.set_title("Leave-one-out predictions (thesis 7.2.1)")
    ax.legend(loc="upper left", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(HERE / "cv_folds.png", dpi=110)
    plt.close(fig)


def fmt(v, nd=3):
    return "-" if v is None or (isinstance(v, float) and np.isnan(v)) else f"{v:.{nd}f}"


def main() -> int:
    th = thesis_tables()
    ward_csv, cov_csv = THESIS / "ward_params.csv", THESIS / "coverages.csv"
    samples = R.load_samples(ward_csv, cov_csv)
    angles = R.rig_angles()
    say(f"{len(samples)} samples, {len(angles)} angle sets ({angles.info['rows_total']} before subsampling)")

    # --- Table 7.1 (the command's computation, same defaults)
    cv = R.cross_validate(samples, angles, progress=say)
    cv["inputs"] = {"ward": "../shared/data/thesis/ward_params.csv", "coverages": "../shared/data/thesis/coverages.csv"}
    (HERE / "cv.json").write_text(json.dumps(cv, indent=1) + "\n")
    outliers = cv["outliers"]

    # --- the production model (method 1's sample set), as `glossrig model fit` writes it
    say("model on all samples but the outliers")
    model = R.fit_model(samples.without(outliers), angles)
    mdoc = model.to_json()
    mdoc["fit"].update(excluded=outliers, exclusion="automatic", outlier_criterion=R.OUTLIER_CRITERION,
                       inputs=cv["inputs"])
    (HERE / "model.json").write_text(R.dumps_model(mdoc))

    # --- diagnostics
    peaks = {n: float(R.ward_values(p, angles).max()) for n, p in zip(samples.names, samples.ward)}
    m1 = samples.without(outliers)
    cost_ours, ce_ours = eq66_cost(m1, angles, model.base2)
    cost_thesis, ce_thesis_b2 = eq66_cost(m1, angles, th["base2"])
    say("eq. 6.6 started from the thesis's base 2 and Table 6.4's effective coverages")
    fb1 = R.ward_values(m1.ward[m1.index(m1.base1_name)], angles)
    T = R.clip_values(np.array([R.ward_values(p, angles) for p in m1.ward]), R.CLIP_LEVEL)
    ce_start = np.array([float(th["cov"].loc[n, "effective_b2"]) for n in m1.names])
    from_thesis = R.fit_bases(T, fb1, angles, [th["base2"]], ce_start, R.CLIP_LEVEL)
    say("cross-validation with base 2 frozen at the thesis's value")
    fixed = loo_fixed_base2(m1, angles, th["base2"])
    say("clip levels that bite")
    clip_rows = []
    for level in (0.2, 0.1, 0.05):
        folds = R.leave_one_out(m1, angles, level, progress=say)
        frac = float(np.mean([np.mean(R.ward_values(p, angles) > level) for p in m1.ward]))
        clip_rows.append({"clip_level": level, "fraction_clipped": frac, **R.error_stats(folds)})
    say("angle sampling")
    sampling_rows = []
    for scale, mx in ((0.05, 3000), (0.1, 24000)):
        a = R.rig_angles(scale=scale, max_samples=mx)
        folds = R.leave_one_out(m1, a, progress=say)
        sampling_rows.append({"scale": scale, "max_samples": mx, "rows_used": len(a), **R.error_stats(folds)})
    say("gamut of the thesis's other materials")
    others = ["sanded_original", "sanded_reproduced", "brushed_original", "brushed_reproduced",
              "transparency_sheet", "white_paper", "polyethylene"]
    gamut = []
    for name in others:
        p = WardParams(*(float(th["ward"].loc[name, c]) for c in th["cols"]))
        pr = model.predict(p)
        gamut.append({"material": name, **pr.to_json()})

    results = {
        "angles": dict(angles.info),
        "table_7_1": [{"method": m["method"], "excluded": m["excluded"], "preprocessing": m["preprocessing"],
                       "ours_error_mean": m["error_mean"], "ours_error_std": m["error_std"],
                       "ours_error_std_ddof1": m["error_std_ddof1"],
                       "thesis_error_mean": float(th["cv"].loc[m["method"], "error_mean"]),
                       "thesis_error_std": float(th["cv"].loc[m["method"], "error_std"])} for m in cv["methods"]],
        "outliers": outliers,
        "outlier_rounds": cv["outlier_detection"]["rounds"],
        "table_6_4": [{"sample": t["sample"], "nominal_b2": t["nominal_b2"],
                       "thesis_effective_b2": (None if pd.isna(th["cov"].loc[t["sample"], "effective_b2"])
                                               else float(th["cov"].loc[t["sample"], "effective_b2"])),
                       "ours_effective_b2": t["effective_b2"], "ours_etn_nominal_b2": t["etn_nominal_b2"],
                       "effective_b2_with_thesis_base2": float(c)}
                      for t, c in zip(model.training, ce_thesis_b2)],
        "base2": {"ours": model.base2.as_dict(), "thesis": th["base2"].as_dict()},
        "etn": model.etn.to_json(),
        "table_9_2": [{"excluded": f["left_out"], "ours": f["base2"],
                       "thesis": {c: float(th["cv_base2"].loc[f["left_out"], c]) for c in th["cols"]}}
                      for f in cv["methods"][0]["folds"] if f["left_out"] in th["cv_base2"].index],
        "diagnostics": {
            "max_ward_value_at_rig_angles": peaks,
            "eq66_cost_ours": cost_ours, "eq66_cost_thesis_base2": cost_thesis,
            "eq66_start_costs_ours": model.fit_info["start_costs"],
            "eq66_from_thesis_start": {"cost": from_thesis.cost, "base2": from_thesis.base2.as_dict(),
                                       "effective_b2": dict(zip(m1.names, from_thesis.effective_b2.tolist()))},
            "loo_thesis_base2_frozen": {"folds": fixed, **stats([f["error"] for f in fixed])},
            "clip_levels": clip_rows, "angle_sampling": sampling_rows,
        },
        "gamut": gamut, "gamut_threshold": model.gamut_threshold,
        "seconds": round(time.monotonic() - T0, 1),
    }
    (HERE / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    plots(model, cv, th)
    (HERE / "README.md").write_text(report(results, cv, model))
    say("done")
    return 0


def report(r: dict, cv: dict, model: R.ReproductionModel) -> str:
    t71 = r["table_7_1"]
    d = r["diagnostics"]
    best = min(t71, key=lambda m: (m["ours_error_mean"], m["method"]))
    peak = max(d["max_ward_value_at_rig_angles"].values())
    L = []
    a = L.append
    a("# Reproduction model against the thesis (issue 4)\n")
    a("Thesis chapter 6 (eq. 6.1-6.8, Tables 6.3-6.5) and its validation in section 7.2.1, run on the "
      "thesis's own measured Ward parameters (`ward_params.csv`, Table 9.1) and nominal coverages "
      "(`coverages.csv`, Table 6.2). Code: `core/reproduction/model.py`; command: `glossrig model`. "
      "All figures below are regenerated by\n")
    a("```\n.venv/bin/python -m validation.reproduction.run\n```\n")
    a(f"(about {r['seconds']:.0f} s here). `cv.json` in this folder is what the first command writes "
      "(the command adds its run time), `model.json` what the second writes:\n")
    a("```\nglossrig model crossval --ward ../shared/data/thesis/ward_params.csv "
      "--coverages ../shared/data/thesis/coverages.csv --out cv.json\n"
      "glossrig model fit --ward ../shared/data/thesis/ward_params.csv "
      "--coverages ../shared/data/thesis/coverages.csv --out model.json\n"
      "glossrig model predict --model model.json --ward rho_d=0.0523,rho_s=0.0153,alpha_x=0.0755,"
      "alpha_y=0.0652,lobe_rotation=2.25\n```\n")
    ai = r["angles"]
    a(f"BRDF values are sampled from the Ward models at the rig's measurement angles: the "
      f"{len(ai['leds'])} middle-row LEDs, sample rotations {', '.join(f'{x:g}' for x in ai['rotations_deg'])} deg, "
      f"one sample per camera pixel on the cylinder (`core.cylinder.nominal_samples`, image scale {ai['scale']}), "
      f"{ai['rows_total']} angle sets, every {ai['stride']}th kept ({ai['rows_used']}).\n")

    a("## Table 7.1: leave-one-out cross-validation\n")
    a("Error = |predicted - true| nominal coverage of the left-out sample; 0/6 and 6/6 are never left out. "
      "Std is the population one (the thesis does not say which; the sample std, ddof = 1, is in brackets).\n")
    a("| method | used samples | preprocessing | ours: error mean | ours: error std | thesis: error mean | thesis: error std |")
    a("|---|---|---|---|---|---|---|")
    for m in t71:
        used = "all" if not m["excluded"] else "all but " + ", ".join(m["excluded"])
        a(f"| {m['method']} | {used} | {m['preprocessing']} | {fmt(m['ours_error_mean'])} | "
          f"{fmt(m['ours_error_std'])} ({fmt(m['ours_error_std_ddof1'])}) | {fmt(m['thesis_error_mean'])} | "
          f"{fmt(m['thesis_error_std'])} |")
    a("")
    e = {m["method"]: m["ours_error_mean"] for m in t71}
    a(f"* **Method 1 vs 2.** As in the thesis, leaving out the fabrication outlier helps: method 1's mean error "
      f"is {fmt(e[1])} against method 2's {fmt(e[2])}, and method 2's spread is dominated by the outlier's own "
      f"fold (see `cv_folds.png`). Best method here: {best['method']}"
      f"{' (tied with 3, below)' if abs(e[1] - e[3]) < 1e-9 and best['method'] in (1, 3) else ''}.")
    a(f"* **Method 3 equals method 1, measured.** Eq. 6.5 clips BRDF values at 1.0. In the thesis it acts on "
      f"the *measured* white-normalised values before each sample's own Ward fit (6.2: \"before the BRDF "
      f"fitting\"), so Table 9.1's parameters already come from clipped data, and the thesis's method 3 refitted "
      f"the samples from unclipped measurements, which are not published. With only Table 9.1 available we can "
      f"clip only the Ward-sampled values, and at the rig's angles no fabricated sample's Ward BRDF exceeds "
      f"{peak:.3f} (per sample in `results.json`), so the clip never bites and methods 1 and 3 are identical by "
      f"construction. The thesis's 0.142 for method 3 cannot be reproduced from its published parameters.")
    se1 = t71[0]["ours_error_std_ddof1"] / np.sqrt(len(cv["methods"][0]["folds"]))
    gap = e[1] - t71[0]["thesis_error_mean"]
    a(f"* **Our method 1 error ({fmt(e[1])}) is above the thesis's ({fmt(t71[0]['thesis_error_mean'])})** by "
      f"{gap:.3f}, {gap / se1:.1f} standard errors of our six-fold mean ({se1:.3f}). Our base 2 differs from the "
      "thesis's (measured below): on our angle set eq. 6.6 has one minimum, rougher than the thesis's base 2.\n")

    a("## Fabrication outliers (the thesis dropped 4/6 by hand)\n")
    a(f"Criterion (`core.reproduction.OUTLIER_CRITERION`): {R.OUTLIER_CRITERION}\n")
    for i, rd in enumerate(r["outlier_rounds"], 1):
        viol = "; ".join(f"{v['lower_nominal']} above {v['higher_nominal']} by {v['effective_drop']:.3f}"
                         for v in rd["violations"]) or "none"
        a(f"* Round {i} ({len(rd['samples'])} samples): order violations: {viol}. "
          f"Flagged: {', '.join(rd['flagged']) or 'none'}.")
    m2 = next(m for m in cv["methods"] if m["method"] == 2)
    worst = max(m2["folds"], key=lambda f: f["error"])
    a(f"\n**Flagged: {', '.join(r['outliers']) or 'none'}** - the sample the thesis removed. In the joint fit its "
      f"effective coverage sits between 5/6's and 6/6's, matching the thesis's \"rather close to 6/6\" (7.2.7). "
      f"Independent evidence from method 2's leave-one-out: the largest error is {worst['left_out']}'s "
      f"({worst['error']:.3f}; next largest "
      f"{sorted(f['error'] for f in m2['folds'])[-2]:.3f}).\n")

    a("## Table 6.4: effective and nominal coverages (method 1 samples, full fit)\n")
    a("| sample | nominal b2 | thesis effective b2 | ours effective b2 | ours ETN(effective) | effective b2 with the thesis's base 2 |")
    a("|---|---|---|---|---|---|")
    for t in r["table_6_4"]:
        a(f"| {t['sample']} | {fmt(t['nominal_b2'], 2)} | {fmt(t['thesis_effective_b2'], 2)} | "
          f"{fmt(t['ours_effective_b2'])} | {fmt(t['ours_etn_nominal_b2'])} | {fmt(t['effective_b2_with_thesis_base2'])} |")
    a("")
    g = model.etn.gamma
    dev = [abs(t["effective_b2_with_thesis_base2"] - t["thesis_effective_b2"]) for t in r["table_6_4"]
           if t["thesis_effective_b2"] is not None]
    a(f"Our effective coverages increase monotonically with nominal coverage, as the thesis's do. ETN (eq. 6.7, "
      f"offset form): gamma = ({g[0]:.4g}, {g[1]:.4g}, {g[2]:.4g}, {g[3]:.4g}); see `etn.png`. The last column "
      f"puts the thesis's own base 2 into our matching (eq. 6.2-6.3): it gives back Table 6.4's effective "
      f"coverages to within {max(dev):.2f} (0/6, 5/6 and 6/6 exactly) - the same ordering and spacing, a little "
      "lower - so the matching agrees with the thesis; what differs is base 2.\n")

    a("## Base 2 (Table 9.1) and its stability over the folds (Table 9.2)\n")
    cols = ["rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation"]
    a("| | " + " | ".join(cols) + " |")
    a("|---|" + "---|" * len(cols))
    a("| thesis base 2 | " + " | ".join(fmt(r["base2"]["thesis"][c], 4) for c in cols) + " |")
    a("| ours base 2 | " + " | ".join(fmt(r["base2"]["ours"][c], 4) for c in cols) + " |")
    for row in r["table_9_2"]:
        a(f"| fold without {row['excluded']}: thesis | " + " | ".join(fmt(row["thesis"][c], 3) for c in cols) + " |")
        a(f"| fold without {row['excluded']}: ours | " + " | ".join(fmt(row["ours"][c], 3) for c in cols) + " |")
    ax_ours = [row["ours"]["alpha_x"] for row in r["table_9_2"]]
    ax_th = [row["thesis"]["alpha_x"] for row in r["table_9_2"]]
    a("")
    a(f"Both bases stay nearly constant over the folds (alpha_x {min(ax_ours):.3f}-{max(ax_ours):.3f} ours, "
      f"{min(ax_th):.3f}-{max(ax_th):.3f} thesis), the thesis's test of generalisation. But ours is rougher "
      f"(alpha_x about 0.26 against 0.10, rho_s 0.026 against 0.010), so every sample's effective coverage is "
      "lower. Measured:\n")
    ft = d["eq66_from_thesis_start"]
    sc = ", ".join(f"{c:.6f}" for c in d["eq66_start_costs_ours"])
    a(f"* Eq. 6.6 cost on our angles, each sample at its best effective coverage: our base 2 "
      f"{d['eq66_cost_ours']:.4f}, the thesis's base 2 {d['eq66_cost_thesis_base2']:.4f} "
      f"({d['eq66_cost_thesis_base2'] / d['eq66_cost_ours']:.2f}x). Our three starts end at costs {sc}; started "
      f"from the thesis's base 2 and Table 6.4's effective coverages (lobe rotation at Table 6.3's 2.6), the fit "
      f"ends at {ft['cost']:.6f} with alpha_x = {ft['base2']['alpha_x']:.3f}. So the thesis's base 2 is not a "
      "minimum of eq. 6.6 at the rig's nominal angles. Plausible causes we cannot test without the thesis's "
      "data: it sampled each sample at its own measured pixels (eq. 6.2 uses theta_m, the material's angles), "
      "not one shared nominal set; its optimiser started at random points (Table 6.3) and may have stopped early.")
    fz = d["loo_thesis_base2_frozen"]
    a(f"* Leave-one-out with base 2 frozen at the thesis's value (only effective coverages and ETN refitted per "
      f"fold): error {fz['error_mean']:.3f} +- {fz['error_std']:.3f}, against {e[1]:.3f} with our base refitted "
      f"per fold and the thesis's 0.049. This is optimistic (the thesis's base 2 was fitted with every left-out "
      f"sample in it) and its worst fold is 5/6 (error {max(f['error'] for f in fz['folds']):.3f}: with that base "
      "5/6 sits at effective coverage 1, the end of the ETN). So base 2 explains part of the gap to the thesis's "
      "0.049, not all of it.\n")

    a("## Sensitivity\n")
    a("Clip levels that do bite (eq. 6.5 at a lower level removes the top of the peaks), method 1's samples:\n")
    a("| clip level | fraction of values clipped | error mean | error std |")
    a("|---|---|---|---|")
    a(f"| 1.0 (thesis) | 0 | {fmt(e[1])} | {fmt(t71[0]['ours_error_std'])} |")
    for c in d["clip_levels"]:
        a(f"| {c['clip_level']} | {c['fraction_clipped']:.4f} | {fmt(c['error_mean'])} | {fmt(c['error_std'])} |")
    a("\nAngle sampling (method 1):\n")
    a("| image scale | max angle sets | used | error mean | error std |")
    a("|---|---|---|---|---|")
    a(f"| {ai_scale(r)} | {r['angles']['max_samples']} | {r['angles']['rows_used']} (default) | {fmt(e[1], 4)} | "
      f"{fmt(t71[0]['ours_error_std'], 4)} |")
    for s in d["angle_sampling"]:
        a(f"| {s['scale']} | {s['max_samples']} | {s['rows_used']} | {fmt(s['error_mean'], 4)} | "
          f"{fmt(s['error_std'], 4)} |")
    a("\nClipping the Ward-sampled peaks harder does not help on these parameters (the peak is what separates "
      "the samples); the angle subsampling changes the error in the fourth decimal.\n")

    a("## Prediction and gamut (thesis 7.2.3)\n")
    a(f"`glossrig model predict` reports the nominal coverage and how far the best mix is from the target: the "
      f"relative L2 distance over the angle set, divided by the largest such distance among the training samples "
      f"({r['gamut_threshold']:.3f}). Ratio <= 1: in the gamut; <= {R.GAMUT_NEAR:g}: near; beyond: out (a warning "
      "on stderr). The thesis's other materials (Table 9.1):\n")
    a("| material | nominal b2 | effective b2 | relative distance | gamut ratio | verdict |")
    a("|---|---|---|---|---|---|")
    for gm in r["gamut"]:
        a(f"| {gm['material']} | {fmt(gm['nominal_b2'])} | {fmt(gm['effective_b2'])} | "
          f"{fmt(gm['relative_distance'])} | {gm['gamut_ratio']:.2f} | {gm['gamut']} |")
    a("\nThe thesis (7.2.3, 7.2.8) calls the sanded sheet \"properly reproduced\" and \"close to the gamut\", and "
      "the brushed varnish \"outside the gamut\"; the verdicts above agree. The transparency sheet, white paper "
      "and polyethylene are far out too. Two rows deserve a word: the thesis's *reproduced* brushed sample is out "
      "as well (its published fit has alpha of 0.009, far narrower than any training sample's 0.029 or more), and "
      "the reproduced sanded sample, published with sample 7/10's parameters but a lobe rotation of 2.19 instead "
      "of 2.56 rad, is only \"near\" where 7/10 itself is \"in\": neither the thesis's model nor ours has the "
      "scratch direction as a degree of freedom, so a rotated lobe counts as distance.\n")

    a("## What falls short\n")
    a("* Method 3 of Table 7.1 cannot be reproduced from the published parameters (above); ours equals method 1.")
    a("* Our base 2, and with it the absolute effective coverages and the method-1 error, differ from the "
      "thesis's; the cause is not identifiable without the thesis's per-sample measured angles and values.")
    a("* The angle set is the rig's nominal geometry, shared by all samples, not each sample's measured pixels.")
    a("* The gamut thresholds (training-sample residual; near = 2x) are our choice; the thesis gives none.")
    a("* The scratch direction is not a model parameter (nor in the thesis), so a target whose lobe is rotated "
      "against the samples' reads as further from the gamut than a rotated fabrication would be.")
    a("* Outlier detection by order can only flag a sample that is out of order with at least two others; a "
      "sample that swaps with a single neighbour is reported as a violation but not flagged (either could be "
      "wrong).")
    return "\n".join(L) + "\n"


def ai_scale(r: dict):
    return r["angles"]["scale"]


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
