"""The coverage study of ``glossrig design coverage`` (thesis 7.1.3): a rig's isotropic
and anisotropic coverage under every convention of :mod:`glossrig.core.design.coverage`,
at several pixel densities and camera distances, set beside the printed 0.98 % and
0.1 %, and its report (``conventions.csv``, ``coverage.json``, ``coverage.md`` and the
theta and rotation plots).

:func:`coverage_study` computes, :func:`write_coverage_report` writes into a folder
the caller has checked (:mod:`glossrig.cli.outputs`).
"""
from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from glossrig.core.design import coverage as cov

if TYPE_CHECKING:
    import pandas as pd

    from glossrig.core.rig import Rig


@dataclass
class CoverageStudy:
    """Every convention's coverages (``table``, one row each, with ``match``) and the
    headline figures (``summary``, the body of ``coverage.json``)."""

    rig: Rig
    table: pd.DataFrame                # the rows of conventions.csv
    summary: dict
    led_sets: dict[str, list[int]]
    rot_sets: dict[str, list[float]]
    headline: cov.CoverageData         # full LED set, first scale, corrected geometry
    headline_leds: list[int]


def headline_leds(rig, leds: str | None = None) -> list[int]:
    """The LEDs of the headline figure: ``leds`` (:meth:`~glossrig.core.rig.Rig.select_leds`),
    else the middle row if it has 8 LEDs as the thesis measured, else all."""
    if leds:
        return rig.select_leds(leds)
    mid = [led.id for led in rig.leds if led.row == "middle"]
    return mid if len(mid) == 8 else rig.led_ids()


def coverage_study(rig, scales: Sequence[float], camera_distances: Sequence[float] = (), leds: str | None = None,
                   log: Callable[[str], None] | None = None) -> CoverageStudy:
    """Collect the rig's bins at every scale (and every camera distance at the last
    scale) in both geometries and tabulate every convention for the headline LEDs and
    all LEDs, the rig's rotations and rotation 0 alone; ``log`` gets progress messages."""
    import pandas as pd

    say = log or (lambda msg: None)
    head_leds = headline_leds(rig, leds)
    led_sets = {f"{len(head_leds)} LEDs ({leds or ('middle row' if head_leds != rig.led_ids() else 'all')})": head_leds}
    if sorted(head_leds) != sorted(rig.led_ids()):
        led_sets[f"all {len(rig.led_ids())} LEDs"] = rig.led_ids()
    rots = [float(r) for r in rig.sample_rotations]
    rot_sets = {"rotations " + ",".join(f"{r:g}" for r in rots): rots}
    if rots != [0.0]:
        rot_sets["rotation 0 only"] = [0.0]
    rows = []
    datasets = {}
    runs = [(s, None) for s in scales] + [(scales[-1], d) for d in camera_distances]
    for s, dist in runs:
        px = cov.pixel_geometry(rig, s, dist)
        for geo in cov.GEOMETRIES:
            say(f"scale {s:g}, camera {px.camera_distance:g} mm, {geo} geometry: {len(px)} pixels on the sample")
            data = cov.collect(rig, led_ids=rig.led_ids(), rotations=sorted(set(rots) | {0.0}), geometry=geo,
                               pixels=px, progress=None if log is None else (lambda m: say("  " + m)))
            datasets[(s, dist, geo)] = data
            rows += cov.convention_rows(data, led_sets, rot_sets)
    df = pd.DataFrame(rows)
    df["match"] = [cov.match_score(a, b) for a, b in zip(df.iso_pct, df.aniso_pct)]
    head = datasets[(scales[0], None, "corrected")]
    base = cov.Convention()
    head_cov = cov.coverage(head, base, head_leds, rots)
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
        "rows": len(df),
    }
    return CoverageStudy(rig=rig, table=df, summary=summary, led_sets=led_sets, rot_sets=rot_sets,
                         headline=head, headline_leds=head_leds)


def write_coverage_report(study: CoverageStudy, out: Path, command: str | None = None) -> dict:
    """Write ``conventions.csv``, the plots, ``coverage.json`` (the summary with
    ``command``, the command line that made it) and ``coverage.md`` into the folder
    ``out``; return the JSON document."""
    out = Path(out)
    rig, head, head_leds = study.rig, study.headline, study.headline_leds
    study.table.to_csv(out / "conventions.csv", index=False, float_format="%.6g")
    base = cov.Convention()
    scale = study.summary["headline"]["scale"]
    cov.plot_theta_coverage(head, out / "theta_per_led.png", "between", head_leds,
                            title=f"{rig.name}: theta_in vs theta_out per LED (thesis fig. 7.2; normal between "
                                  f"camera and lamp)")
    cov.plot_theta_coverage(head, out / "theta_per_led_lit.png", "lit", rig.led_ids())
    cov.plot_rotation_coverage({f"{len(head_leds)} LEDs": (head, base, head_leds),
                                f"{len(rig.led_ids())} LEDs": (head, base, rig.led_ids())},
                               out / "aniso_by_rotation.png",
                               title=f"{rig.name}: anisotropic coverage by sample rotation (scale {scale:g})")
    doc = {**study.summary, "command": command}
    (out / "coverage.json").write_text(json.dumps(doc, indent=2, default=jsonable) + "\n")
    (out / "coverage.md").write_text(coverage_markdown(study.table, doc, study.led_sets, study.rot_sets))
    return doc


def jsonable(o):
    """``json.dumps`` ``default=``: numpy scalars as Python numbers."""
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
    iso = df.iloc[(df.iso_pct - 100 * cov.PRINTED["isotropic"]).abs().argsort().iloc[0]]
    an = df.iloc[(df.aniso_pct - 100 * cov.PRINTED["anisotropic"]).abs().argsort().iloc[0]]
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
    """``coverage.md``: the headline, the conventions and the tables of closest rows."""
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
