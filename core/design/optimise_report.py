"""The report of ``glossrig design optimise`` (thesis 9.1): the optimised LED design
(:func:`glossrig.core.design.placement.optimise`) compared with the thesis rig at a final
image scale, coverage (every convention of the headline table) and expected Fisher errors
of both, written as ``design.json``, ``design.md`` and the plots of
:mod:`glossrig.core.design.plots`; and the header of the optimised rig file.

:func:`compare_designs` computes, :func:`write_design_report` writes into a folder the
caller has checked (:mod:`glossrig.cli.outputs`).
"""
from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from glossrig.core.design import coverage as cov
from glossrig.core.design import placement as D
from glossrig.core.design.coverage_report import jsonable
from glossrig.core.design.fisher import PARAMS
from glossrig.core.design.plots import plot_errors, plot_layout, plot_prefixes

DESIGN_NAMES = ("thesis_middle", "thesis_16", "optimised")


@dataclass(frozen=True)
class ScoreSettings:
    """The settings of the sweep that the report states: weights of the score, the image
    scale of the sweep (also that of the expected errors) and the noise model."""

    lam: float = 1.0
    iso_weight: float = 1.0
    scale: float = 0.25
    noise: str = "hdr"


def optimised_rig_header(n_leds: int, n_rotations: int, materials: str, template_path) -> str:
    """The comment block opening the rig file that ``glossrig design optimise`` writes."""
    return (f"# Optimised rig (glossrig design optimise, thesis 9.1): {n_leds} LEDs and "
            f"{n_rotations} sample rotations chosen for anisotropic and isotropic BRDF-space coverage (thesis 7.1.3) and\n"
            f"# the expected extended-Ward parameter error (Fisher information) of {materials}.\n"
            f"# Everything but the LED table, sample rotations, name and description is copied from {template_path}.\n"
            f"# LEDs mount on printed vertical posts with sliding carriages (heights -40..120 mm), see\n"
            f"# glossrig.core.design.placement. Regenerate: see validation/design/README.md.\n#\n")


def compare_designs(ref_rig, new_rig, res, materials, settings: ScoreSettings, final_scale: float,
                    command: str | None = None, log: Callable[[str], None] | None = None):
    """Coverage at ``final_scale`` and expected errors of the thesis rig (all LEDs, and
    its middle row when it has one) and the optimised rig: the ``design.json`` document
    and the coverage data of each design (for the plots)."""
    say = log or (lambda msg: None)
    fs = final_scale
    out = {"design": res.to_json(), "command": command,
           "materials": {lb: p.as_dict() for lb, p in materials}, "noise": settings.noise, "final_scale": fs,
           "rigs": {}}
    ref_sets = {"thesis_16": (ref_rig, ref_rig.led_ids(), list(ref_rig.sample_rotations))}
    mid = [led.id for led in ref_rig.leds if led.row == "middle"]
    if mid and len(mid) < len(ref_rig.led_ids()):
        ref_sets["thesis_middle"] = (ref_rig, mid, list(ref_rig.sample_rotations))
    ref_sets["optimised"] = (new_rig, new_rig.led_ids(), list(new_rig.sample_rotations))
    datas = {}
    for key, (rg, leds, rots) in ref_sets.items():
        say(f"final comparison: {key} at scale {fs:g}")
        data = cov.collect(rg, led_ids=leds, rotations=rots, scale=fs, filters=("lit", "between"))
        datas[key] = data
        convs = {"lit": cov.Convention("lit"), "lit+half_turn": cov.Convention("lit", pi_fold=True),
                 "between": cov.Convention("between")}
        c = {name: cov.coverage(data, cv) for name, cv in convs.items()}
        errs = D.design_errors(rg, materials, rotations=rots, led_ids=leds, scale=settings.scale,
                               noise=settings.noise)
        out["rigs"][key] = {"leds": leds, "rotations_deg": rots,
                            "coverage_pct": {k: {"isotropic": 100 * v["isotropic"], "anisotropic": 100 * v["anisotropic"]}
                                             for k, v in c.items()},
                            "expected_errors": {lb: e.to_json() for lb, e in errs.items()}}
    r_ref, r_new = out["rigs"]["thesis_16"], out["rigs"]["optimised"]
    out["ratio_anisotropic_lit"] = r_new["coverage_pct"]["lit"]["anisotropic"] / r_ref["coverage_pct"]["lit"]["anisotropic"]
    out["error_ratios"] = {lb: r_new["expected_errors"][lb]["geometric_mean_relative"]
                           / r_ref["expected_errors"][lb]["geometric_mean_relative"] for lb, _ in materials}
    return out, datas


def write_design_report(ref_rig, new_rig, res, materials, folder: Path, settings: ScoreSettings,
                        final_scale: float, command: str | None = None,
                        log: Callable[[str], None] | None = None) -> dict:
    """Final comparison at ``final_scale`` (:func:`compare_designs`); write design.json,
    design.md and the plots into ``folder``; return the JSON document."""
    say = log or (lambda msg: None)
    report = Path(folder)
    out, datas = compare_designs(ref_rig, new_rig, res, materials, settings, final_scale, command=command, log=log)
    (report / "design.json").write_text(json.dumps(out, indent=2, default=jsonable) + "\n")
    (report / "design.md").write_text(design_markdown(out, materials, ref_rig, new_rig, settings))
    plot_prefixes(res, report / "leds_vs_score.png")
    base = cov.Convention()
    cov.plot_rotation_coverage({k: (d, base, None) for k, d in datas.items()}, report / "aniso_by_rotation.png",
                               title=f"Anisotropic coverage by sample rotation (scale {final_scale:g})")
    cov.plot_theta_coverage(datas["optimised"], report / "theta_per_led.png", "lit",
                            title="optimised: occupied theta bins per LED (lit pixels)")
    plot_layout(ref_rig, new_rig, report / "layout.png")
    cov.plot_per_led({k: cov.per_led(d, base) for k, d in datas.items() if k != "thesis_middle"},
                     {}, report / "coverage_per_led.png")
    plot_errors(out, materials, report / "expected_errors.png")
    say(f"optimised vs thesis (16 LEDs): anisotropic coverage x{out['ratio_anisotropic_lit']:.2f}, error ratios "
        + ", ".join(f"{k} {v:.2f}" for k, v in out["error_ratios"].items()))
    return out


def design_markdown(out: dict, materials, ref_rig, new_rig, settings: ScoreSettings) -> str:
    """``design.md``: score, coverage and error tables of the designs, the LED table and
    the greedy prefixes (``out``: the document of :func:`compare_designs`)."""
    d = out["design"]
    rigs = out["rigs"]
    keys = [k for k in DESIGN_NAMES if k in rigs]
    names = {"thesis_middle": "thesis, 8 middle LEDs (as measured)", "thesis_16": "thesis, all 16 LEDs",
             "optimised": f"optimised, {len(new_rig.leds)} LEDs"}
    L = ["# Optimised LED design (thesis 9.1)", ""]
    L.append(f"Command: `{out.get('command') or 'glossrig design optimise ...'}` (sweep on {d['runner']}; "
             f"{d['n_candidates']} candidate mounts, {d['n_feasible']} within the mounting limits; sweep "
             f"{d['timings_s']['sweep']:.0f} s, selection {d['timings_s']['selection']:.0f} s).")
    L.append("")
    L.append(f"Score (glossrig.core.design.placement): ln(C/C_thesis) + {settings.iso_weight:g} * ln(C_iso/C_iso,thesis) - {settings.lam:g} "
             f"* mean ln(E/E_thesis), C the anisotropic and C_iso the isotropic coverage, and E the geometric mean of the relative standard errors of each target material "
             f"({', '.join(lb for lb, _ in materials)}), both at image scale {settings.scale:g}; noise model {settings.noise!r}. "
             f"Optimised score {d['score']:+.3f} (thesis 0).")
    L += ["", f"## Coverage at image scale {out['final_scale']:g} (camera 500 mm)", "",
          "| design | rotations | iso lit % | aniso lit % | aniso lit, half-turn fold % | iso between % | aniso between % |",
          "|---|---|---|---|---|---|---|"]
    for k in keys:
        c = rigs[k]["coverage_pct"]
        L.append(f"| {names[k]} | {rigs[k]['rotations_deg']} | {c['lit']['isotropic']:.3f} | {c['lit']['anisotropic']:.4f} | "
                 f"{c['lit+half_turn']['anisotropic']:.4f} | {c['between']['isotropic']:.3f} | {c['between']['anisotropic']:.4f} |")
    L += ["", f"Anisotropic coverage (lit) of the optimised design: **x{out['ratio_anisotropic_lit']:.2f}** the thesis "
          f"rig with all 16 LEDs (x{rigs['optimised']['coverage_pct']['lit']['anisotropic'] / rigs['thesis_middle']['coverage_pct']['lit']['anisotropic']:.2f} "
          "the 8 LEDs the thesis measured with)." if "thesis_middle" in rigs else "", ""]
    L += [f"## Expected relative standard errors (Fisher information, scale {settings.scale:g})", "",
          "| material | design | " + " | ".join(PARAMS) + " | geometric mean |", "|---|---|" + "---|" * (len(PARAMS) + 1)]
    for lb, _ in materials:
        for k in keys:
            e = rigs[k]["expected_errors"][lb]
            cells = [("-" if e["relative"][p] is None else f"{e['relative'][p]:.2e}") for p in PARAMS]
            gm = e["geometric_mean_relative"]
            L.append(f"| {lb} | {names[k]} | " + " | ".join(cells) + f" | {gm:.2e} |")
    L += ["", "Error ratio optimised / thesis (16 LEDs), geometric mean: "
          + ", ".join(f"{k} {v:.2f}" for k, v in out["error_ratios"].items()), "",
          "Relative errors: sigma/p for rho_d, rho_s, alpha_x, alpha_y; sigma in radians for the lobe rotation. "
          "They assume independent pixels (scale as 1/scale) and leave out LED drift common to a frame and the "
          "peak clipping of eq. 6.5, so they are lower bounds; the ratios between designs are the point. "
          "Confirming them by simulating both rigs on the twin and fitting needs the measurement pipeline.", "",
          "## The design", "", "| LED | angle (deg) | height (mm) | distance (mm) |", "|---|---|---|---|"]
    for led in new_rig.leds:
        a, h, dist = D.mount_of(led.position)
        L.append(f"| {led.id} | {a:+.0f} | {h:+.0f} | {dist:.0f} |")
    L += ["", f"Sample rotations: {list(new_rig.sample_rotations)} (thesis: {list(ref_rig.sample_rotations)}).", "",
          "## Fewer LEDs", "", "Prefixes of the design ordered greedily (`leds_vs_score.png`); each LED costs "
          f"{len(new_rig.sample_rotations)} rotations x 3 sequences x ~4 min of capture (thesis 4.2.3).", "",
          "| LEDs | score | aniso coverage % (scale " + f"{settings.scale:g}) | " + " | ".join(lb for lb, _ in materials) + " |",
          "|---|---|---|" + "---|" * len(materials)]
    for row in d["prefixes"]:
        L.append(f"| {row['n_leds']} | {row['score']:+.3f} | {100 * row['anisotropic_coverage']:.4f} | "
                 + " | ".join(f"{row['geometric_mean_relative_error'][lb]:.2e}" for lb, _ in materials) + " |")
    L += ["", "Mounting limits (glossrig.core.design.placement.MountingLimits): "
          + ", ".join(f"{k}={v}" for k, v in D.MountingLimits().to_json().items()) + ".", "",
          "Plots: `layout.png` (top and side views with board and camera view), `aniso_by_rotation.png`, "
          "`theta_per_led.png`, `coverage_per_led.png`, `expected_errors.png`, `leds_vs_score.png`.", ""]
    return "\n".join(L)
