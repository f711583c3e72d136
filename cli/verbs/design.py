"""Rig design from geometry alone: BRDF-space coverage (thesis 7.1.3) and LED /
rotation optimisation for coverage and expected Ward-parameter error (thesis 9.1).

sub-verbs:
  coverage   the rig's isotropic and anisotropic coverage under every binning
             convention, beside the thesis's printed 0.98 % and 0.1 %, with plots
             (theta_in/theta_out per LED as thesis fig. 7.2, anisotropic
             coverage by rotation, coverage per LED)
  optimise   sweep LED mounts and sample rotations (Dask: a local cluster by
             default, --scheduler ADDRESS for an existing one, --workers 0 for
             one process) and write the best design as a new rig file
  errors     expected extended-Ward parameter errors of a rig's design for
             target materials (Fisher information, glossrig.core.design.fisher)

Further sub-verbs can be added as modules ``glossrig.cli.verbs._design_<name>``
that define HELP, add_arguments(parser) and run(args), like a verb.

examples:
  glossrig design coverage --rig scenes/thesis_rig.toml --out validation/design/coverage
  glossrig design optimise --rig scenes/thesis_rig.toml --leds 16 \\
      --materials brushed_original,sanded_original,base_2 --out scenes/optimised_rig.toml \\
      --report validation/design/optimise
"""
from __future__ import annotations

import importlib
import json
import logging
import math
import pkgutil
import sys
from pathlib import Path

from glossrig.cli.outputs import add_force_option, prepare_output
from glossrig.core.errors import InputError

_logger = logging.getLogger(__name__)

HELP = "rig design: BRDF-space coverage and LED/rotation optimisation (thesis 7.1.3, 9.1)"
PRINTED_ISO, PRINTED_ANISO = 0.0098, 0.001      # thesis 7.1.3, fractions


def _log(quiet: bool):
    """Progress messages through the ``glossrig`` logger (``-q`` silences them)."""
    if quiet:
        return lambda msg: None
    return _logger.info


def _floats(text: str, what: str) -> list[float]:
    try:
        vals = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise InputError(f"{what}: expected comma-separated numbers, got {text!r}") from None
    if not vals or not all(math.isfinite(v) for v in vals):
        raise InputError(f"{what}: expected finite numbers, got {text!r}")
    return vals


def _out_dir(path: str, force: bool = False) -> Path:
    """Check (glossrig.cli.outputs: refused if not empty unless ``force``) and create an output folder."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise InputError("output exists and is not a folder", path=out)
    if not out.parent.is_dir():
        raise InputError("parent folder of the output does not exist", path=out)
    prepare_output(out, force, kind="folder")
    out.mkdir(exist_ok=True)
    return out


# ----------------------------------------------------------------------------
# coverage
# ----------------------------------------------------------------------------

def add_coverage_arguments(p) -> None:
    p.add_argument("--rig", required=True, help="rig file (scenes/*.toml)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for coverage.json, coverage.md, conventions.csv and plots")
    p.add_argument("--scales", default="1.0,0.5,0.25",
                   help="pixel densities (image scales) to tabulate; the first is the headline (default 1.0,0.5,0.25)")
    p.add_argument("--camera-distances", default=None,
                   help="also tabulate these camera distances (mm), at the last of --scales, e.g. 450,550")
    p.add_argument("--leds", default=None,
                   help="LEDs of the headline figure (default: 'middle' if the rig has a middle row of 8 as the "
                        "thesis measured, else all)")
    add_force_option(p, "the files in a non-empty --out folder")


def run_coverage(args) -> int:
    import pandas as pd

    from glossrig.core.design import coverage as cov
    from glossrig.core.rig import load_rig

    say = _log(args.quiet)
    prepare_output(args.out, args.force, kind="folder")
    rig = load_rig(args.rig)
    out = _out_dir(args.out, args.force)
    scales = _floats(args.scales, "--scales")
    dists = _floats(args.camera_distances, "--camera-distances") if args.camera_distances else []
    if args.leds:
        head_leds = rig.select_leds(args.leds)
    else:
        mid = [led.id for led in rig.leds if led.row == "middle"]
        head_leds = mid if len(mid) == 8 else rig.led_ids()
    led_sets = {f"{len(head_leds)} LEDs ({args.leds or ('middle row' if head_leds != rig.led_ids() else 'all')})": head_leds}
    if sorted(head_leds) != sorted(rig.led_ids()):
        led_sets[f"all {len(rig.led_ids())} LEDs"] = rig.led_ids()
    rots = [float(r) for r in rig.sample_rotations]
    rot_sets = {"rotations " + ",".join(f"{r:g}" for r in rots): rots}
    if rots != [0.0]:
        rot_sets["rotation 0 only"] = [0.0]
    rows = []
    datasets = {}
    runs = [(s, None) for s in scales] + [(scales[-1], d) for d in dists]
    for s, dist in runs:
        px = cov.pixel_geometry(rig, s, dist)
        for geo in cov.GEOMETRIES:
            say(f"scale {s:g}, camera {px.camera_distance:g} mm, {geo} geometry: {len(px)} pixels on the sample")
            data = cov.collect(rig, led_ids=rig.led_ids(), rotations=sorted(set(rots) | {0.0}), geometry=geo,
                               pixels=px, progress=None if args.quiet else (lambda m: say("  " + m)))
            datasets[(s, dist, geo)] = data
            rows += cov.convention_rows(data, led_sets, rot_sets)
    df = pd.DataFrame(rows)
    df["match"] = [cov.match_score(a, b) for a, b in zip(df.iso_pct, df.aniso_pct)]
    df.to_csv(out / "conventions.csv", index=False, float_format="%.6g")
    head = datasets[(scales[0], None, "corrected")]
    base = cov.Convention()
    head_cov = cov.coverage(head, base, head_leds, rots)
    # plots
    cov.plot_theta_coverage(head, out / "theta_per_led.png", "between", head_leds,
                            title=f"{rig.name}: theta_in vs theta_out per LED (thesis fig. 7.2; normal between "
                                  f"camera and lamp)")
    cov.plot_theta_coverage(head, out / "theta_per_led_lit.png", "lit", rig.led_ids())
    cov.plot_rotation_coverage({f"{len(head_leds)} LEDs": (head, base, head_leds),
                                f"{len(rig.led_ids())} LEDs": (head, base, rig.led_ids())},
                               out / "aniso_by_rotation.png",
                               title=f"{rig.name}: anisotropic coverage by sample rotation (scale {scales[0]:g})")
    summary = {
        "rig": str(rig.path), "printed_pct": {"isotropic": 0.98, "anisotropic": 0.1},
        "headline": {"leds": head_leds, "rotations_deg": rots, "scale": scales[0],
                     "camera_distance_mm": head.camera_distance, "geometry": "corrected",
                     "convention": base.label(), "isotropic_pct": 100 * head_cov["isotropic"],
                     "anisotropic_pct": 100 * head_cov["anisotropic"],
                     "bins": {k: v for k, v in head_cov.items() if k.endswith("bins") or k.endswith("total")}},
        "best_match": df.sort_values(["match", "geometry"]).iloc[0].to_dict(),
        "best_isotropic_match": df.iloc[(df.iso_pct - 0.98).abs().argsort().iloc[0]].to_dict(),
        "best_anisotropic_match": df.iloc[(df.aniso_pct - 0.1).abs().argsort().iloc[0]].to_dict(),
        "rows": len(df), "command": " ".join(["glossrig", "design"] + sys.argv[2:]) if sys.argv[1:2] == ["design"] else None,
    }
    (out / "coverage.json").write_text(json.dumps(summary, indent=2, default=_jsonable) + "\n")
    (out / "coverage.md").write_text(coverage_markdown(df, summary, led_sets, rot_sets))
    say(f"{rig.name}: isotropic {summary['headline']['isotropic_pct']:.3f} %, anisotropic "
        f"{summary['headline']['anisotropic_pct']:.4f} % ({base.label()}, scale {scales[0]:g}); printed 0.98 % and 0.1 %")
    say(f"best joint match: {summary['best_match']['iso_pct']:.3f} % / {summary['best_match']['aniso_pct']:.4f} % "
        f"(off by a factor {10 ** summary['best_match']['match']:.2f} at worst); wrote {out}")
    return 0


def _jsonable(o):
    if hasattr(o, "item"):
        return o.item()
    raise TypeError(type(o).__name__)


def _conv_desc(r) -> str:
    folds = [n for n, on in (("reciprocity", r["reciprocity"]), ("half-turn", r["half_turn"])) if on]
    return (f"{r['geometry']} geometry, {r['leds']}, {r['rotations']}, scale {r['scale']:g}, camera "
            f"{r['camera_mm']:g} mm, filter {r['filter']}, dphi {r['dphi']}, {', '.join(folds) or 'no folds'}, "
            f"{r['phi_bins']} phi bins")


def _reproduction_text(df, summary, first_leds, first_rots) -> str:
    best = df.sort_values(["match", "geometry"]).iloc[0]
    own = df[(df.leds == first_leds) & (df.rotations == first_rots) & (df.scale == df.scale.max())]
    own_best = own.sort_values(["match", "geometry"]).iloc[0]
    iso = df.iloc[(df.iso_pct - 100 * PRINTED_ISO).abs().argsort().iloc[0]]
    an = df.iloc[(df.aniso_pct - 100 * PRINTED_ANISO).abs().argsort().iloc[0]]
    verdict = ("A single convention reproduces both printed figures within 10 %."
               if best["match"] <= math.log10(1.1) else
               f"**No single convention reproduces both printed figures**: of {len(df)} combinations the closest "
               f"pair is {best['iso_pct']:.3f} % / {best['aniso_pct']:.4f} %, off by x{10 ** best['match']:.2f} "
               f"({_conv_desc(best)}).")
    return "\n".join([
        verdict, "",
        f"- In the thesis's own configuration ({first_leds}, {first_rots}, full resolution) the closest is "
        f"{own_best['iso_pct']:.3f} % / {own_best['aniso_pct']:.4f} % (x{10 ** own_best['match']:.2f}; "
        f"{_conv_desc(own_best)}).",
        f"- Isotropic alone: {iso['iso_pct']:.3f} % is nearest 0.98 % ({_conv_desc(iso)}); anisotropic there "
        f"{iso['aniso_pct']:.4f} %.",
        f"- Anisotropic alone: {an['aniso_pct']:.4f} % is nearest 0.1 % ({_conv_desc(an)}); isotropic there "
        f"{an['iso_pct']:.3f} %.",
        "- Every convention that counts only lit samples puts the isotropic coverage well above 0.98 % at full "
        "resolution while the anisotropic one stays near or below 0.1 %; the printed pair needs a ratio "
        "aniso/iso of about 0.1, which only the conventions that enlarge the isotropic space (visible pixels, "
        "literal |phi_in - phi_out|) or fold the anisotropic one approach."])


def coverage_markdown(df, summary, led_sets, rot_sets) -> str:
    cols = ["geometry", "scale", "camera_mm", "leds", "rotations", "filter", "dphi", "reciprocity", "half_turn",
            "phi_bins", "iso_pct", "aniso_pct", "match"]

    def table(d):
        lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        for _, r in d.iterrows():
            cells = []
            for c in cols:
                v = r[c]
                if c in ("iso_pct",):
                    cells.append(f"{v:.3f}")
                elif c in ("aniso_pct",):
                    cells.append(f"{v:.4f}")
                elif c == "match":
                    cells.append(f"{10 ** v:.2f}x")
                elif isinstance(v, float):
                    cells.append(f"{v:g}")
                else:
                    cells.append(str(v))
            lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines)

    h = summary["headline"]
    first_leds, first_rots = next(iter(led_sets)), next(iter(rot_sets))
    base = df[(df.leds == first_leds) & (df.rotations == first_rots)]
    one_at_a_time = base[(base.scale == h["scale"]) & (base.camera_mm == h["camera_distance_mm"])]
    txt = [
        "# BRDF-space coverage of the rig (thesis 7.1.3)",
        "",
        f"Rig: `{summary['rig']}`. Printed in the thesis (7.1.3, 8 middle-row LEDs): "
        "**0.98 % isotropic, 0.1 % anisotropic**.",
        "",
        f"Headline (project conventions): {len(h['leds'])} LEDs {h['leds']}, rotations {h['rotations_deg']}, "
        f"image scale {h['scale']:g} (full resolution), camera {h['camera_distance_mm']:g} mm from the axis, "
        f"corrected geometry ({h['convention']}): **isotropic {h['isotropic_pct']:.3f} %, anisotropic "
        f"{h['anisotropic_pct']:.4f} %** ({h['bins']['isotropic_bins']} of {h['bins']['isotropic_total']} and "
        f"{h['bins']['anisotropic_bins']} of {h['bins']['anisotropic_total']} bins).",
        "",
        "Conventions (glossrig.core.design.coverage): 1-degree bins, `floor(angle)`; theta in [0, 90), "
        "azimuths in [0, 360) counter-clockwise from the tangent; isotropic space 90 x 90 x 180 with "
        "|phi_in - phi_out| folded onto [0, 180] (`dphi folded`) or 90 x 90 x 360 taken literally "
        "(`dphi literal`); anisotropic space 90 x 90 x 360 x 360. Filters: `lit` = both directions above the "
        "surface; `between` = also the normal between camera and lamp in the cross-section (the pixels of "
        "fig. 7.2); `visible` = every pixel on the sample, lit or not (theta_in to 180, space doubled). "
        "`reciprocity` identifies (in, out) with (out, in), `half_turn` (phi_in, phi_out) with "
        "(phi_in+180, phi_out+180); numerator and denominator both count classes (Burnside). "
        "`printed` geometry: the thesis's equations as printed (incident vector from the axis point, "
        "eq. 4.59; unsigned azimuth in [0, 180], eq. 4.68-4.70), with 360 or 180 azimuth bins in the "
        "denominator. `match` = how far the worse of the two figures is from the printed one (1.00x = both "
        "reproduced).",
        "",
        "## Can the printed figures be reproduced?",
        "",
        _reproduction_text(df, summary, first_leds, first_rots),
        "",
        "## Closest to both printed figures",
        "",
        table(df.sort_values(["match", "geometry"]).head(12)),
        "",
        "## Every convention at the headline density and camera distance",
        "",
        table(one_at_a_time),
        "",
        "## Pixel density and camera distance (lit, dphi folded, no folds)",
        "",
        table(df[(df.filter == "lit") & (df.dphi == "folded") & (~df.reciprocity) & (~df.half_turn)
                 & (df.phi_bins == 360)]),
        "",
        "All rows: `conventions.csv`. Plots: `theta_per_led.png` (fig. 7.2: theta_in vs theta_out per LED, "
        "between-filtered), `theta_per_led_lit.png` (all lit pixels of all LEDs), `aniso_by_rotation.png`.",
        "",
    ]
    return "\n".join(txt)


# ----------------------------------------------------------------------------
# optimise
# ----------------------------------------------------------------------------

DEFAULT_MATERIALS = "brushed_original,sanded_original,base_2"


def add_optimise_arguments(p) -> None:
    p.add_argument("--rig", required=True, help="rig to improve (also the reference design and the file template)")
    p.add_argument("--leds", type=int, required=True, help="number of LEDs of the design (at most 16 relay channels)")
    p.add_argument("--materials", default=DEFAULT_MATERIALS,
                   help=f"target extended-Ward materials (names in scenes/materials or ward:... specs, lobe_rotation "
                        f"in radians or with a unit: 140deg), default {DEFAULT_MATERIALS}")
    p.add_argument("--out", required=True, help="new rig file to write (scenes/*.toml)")
    p.add_argument("--report", metavar="DIR", default=None, help="also write design.json and plots here")
    p.add_argument("--rotations", type=int, default=4, help="number of sample rotations (default 4, as the thesis)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS", help="existing Dask scheduler (tcp://host:8786)")
    p.add_argument("--workers", type=int, default=2,
                   help="worker processes of the local Dask cluster (default 2); 0 = run in this one process")
    p.add_argument("--angle-step", type=float, default=10.0, help="candidate angle grid step, degrees (default 10)")
    p.add_argument("--heights", default="-40,-20,0,20,40,80,120", help="candidate heights, mm")
    p.add_argument("--distances", default="150,250,350", help="candidate distances from the axis, mm")
    p.add_argument("--rotation-step", type=int, default=15, help="candidate sample-rotation step, whole degrees (default 15)")
    p.add_argument("--lambda", dest="lam", type=float, default=1.0,
                   help="weight of the expected-error term against the coverage term (default 1)")
    p.add_argument("--iso-weight", type=float, default=1.0,
                   help="weight of the isotropic-coverage term (default 1; 0 = anisotropic coverage and errors only)")
    p.add_argument("--scale", type=float, default=0.25, help="image scale of the sweep (default 0.25)")
    p.add_argument("--noise", default="hdr", help="noise model: hdr[:LED_REL] (default) or relative[:REL]")
    p.add_argument("--final-scale", type=float, default=1.0,
                   help="image scale of the final coverage comparison (default 1.0, full resolution)")
    add_force_option(p, "an existing output rig file and the files in a non-empty --report folder")


def run_optimise(args) -> int:

    from glossrig.core.design import placement as D
    from glossrig.core.rig import load_rig

    say = _log(args.quiet)
    out = prepare_output(args.out, args.force)
    if args.report:
        prepare_output(args.report, args.force, kind="folder")
    rig = load_rig(args.rig)
    report = _out_dir(args.report, args.force) if args.report else None
    if args.rotation_step < 1 or 360 % args.rotation_step:
        raise InputError(f"--rotation-step must divide 360, got {args.rotation_step}")
    if args.workers < 0:
        raise InputError(f"--workers must be >= 0, got {args.workers}")
    materials = D.parse_materials(args.materials)
    space = D.SearchSpace(angle_step_deg=args.angle_step, heights_mm=tuple(_floats(args.heights, "--heights")),
                          distances_mm=tuple(_floats(args.distances, "--distances")),
                          rotations_deg=tuple(range(-180, 180, args.rotation_step)))
    limits = D.MountingLimits()
    runner = D.make_runner(args.scheduler, args.workers)
    say(f"sweeping on {runner.name}")
    try:
        res = D.optimise(rig, args.leds, materials, runner, space=space, limits=limits, n_rotations=args.rotations,
                         lam=args.lam, iso_weight=args.iso_weight, coverage_scale=args.scale, fisher_scale=args.scale, noise=args.noise,
                         progress=not args.quiet, log=say)
    finally:
        runner.close()
    problems = D.design_problems(rig, res.positions, limits)
    if problems:
        raise InputError("the optimised design breaks the mounting limits: " + "; ".join(problems))
    header = (f"# Optimised rig (glossrig design optimise, thesis 9.1): {args.leds} LEDs and "
              f"{args.rotations} sample rotations chosen for anisotropic and isotropic BRDF-space coverage (thesis 7.1.3) and\n"
              f"# the expected extended-Ward parameter error (Fisher information) of {args.materials}.\n"
              f"# Everything but the LED table, sample rotations, name and description is copied from {rig.path}.\n"
              f"# LEDs mount on printed vertical posts with sliding carriages (heights -40..120 mm), see\n"
              f"# glossrig.core.design.placement. Regenerate: see validation/design/README.md.\n#\n")
    D.write_rig_toml(rig.path, res.positions, res.rotations, out, header=header, name="optimised",
                     description=f"Thesis rig with {args.leds} LEDs placed by glossrig design optimise")
    say(f"wrote {out}: score {res.score:+.4f} (thesis 0), coverage x{res.coverage / res.reference['anisotropic_coverage_design_scale']:.2f}")
    if report is not None:
        new = load_rig(out)
        write_design_report(rig, new, res, materials, report, args, say)
    return 0


def write_design_report(ref_rig, new_rig, res, materials, report: Path, args, say) -> dict:
    """Final comparison at ``--final-scale``: coverage (every convention of the
    headline table) and Fisher errors of both rigs, design.json, design.md, plots."""
    from glossrig.core.design import coverage as cov
    from glossrig.core.design import placement as D
    fs = args.final_scale
    out = {"design": res.to_json(), "command": "glossrig design " + " ".join(sys.argv[2:]) if sys.argv[1:2] == ["design"] else None,
           "materials": {lb: p.as_dict() for lb, p in materials}, "noise": args.noise, "final_scale": fs,
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
        errs = D.design_errors(rg, materials, rotations=rots, led_ids=leds, scale=args.scale, noise=args.noise)
        out["rigs"][key] = {"leds": leds, "rotations_deg": rots,
                            "coverage_pct": {k: {"isotropic": 100 * v["isotropic"], "anisotropic": 100 * v["anisotropic"]}
                                             for k, v in c.items()},
                            "expected_errors": {lb: e.to_json() for lb, e in errs.items()}}
    r_ref, r_new = out["rigs"]["thesis_16"], out["rigs"]["optimised"]
    out["ratio_anisotropic_lit"] = r_new["coverage_pct"]["lit"]["anisotropic"] / r_ref["coverage_pct"]["lit"]["anisotropic"]
    out["error_ratios"] = {lb: r_new["expected_errors"][lb]["geometric_mean_relative"]
                           / r_ref["expected_errors"][lb]["geometric_mean_relative"] for lb, _ in materials}
    (report / "design.json").write_text(json.dumps(out, indent=2, default=_jsonable) + "\n")
    (report / "design.md").write_text(design_markdown(out, materials, ref_rig, new_rig, args))
    plot_prefixes(res, report / "leds_vs_score.png")
    base = cov.Convention()
    cov.plot_rotation_coverage({k: (d, base, None) for k, d in datas.items()}, report / "aniso_by_rotation.png",
                               title=f"Anisotropic coverage by sample rotation (scale {fs:g})")
    cov.plot_theta_coverage(datas["optimised"], report / "theta_per_led.png", "lit",
                            title="optimised: occupied theta bins per LED (lit pixels)")
    plot_layout(ref_rig, new_rig, report / "layout.png")
    cov.plot_per_led({k: cov.per_led(d, base) for k, d in datas.items() if k != "thesis_middle"},
                     {}, report / "coverage_per_led.png")
    plot_errors(out, materials, report / "expected_errors.png")
    say(f"optimised vs thesis (16 LEDs): anisotropic coverage x{out['ratio_anisotropic_lit']:.2f}, error ratios "
        + ", ".join(f"{k} {v:.2f}" for k, v in out["error_ratios"].items()))
    return out


def design_markdown(out: dict, materials, ref_rig, new_rig, args) -> str:
    from glossrig.core.design.placement import mount_of
    from glossrig.core.design.fisher import PARAMS

    d = out["design"]
    rigs = out["rigs"]
    keys = [k for k in ("thesis_middle", "thesis_16", "optimised") if k in rigs]
    names = {"thesis_middle": "thesis, 8 middle LEDs (as measured)", "thesis_16": "thesis, all 16 LEDs",
             "optimised": f"optimised, {len(new_rig.leds)} LEDs"}
    L = ["# Optimised LED design (thesis 9.1)", ""]
    L.append(f"Command: `{out.get('command') or 'glossrig design optimise ...'}` (sweep on {d['runner']}; "
             f"{d['n_candidates']} candidate mounts, {d['n_feasible']} within the mounting limits; sweep "
             f"{d['timings_s']['sweep']:.0f} s, selection {d['timings_s']['selection']:.0f} s).")
    L.append("")
    L.append(f"Score (glossrig.core.design.placement): ln(C/C_thesis) + {args.iso_weight:g} * ln(C_iso/C_iso,thesis) - {args.lam:g} "
             f"* mean ln(E/E_thesis), C the anisotropic and C_iso the isotropic coverage, and E the geometric mean of the relative standard errors of each target material "
             f"({', '.join(lb for lb, _ in materials)}), both at image scale {args.scale:g}; noise model {args.noise!r}. "
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
    L += [f"## Expected relative standard errors (Fisher information, scale {args.scale:g})", "",
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
        a, h, dist = mount_of(led.position)
        L.append(f"| {led.id} | {a:+.0f} | {h:+.0f} | {dist:.0f} |")
    L += ["", f"Sample rotations: {list(new_rig.sample_rotations)} (thesis: {list(ref_rig.sample_rotations)}).", "",
          "## Fewer LEDs", "", "Prefixes of the design ordered greedily (`leds_vs_score.png`); each LED costs "
          f"{len(new_rig.sample_rotations)} rotations x 3 sequences x ~4 min of capture (thesis 4.2.3).", "",
          "| LEDs | score | aniso coverage % (scale " + f"{args.scale:g}) | " + " | ".join(lb for lb, _ in materials) + " |",
          "|---|---|---|" + "---|" * len(materials)]
    for row in d["prefixes"]:
        L.append(f"| {row['n_leds']} | {row['score']:+.3f} | {100 * row['anisotropic_coverage']:.4f} | "
                 + " | ".join(f"{row['geometric_mean_relative_error'][lb]:.2e}" for lb, _ in materials) + " |")
    L += ["", "Mounting limits (glossrig.core.design.placement.MountingLimits): "
          + ", ".join(f"{k}={v}" for k, v in _mount_doc().items()) + ".", "",
          "Plots: `layout.png` (top and side views with board and camera view), `aniso_by_rotation.png`, "
          "`theta_per_led.png`, `coverage_per_led.png`, `expected_errors.png`, `leds_vs_score.png`.", ""]
    return "\n".join(L)


def _mount_doc():
    from glossrig.core.design.placement import MountingLimits

    return MountingLimits().to_json()


def plot_prefixes(res, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = res.prefixes
    n = [r["n_leds"] for r in rows]
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].plot(n, [r["score"] for r in rows], "o-")
    ax[0].axhline(0, color="0.5", ls="--", lw=0.8)
    ax[0].set_xlabel("number of LEDs (greedy order)")
    ax[0].set_ylabel("score (thesis rig = 0)")
    ax[1].plot(n, [100 * r["anisotropic_coverage"] for r in rows], "o-", color="C3", label="anisotropic coverage")
    ax[1].axhline(100 * res.reference["anisotropic_coverage_design_scale"], color="C3", ls="--", lw=0.8,
                  label="thesis rig")
    ax[1].set_xlabel("number of LEDs (greedy order)")
    ax[1].set_ylabel("anisotropic coverage (%)")
    ax2 = ax[1].twinx()
    for lb in rows[0]["geometric_mean_relative_error"]:
        ax2.semilogy(n, [r["geometric_mean_relative_error"][lb] for r in rows], ".:", label=lb)
    ax2.set_ylabel("geometric-mean relative error")
    ax[1].legend(fontsize=7, loc="upper left")
    ax2.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def plot_layout(ref_rig, new_rig, path) -> None:
    """Top and side views of both LED layouts with the board, camera and its field of view."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from glossrig.core.design import placement as D
    lim = D.MountingLimits()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 5.5))
    bx, bz = lim.board_x_mm, lim.board_z_mm
    ax1.add_patch(plt.Rectangle((bx[0], bz[0]), bx[1] - bx[0], bz[1] - bz[0], fill=False, ls="--", color="0.5"))
    cam = ref_rig.camera
    half = math.atan((cam.image_px[1] / 2) / cam.fy)       # across the axis (rolled camera)
    zc = cam.distance_to_axis
    for s in (-1, 1):
        ax1.plot([0, s * zc * math.tan(half) * 2], [zc, -zc], color="C2", lw=0.8)
    ax1.plot([0], [zc], "s", color="C2", label="camera")
    ax1.add_patch(plt.Circle((0, 0), ref_rig.cylinder_radius, color="0.3"))
    for rg, mk, col, lab in ((ref_rig, "o", "C0", "thesis"), (new_rig, "^", "C3", "optimised")):
        P = np.array([led.position for led in rg.leds])
        ax1.scatter(P[:, 0], P[:, 2], marker=mk, color=col, label=lab, s=30)
        ang = np.degrees(np.arctan2(P[:, 0], P[:, 2]))
        ax2.scatter(ang, P[:, 1], marker=mk, color=col, label=lab, s=30)
    ax1.set_aspect("equal")
    ax1.set_xlabel("x (mm)")
    ax1.set_ylabel("z (mm, towards the camera)")
    ax1.set_title("Top view: board (dashed), camera field of view (green)")
    ax1.legend(fontsize=8)
    ax2.set_xlabel("angle about the axis from the camera (deg)")
    ax2.set_ylabel("height (mm)")
    ax2.axhspan(*lim.height_mm, color="0.9", zorder=0)
    ax2.set_title("Angle and height of every LED")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def plot_errors(out: dict, materials, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from glossrig.core.design.fisher import PARAMS

    keys = [k for k in ("thesis_middle", "thesis_16", "optimised") if k in out["rigs"]]
    fig, axes = plt.subplots(1, len(materials), figsize=(4.5 * len(materials), 4), squeeze=False)
    for ax, (lb, _) in zip(axes[0], materials):
        x = np.arange(len(PARAMS))
        w = 0.8 / len(keys)
        for k, key in enumerate(keys):
            rel = out["rigs"][key]["expected_errors"][lb]["relative"]
            vals = [rel[p] if rel[p] is not None else np.nan for p in PARAMS]
            ax.bar(x + k * w, vals, width=w, label=key)
        ax.set_yscale("log")
        ax.set_xticks(x + w * (len(keys) - 1) / 2, ["rho_d", "rho_s", "a_x", "a_y", "rot (rad)"], fontsize=8)
        ax.set_title(lb, fontsize=9)
        ax.set_ylabel("expected relative standard error")
    axes[0][0].legend(fontsize=8)
    fig.suptitle("Expected Ward-parameter errors (Fisher information)")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


# ----------------------------------------------------------------------------
# errors
# ----------------------------------------------------------------------------

def add_errors_arguments(p) -> None:
    p.add_argument("--rig", required=True, help="rig file")
    p.add_argument("--materials", default=DEFAULT_MATERIALS,
                   help=f"extended-Ward materials (names or ward:... specs, lobe_rotation in radians or with a unit: "
                        f"140deg; default {DEFAULT_MATERIALS})")
    p.add_argument("--leds", default="all", help="LEDs used: all, middle, a row or ids (default all)")
    p.add_argument("--rotations", default=None, help="sample rotations, degrees (default: the rig's)")
    p.add_argument("--scale", type=float, default=0.25, help="image scale the pixels are counted at (default 0.25)")
    p.add_argument("--noise", default="hdr", help="hdr[:LED_REL] (default) or relative[:REL]")
    p.add_argument("--gain-noise", type=float, default=0.0,
                   help="residual LED gain per (LED, rotation) sequence after neighbour correction and patch "
                        "normalisation, relative standard deviation, a nuisance parameter common to the "
                        "sequence's pixels (default 0: none; use with --noise hdr:0)")
    p.add_argument("--out", default=None, help="JSON file to write (default: print)")
    add_force_option(p, "an existing --out file")


def run_errors(args) -> int:
    from glossrig.core.design import placement as D
    from glossrig.core.rig import load_rig

    if args.out:
        prepare_output(args.out, args.force)
    rig = load_rig(args.rig)
    materials = D.parse_materials(args.materials)
    leds = rig.select_leds(args.leds)
    rots = _floats(args.rotations, "--rotations") if args.rotations else list(rig.sample_rotations)
    errs = D.design_errors(rig, materials, rotations=rots, led_ids=leds, scale=args.scale, noise=args.noise,
                           gain_rel=args.gain_noise)
    doc = {"rig": str(rig.path), "leds": leds, "rotations_deg": rots, "scale": args.scale, "noise": args.noise,
           "gain_noise": args.gain_noise,
           "method": "Fisher information (Cramer-Rao bound), glossrig.core.design.fisher",
           "stderr_kind": "noise-only (the --noise model and --gain-noise; excludes calibration and model error)",
           "expected_errors": {lb: e.to_json() for lb, e in errs.items()}}
    text = json.dumps(doc, indent=2) + "\n"
    if args.out:
        Path(args.out).write_text(text)
    else:
        sys.stdout.write(text)
    return 0


# ----------------------------------------------------------------------------
# sub-verb registry
# ----------------------------------------------------------------------------

SUBVERBS = {
    "coverage": ("BRDF-space coverage of a rig under every convention, with plots (thesis 7.1.3)",
                 add_coverage_arguments, run_coverage),
    "optimise": ("optimise LED mounts and sample rotations; write a new rig file (thesis 9.1)",
                 add_optimise_arguments, run_optimise),
    "errors": ("expected Ward-parameter errors of a rig from the Fisher information",
               add_errors_arguments, run_errors),
}


def _plugins() -> dict:
    """Sub-verbs from modules ``glossrig.cli.verbs._design_<name>``."""
    from glossrig.cli import verbs

    found = {}
    for info in pkgutil.iter_modules(verbs.__path__):
        if info.name.startswith("_design_"):
            mod = importlib.import_module(f"{verbs.__name__}.{info.name}")
            found[info.name[len("_design_"):].replace("_", "-")] = (mod.HELP, mod.add_arguments, mod.run)
    return found


def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest="design_cmd", metavar="SUBVERB", required=True)
    for name, (help_, add, run_) in {**SUBVERBS, **_plugins()}.items():
        p = sub.add_parser(name, help=help_, description=help_)
        add(p)
        p.set_defaults(func=run_)


def run(args) -> int:
    return int(args.func(args) or 0)
