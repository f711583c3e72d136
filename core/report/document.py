"""The measurement report (issue 17): one self-contained HTML file and the same content as Markdown.

:func:`write_report` reads what a measurement folder holds - ``fit.json``, the samples
table, the capture folders, the calibrations, and whatever else exists (gloss units,
exports, renders of the fitted material, a twin capture's ``truth.json``) - and
writes ``OUT/report.html`` (every figure embedded as a base64 PNG ``data:`` URI, no
external file or network access needed) and ``OUT/report.md`` (figures as PNG files
in ``OUT/report_figures/``). A section whose input is absent says so ("not
computed", "not available: why") instead of failing; only a missing or unreadable
``fit.json`` or samples table stops it (:class:`~glossrig.core.errors.InputError`).

Sections: provenance (inputs with checksums, calibrations, versions); the capture
(LEDs, rotations, exposures, saturation); markers and poses on the calibration image
(:func:`glossrig.core.calibration.poses.draw_diagnostic`); HDR per LED (log10 tone map, colour
bar; :mod:`glossrig.core.report.figures`); BRDF-space coverage; incidence-plane slices
(thesis fig. 7.1) and a polar lobe plot; measured against fitted and residuals
(:mod:`glossrig.core.fitting.fit_plots`); the fitted parameters with their standard errors,
labelled **noise-only** as fit.json labels them (they exclude calibration and model
error); gloss units; renders (sphere and cloth, thesis figs. 6.2 and 7.4: made by
:func:`glossrig.twin.material_renders.render_material_views` and passed in as PNG
files, so ``glossrig.core`` stays free of Mitsuba); for twin captures the truth
beside the fit and the recovery table; the exports.

The HTML page carries a small script that, once the page has loaded, counts the
images that decoded (``img.complete && img.naturalWidth > 0``) and writes
``images loaded K/N`` into ``document.title`` and the body's ``data-images-loaded``
attribute, so a headless browser can check that every figure loads.
"""
from __future__ import annotations

import base64
import html
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Callable
from typing import Any

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.fitting.export import fit_from_doc
from glossrig.core.toml_input import read_json

FIGURES = "report_figures"
HTML_NAME = "report.html"
MD_NAME = "report.md"
PARAMS = ("rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation")
UNITS = {"rho_d": "", "rho_s": "", "alpha_x": "", "alpha_y": "", "lobe_rotation": "rad"}


# --------------------------------------------------------------------------- document model

@dataclass
class _Block:
    kind: str                      # h, p, note, table, fig, items, code
    data: Any                      # by kind: str, list of str, (header, rows), figure path
    extra: dict = field(default_factory=dict)


class _Doc:
    """A report as a list of blocks, rendered alike to HTML and Markdown."""

    def __init__(self, fig_dir: Path):
        self.blocks: list[_Block] = []
        self.fig_dir = fig_dir

    def h(self, level: int, text: str):
        self.blocks.append(_Block("h", text, {"level": level}))

    def p(self, text: str):
        self.blocks.append(_Block("p", text))

    def note(self, text: str):
        self.blocks.append(_Block("note", text))

    def items(self, rows: list[str]):
        if rows:
            self.blocks.append(_Block("items", list(rows)))

    def table(self, header: list[str], rows: list[list], caption: str | None = None):
        self.blocks.append(_Block("table", (header, [[_cell(c) for c in r] for r in rows]), {"caption": caption}))

    def fig(self, path: Path, caption: str, alt: str | None = None):
        """A PNG figure; one from elsewhere (a render, a diagnostic image) is copied
        into the figure folder so that the Markdown report's folder is complete."""
        import shutil

        path = Path(path)
        if path.resolve().parent != self.fig_dir.resolve():
            dest = self.fig_dir / f"input_{path.name}"
            shutil.copyfile(path, dest)
            path = dest
        self.blocks.append(_Block("fig", path, {"caption": caption, "alt": alt or caption}))

    def code(self, text: str):
        self.blocks.append(_Block("code", text))


def _cell(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        if not math.isfinite(v):
            return "-"
        return f"{v:.4g}"
    return str(v)


def _md_escape(s: str) -> str:
    return str(s).replace("|", "\\|").replace("\n", " ")


def _render_md(doc: _Doc, out_dir: Path) -> str:
    lines: list[str] = []
    for b in doc.blocks:
        if b.kind == "h":
            lines += ["#" * b.extra["level"] + " " + b.data, ""]
        elif b.kind == "p":
            lines += [b.data, ""]
        elif b.kind == "note":
            lines += [f"> {b.data}", ""]
        elif b.kind == "items":
            lines += [f"- {x}" for x in b.data] + [""]
        elif b.kind == "code":
            lines += ["```", b.data, "```", ""]
        elif b.kind == "table":
            head, rows = b.data
            if b.extra.get("caption"):
                lines += [f"*{b.extra['caption']}*", ""]
            lines.append("| " + " | ".join(_md_escape(h) for h in head) + " |")
            lines.append("|" + "---|" * len(head))
            for r in rows:
                lines.append("| " + " | ".join(_md_escape(c) for c in r) + " |")
            lines.append("")
        elif b.kind == "fig":
            rel = os.path.relpath(b.data, out_dir).replace(os.sep, "/")
            lines += [f"![{_md_escape(b.extra['alt'])}]({rel})", "", f"*{b.extra['caption']}*", ""]
    return "\n".join(lines).rstrip() + "\n"


_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;max-width:1400px;margin:0 auto;
padding:0 24px 48px;color:#1b1b1b;line-height:1.45}
h1{border-bottom:2px solid #444;padding-bottom:4px}h2{border-bottom:1px solid #bbb;margin-top:2em}
table{border-collapse:collapse;margin:8px 0 16px;font-size:14px}
th,td{border:1px solid #ccc;padding:3px 8px;text-align:left;vertical-align:top}
th{background:#f0f0f0}td{font-variant-numeric:tabular-nums}
figure{margin:12px 0 24px}figure img{max-width:100%;height:auto;border:1px solid #ddd}
figcaption{font-size:14px;color:#333;margin-top:4px}
.note{background:#fff7e0;border-left:4px solid #e0a800;padding:6px 10px}
.caption{font-style:italic;font-size:14px}code,pre{background:#f5f5f5}pre{padding:8px;overflow-x:auto}
nav ul{columns:3;font-size:14px}
"""

_SCRIPT = """
window.addEventListener('load', function () {
  var imgs = document.images, ok = 0;
  for (var i = 0; i < imgs.length; i++) { if (imgs[i].complete && imgs[i].naturalWidth > 0) { ok++; } }
  var s = 'images loaded ' + ok + '/' + imgs.length;
  document.body.setAttribute('data-images-loaded', ok + '/' + imgs.length);
  document.title = s + ' | ' + document.title;
});
"""


def _png_size(data: bytes) -> tuple[int, int]:
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise InputError("not a PNG file")
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def _render_html(doc: _Doc, title: str) -> str:
    e = html.escape
    body: list[str] = []
    toc = [b for b in doc.blocks if b.kind == "h" and b.extra["level"] == 2]
    n_h2 = 0
    for b in doc.blocks:
        if b.kind == "h":
            lvl = b.extra["level"]
            if lvl == 2:
                n_h2 += 1
                body.append(f'<h2 id="s{n_h2}">{e(b.data)}</h2>')
            else:
                body.append(f"<h{lvl}>{e(b.data)}</h{lvl}>")
            if lvl == 1 and toc:
                body.append("<nav><ul>" + "".join(f'<li><a href="#s{i + 1}">{e(t.data)}</a></li>'
                                                   for i, t in enumerate(toc)) + "</ul></nav>")
        elif b.kind == "p":
            body.append(f"<p>{e(b.data)}</p>")
        elif b.kind == "note":
            body.append(f'<p class="note">{e(b.data)}</p>')
        elif b.kind == "items":
            body.append("<ul>" + "".join(f"<li>{e(x)}</li>" for x in b.data) + "</ul>")
        elif b.kind == "code":
            body.append(f"<pre>{e(b.data)}</pre>")
        elif b.kind == "table":
            head, rows = b.data
            cap = f"<caption class=\"caption\">{e(b.extra['caption'])}</caption>" if b.extra.get("caption") else ""
            body.append(f"<table>{cap}<thead><tr>" + "".join(f"<th>{e(h)}</th>" for h in head) + "</tr></thead><tbody>"
                        + "".join("<tr>" + "".join(f"<td>{e(c)}</td>" for c in r) + "</tr>" for r in rows)
                        + "</tbody></table>")
        elif b.kind == "fig":
            data = Path(b.data).read_bytes()
            w, h = _png_size(data)
            uri = "data:image/png;base64," + base64.b64encode(data).decode("ascii")
            body.append(f'<figure><img src="{uri}" alt="{e(b.extra["alt"])}" width="{w}" height="{h}">'
                        f"<figcaption>{e(b.extra['caption'])}</figcaption></figure>")
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\"><title>{e(title)}</title>"
            f"<style>{_CSS}</style><script>{_SCRIPT}</script></head>\n<body>\n" + "\n".join(body)
            + "\n</body></html>\n")


# --------------------------------------------------------------------------- inputs

def _load_json(x, what: str) -> dict | None:
    if x is None:
        return None
    if isinstance(x, dict):
        return x
    return read_json(x, what)


def _short(sha: str | None) -> str:
    return "-" if not sha else sha[:16]


def _describe(path) -> dict | None:
    from glossrig.core.provenance import describe_input

    if path is None:
        return None
    try:
        return describe_input(path)
    except InputError as e:
        return {"path": str(path), "error": str(e)}


def _truth(sample_dir) -> dict | None:
    if sample_dir is None:
        return None
    from glossrig.core.capture import TRUTH, read_truth

    p = Path(sample_dir) / TRUTH
    if not p.is_file():
        return None
    try:
        return read_truth(p)
    except InputError:
        return None


def _truth_ward(truth: dict | None):
    from glossrig.core.models.ward import WardParams

    m = (truth or {}).get("material") or {}
    if m.get("kind") == "ward" and isinstance(m.get("ward"), dict):
        try:
            return WardParams(**{k: float(m["ward"][k]) for k in PARAMS})
        except (KeyError, TypeError, InputError):
            return None
    return None


def _flatten(d, prefix: str = "") -> list[tuple[str, object]]:
    out = []
    if isinstance(d, dict):
        for k, v in d.items():
            out += _flatten(v, f"{prefix}.{k}" if prefix else str(k))
    elif isinstance(d, (list, tuple)) and d and all(isinstance(x, (int, float)) for x in d):
        out.append((prefix, ", ".join(_cell(float(x)) for x in d)))
    else:
        out.append((prefix, d))
    return out


# --------------------------------------------------------------------------- sections

def _provenance_section(doc: _Doc, fit: dict, samples_prov: dict | None, inputs: dict, log):
    from glossrig.core.checkpoint import glossrig_version
    from glossrig.core.provenance import source_revision

    doc.h(2, "Provenance")
    src = source_revision()
    doc.p(f"Report written by glossrig {glossrig_version()}"
          + (f", source commit {src['commit']}{' (modified)' if src.get('dirty') else ''}" if src else "")
          + ". Checksums are sha256 (first 16 hex digits shown); a capture folder is identified by its "
            "capture.json, which records the sha256 of every raw file.")
    rows = []
    for name, d in inputs.items():
        if d is None:
            continue
        if "error" in d:
            rows.append([name, d["path"], f"not available: {d['error']}"])
        else:
            rows.append([name, d["path"] + (f" ({d['file']})" if d.get("file") else ""), _short(d.get("sha256"))])
    doc.table(["input", "path", "sha256"], rows, "Inputs of this report, hashed now")
    chain = []
    fp = fit.get("provenance") or {}
    for who, prov in (("fit.json", fp), ("samples table", samples_prov or {})):
        if not prov:
            chain.append([who, "-", "not recorded", "-"])
            continue
        ver = prov.get("glossrig_version", "?")
        s = prov.get("source") or {}
        ver += f" @ {s['commit'][:10]}" if s.get("commit") else ""
        ver += " (modified)" if s.get("dirty") else ""
        for k, v in (prov.get("inputs") or {}).items():
            if isinstance(v, dict):
                chain.append([f"{who} ({prov.get('tool', '?')}, glossrig {ver})", k, v.get("path", "-"),
                              _short(v.get("sha256"))])
    doc.table(["recorded by", "input", "path", "sha256"], chain, "Inputs recorded by the steps that made the "
              "samples table and the fit")
    opts = []
    for who, prov in (("extract", samples_prov or {}), ("fit", fp)):
        for k, v in _flatten(prov.get("options") or {}):
            opts.append([who, k, v])
    if opts:
        doc.table(["step", "option", "value"], opts, "Options recorded with the samples table and the fit")


def _calibration_section(doc: _Doc, camera: dict | None, lamps: dict | None):
    doc.h(3, "Calibrations")
    if camera:
        d = camera.get("distortion") or []
        doc.table(["quantity", "value"], [
            ["fx, fy (px)", f"{_cell(camera.get('fx'))}, {_cell(camera.get('fy'))}"],
            ["cx, cy (px)", f"{_cell(camera.get('cx'))}, {_cell(camera.get('cy'))}"],
            ["distortion (k1 k2 p1 p2 k3)", ", ".join(_cell(float(x)) for x in d)],
            ["image size (px)", " x ".join(str(x) for x in camera.get("image_size") or [])],
            ["reprojection RMS (px)", camera.get("reprojection_rms_px")],
            ["views", len(camera["views"]) if isinstance(camera.get("views"), list) else camera.get("views", "-")],
        ], "Camera intrinsics (glossrig calibrate camera, OpenCV)")
    else:
        doc.note("Camera calibration: not given.")
    if lamps and isinstance(lamps.get("lamps_mm"), dict):
        spread = lamps.get("spread_mm") or {}
        rows = [[k, ", ".join(f"{float(x):.2f}" for x in v), spread.get(k)]
                for k, v in sorted(lamps["lamps_mm"].items(), key=lambda kv: int(kv[0]) if kv[0].isdigit() else kv[0])]
        doc.table(["LED", "position (x, y, z) mm, holder frame", "spread (mm)"], rows,
                  "Lamp positions (glossrig calibrate lamps, thesis 4.3.4)")
    else:
        doc.note("Lamp calibration: not given.")


def _capture_section(doc: _Doc, name: str, folder):
    from glossrig.core.capture import load_manifest

    if folder is None:
        doc.note(f"{name}: not given.")
        return
    try:
        man = load_manifest(folder)
    except InputError as e:
        doc.note(f"{name}: not available ({e}).")
        return
    seq = man.select("sequence")
    leds = sorted({i for im in seq for i in im.leds})
    exps = sorted({im.exposure_s for im in seq})
    reps = sorted({im.repeat for im in seq})
    isos = sorted({im.iso for im in seq})
    aps = sorted({im.aperture for im in seq})
    twin = man.meta.get("twin")
    rows: list[list] = [["folder", str(folder)], ["material label", man.material],
                        ["rig", f"{man.meta.get('rig_name', '-')} ({man.rig})"], ["complete", man.complete],
                        ["images", f"{len(man.images)} ({len(seq)} sequence, {len(man.select('calibration'))} calibration, "
                                   f"{len(man.select('checkerboard'))} checkerboard)"],
                        ["rotations (deg)", ", ".join(f"{r:g}" for r in man.rotations()) or "-"],
                        ["LEDs", ", ".join(str(i) for i in leds) or "-"],
                        ["exposures (s)", (f"{len(exps)}: " + ", ".join(f"{t:g}" for t in exps)) if exps else "-"],
                        ["repeats", len(reps)], ["ISO", ", ".join(str(i) for i in isos) or "-"],
                        ["f-number", ", ".join(f"{a:g}" for a in aps) or "-"]]
    if man.meta.get("backends"):
        rows.append(["backends", ", ".join(f"{k}: {v}" for k, v in man.meta["backends"].items())])
    if isinstance(twin, dict):
        rows.append(["twin", ", ".join(f"{k}={v}" for k, v in twin.items())])
    doc.table(["field", "value"], rows, f"{name} capture (capture.json)")


def _hdr_section(doc: _Doc, sample_dir, fig_dir: Path, enabled: bool, log):
    from glossrig.core.report.figures import hdr_per_led, plot_hdr_per_led

    doc.h(2, "HDR per LED")
    if not enabled:
        doc.note("HDR images: not computed (switched off).")
        return
    if sample_dir is None:
        doc.note("HDR images: not computed (no sample capture given).")
        return
    try:
        hdrs = hdr_per_led(sample_dir, log=log)
        png = plot_hdr_per_led(hdrs, fig_dir / "hdr_per_led.png")
    except InputError as e:
        doc.note(f"HDR images: not available ({e}).")
        return
    doc.p("Tone map: the colour is log10 of the HDR rate - the mean of the 2x2 Bayer block's four pixels, "
          "(R + 2G + B)/4 in camera RGB, not white-balanced, in fractions of the sensor's white-black range per "
          "second of exposure - on one colour scale shared by all LEDs (0.5th to 99.9th percentile of the valid "
          "rates, at most 5 decades). HDR as the extraction computes it: repeats averaged (thesis eq. 4.31), LED "
          "jitter corrected (eq. 4.32-4.38), maximum-likelihood rate of glossrig.core.radiometry.hdr.hdr_ml; no patch "
          "normalisation.")
    doc.fig(png, f"HDR image of every LED at rotation {hdrs[0].rotation:g} deg (log10 tone map, colour bar in "
                 "fractions of the white-black range per second; black: too dark or invalid; magenta: saturated "
                 "even at the shortest exposure).", "HDR per LED")
    rows = []
    for h in hdrs:
        n = max(1, sum(h.status_counts.values()))
        valid = next((v for k, v in h.status_counts.items() if k == "valid"), 0)
        bright = sum(v for k, v in h.status_counts.items() if k.startswith("too bright"))
        dark = sum(v for k, v in h.status_counts.items() if k.startswith("too dark"))
        rows.append([h.led, f"{h.rotation:g}", h.files, f"{min(h.exposures_s):g} .. {max(h.exposures_s):g}",
                     h.repeats, f"{100 * h.saturated_at_shortest:.3f}", f"{100 * h.saturated_at_longest:.1f}",
                     f"{100 * valid / n:.1f}", f"{100 * bright / n:.3f}", f"{100 * dark / n:.1f}"])
    doc.table(["LED", "rotation (deg)", "images", "exposures (s)", "repeats", "saturated at shortest (% px)",
               "saturated at longest (% px)", "HDR valid (% px)", "too bright (% px)", "too dark (% px)"], rows,
              "Saturation per LED: pixels at the white level in the shortest and the longest exposure, and the "
              "HDR status of every pixel (too bright: saturated even at the shortest exposure)")


def _poses_section(doc: _Doc, sample_dir, camera_json, poses_image, fig_dir: Path, log):
    doc.h(2, "Markers and poses")
    if poses_image is not None and Path(poses_image).is_file():
        doc.fig(Path(poses_image), "Detected markers (green outlines, numbered corners), model edges reprojected "
                                   "with the solved poses (magenta) and pose axes on the calibration image.",
                "markers and poses")
        return
    if sample_dir is None or camera_json is None:
        doc.note("Markers and poses: not drawn (needs the sample capture and camera.json).")
        return
    from glossrig.core.calibration.poses import calibrate_capture
    from glossrig.core.capture import load_manifest

    png = fig_dir / "poses.png"
    try:
        # the figure shows the first calibration image: solve that one only (without a rotation
        # calibrate_capture solves every rotation's image and draws the first)
        first = load_manifest(sample_dir).select("calibration")[:1]
        if log:
            log("solving the poses on the calibration image")
        res = calibrate_capture(sample_dir, camera_json, rotation=float(first[0].rotation) if first else None,
                                diagnostic=png)
    except InputError as e:
        doc.note(f"Markers and poses: not available ({e}).")
        return
    doc.fig(png, f"Calibration image {res['file']} (rotation {res['rotation']:g} deg): detected markers (green "
                 "outlines, numbered corners P1..P4), model edges reprojected with the solved poses (magenta), "
                 "holder and cylinder axes (x red, y green, z blue); below, zoomed crops of every marker "
                 "(thesis 4.3.2).", "markers and poses")
    rows = []
    for k in ("holder", "cylinder"):
        r = res.get(k) or {}
        rows.append([k, r.get("reprojection_rms_px"), ", ".join(f"{float(x):.2f}" for x in np.ravel(r.get("t_mm", [])))])
    doc.table(["marker set", "corner reprojection RMS (px)", "translation (mm, camera frame)"], rows,
              "Poses (corner PnP, then edge refinement)")


def _fit_section(doc: _Doc, fit: dict):
    from glossrig.core.fitting.fit import STDERR_KIND

    doc.h(2, "Fitted parameters")
    chans = [c for c in ("luminance", "r", "g", "b") if isinstance(fit.get(c), dict)]
    kinds = {fit[c].get("stderr_kind") for c in chans} - {None}
    kind = "; ".join(sorted(kinds)) or STDERR_KIND
    doc.p(f"Model: {fit.get('model', 'extended Ward (thesis eq. 4.79-4.80)')}; canonical form "
          f"{fit.get('canonical_form', '-')}; angles in radians. Values are given as value +- standard error.")
    doc.note(f"Standard errors are {kind}: they are not the measurement's uncertainty.")
    rows = []
    for c in chans:
        d = fit[c]
        row = [c]
        for k in PARAMS:
            v, s = d.get(k), d.get(f"{k}_stderr")
            row.append("-" if v is None else (f"{v:.4g} +- {s:.2g}" if s is not None else f"{v:.4g} +- (undetermined)"))
        row.append(d.get("n_samples"))
        rows.append(row)
    doc.table(["channel", "rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation (rad)", "samples"], rows,
              f"Fitted parameters, standard errors {kind}")
    _budget_section(doc, fit, chans)
    res_rows = []
    for c in chans:
        r = fit[c].get("residuals") or {}
        res_rows.append([c, r.get("rmse"), r.get("rms_relative"), r.get("median_abs_relative"),
                         r.get("r_squared_weighted"), r.get("chi2_per_dof"), r.get("n_clipped"),
                         ", ".join(fit[c].get("at_bound") or []) or "-", fit[c].get("converged")])
    doc.table(["channel", "RMSE (1/sr)", "RMS relative", "median |relative|", "weighted R^2", "chi^2 / dof",
               "clipped", "at bound", "converged"], res_rows, "Residual statistics (measured minus fitted)")
    sh = fit.get("shared_lobe_rgb")
    if isinstance(sh, dict):
        doc.table(["", "r", "g", "b"], [["rho_d", *sh.get("rho_d", [None] * 3)], ["rho_s", *sh.get("rho_s", [None] * 3)]],
                  f"RGB albedos for the shared lobe of the {sh.get('lobe_from', 'luminance')} fit (what a renderer "
                  f"with one lobe takes: alpha_x {_cell(sh.get('alpha_x'))}, alpha_y {_cell(sh.get('alpha_y'))}, "
                  f"rotation {_cell(sh.get('lobe_rotation'))} rad)")


def _budget_section(doc: _Doc, fit: dict, chans: list[str]):
    """The uncertainty budget (GUM) of each channel as fit.json holds it
    (:mod:`glossrig.core.fitting.uncertainty`): per parameter its components, the
    combined standard uncertainty and the 95 % interval; what the budget omits."""
    rows: list[list] = []
    omitted: set[str] = set()
    for c in chans:
        unc = fit[c].get("uncertainty")
        if not isinstance(unc, dict):
            continue
        for k in PARAMS:
            e = unc.get(k) or {}
            comp = e.get("components") or {}
            iv = e.get("interval95")
            rows.append([c, k, e.get("value"), comp.get("noise"), comp.get("model"), comp.get("footprint"),
                         comp.get("calibration"), e.get("combined"), e.get("coverage_factor"),
                         "-" if iv is None else f"[{iv[0]:.4g}, {iv[1]:.4g}]"])
        omitted.update(f"{k}: {v}" for k, v in ((unc.get("budget") or {}).get("omitted") or {}).items())
    if not rows:
        doc.note("Uncertainty budget: not in this fit.json (written before the budget existed).")
        return
    doc.table(["channel", "parameter", "value", "noise", "model", "footprint", "calibration", "combined u", "k",
               "95 % interval"], rows,
              "Uncertainty budget (GUM): standard uncertainties in each parameter's unit (lobe_rotation in radians), "
              "combined = root sum of squares, 95 % interval = value +- k combined (Student t, Welch-Satterthwaite); "
              "this, not the noise-only standard error above, is the measurement's uncertainty")
    doc.items(sorted(f"omitted - {o}" for o in omitted))


def _gloss_section(doc: _Doc, gloss: dict | None):
    doc.h(2, "Gloss units")
    if not gloss:
        doc.note("Gloss units: not computed.")
        return
    caption = ("Gloss as the coatings and print industry measures it (ISO 2813 / ASTM D523 specular gloss in GU; "
               "haze and distinctness of image, ASTM E430 / ISO 13803), computed from the fitted BRDF")
    spread = gloss.get("spread") if isinstance(gloss.get("spread"), dict) else None
    if spread:
        # one row per quantity: the central value, its spread over the candidate models, and
        # whether it lies outside the angles the rig measures (core.gloss)
        models = sorted({m for v in spread.values() if isinstance(v, dict) for m in (v.get("models") or {})})
        rows = []
        for q, v in spread.items():
            if not isinstance(v, dict):
                continue
            ms = v.get("models") or {}
            rows.append([q, v.get("value"), v.get("min"), v.get("max"), "yes" if v.get("extrapolated") else "no",
                         *[ms.get(m) for m in models]])
        doc.table(["quantity", "value", "min", "max", "extrapolated", *models], rows,
                  caption + "; min and max span the candidate models, whose own values follow")
    else:
        rows = [[k, v] for k, v in _flatten({k: v for k, v in gloss.items() if k not in ("assumptions", "detail")})]
        doc.table(["quantity", "value"], rows, caption)
    if isinstance(gloss.get("assumptions"), str):
        doc.p("Assumptions: " + gloss["assumptions"])


def _renders_section(doc: _Doc, renders: dict):
    doc.h(2, "Renders of the fitted material")
    shown = 0
    captions = {"sphere": "A sphere of the fitted material lit by a studio environment map (cf. thesis fig. 6.2); "
                          "the lobe's x axis runs around the vertical pole axis.",
                "cloth": "A draped cloth of the fitted material, the weave (the lobe's x axis at lobe_rotation = 0) "
                         "along the image's horizontal, lit by the same environment (cf. thesis fig. 7.4)."}
    for name, p in (renders or {}).items():
        p = Path(p)
        if p.is_file():
            doc.fig(p, captions.get(name, f"Render: {name}."), f"render {name}")
            shown += 1
        else:
            doc.note(f"Render {name}: file missing ({p}).")
    if not shown:
        doc.note("Renders: not rendered (glossrig.twin.material_renders.render_material_views makes them with "
                 "Mitsuba 3).")
    else:
        doc.p("Renders: Mitsuba 3 path tracing through the project's glossrig_ward BSDF with the shared-lobe RGB "
              "albedos of fit.json; a procedural environment (sky gradient, grey floor, three softboxes); fixed "
              "exposure, sRGB, clipped at white.")


def _truth_section(doc: _Doc, fit: dict, truth: dict | None, recovery: dict | None):
    from glossrig.core.fitting.fit import parameter_errors

    doc.h(2, "Truth and fit (twin captures)")
    tw = _truth_ward(truth)
    if truth is None and not recovery:
        doc.note("Truth: not available (not a twin capture: no truth.json in the sample folder).")
        return
    if truth is not None and tw is None:
        m = truth.get("material") or {}
        doc.note(f"Truth: the simulated material {m.get('label', m.get('kind', '?'))} is not an extended-Ward "
                 "material, so there is no parameter truth to compare.")
    if tw is not None and isinstance(fit.get("luminance"), dict):
        lum = fit["luminance"]
        err = parameter_errors({k: lum[k] for k in PARAMS}, tw)
        rows = []
        for k in PARAMS:
            s = lum.get(f"{k}_stderr")
            e = err["lobe_rotation_deg"] if k == "lobe_rotation" else err[k]
            rows.append([k, getattr(tw, k), lum[k], "-" if s is None else f"{s:.2g}",
                         f"{e:.3f} deg" if k == "lobe_rotation" else f"{100 * e:+.2f} %"])
        doc.table(["parameter", "truth", "fitted (luminance)", "std. error (noise-only)", "error"], rows,
                  "Truth recorded by the twin (truth.json) beside the luminance fit; errors relative except the "
                  "rotation (degrees, modulo 180), both in canonical form")
    if recovery:
        # the calibrations against the twin's truth (recovery.json, core.recovery); the material's
        # truth against the fit is the table above
        rows = []
        i = recovery.get("intrinsics") or {}
        if i:
            rows += [["focal length fx", f"{i['fx_error_percent']:+.3f} %"],
                     ["focal length fy", f"{i['fy_error_percent']:+.3f} %"],
                     ["principal point", f"({i['cx_error_px']:+.2f}, {i['cy_error_px']:+.2f}) px"]]
        lp = recovery.get("lamps") or {}
        for led, e in sorted((lp.get("error_mm") or {}).items(), key=lambda kv: int(kv[0])):
            rows.append([f"LED {led} position", f"{e:.2f} mm"])
        if rows:
            doc.table(["calibrated quantity", "error against the twin's truth"], rows,
                      "Recovery of the calibrations used by this measurement (recovery.json)")


def _exports_section(doc: _Doc, exports: list, out_dir: Path):
    from glossrig.core.capture import sha256_file

    doc.h(2, "Exports")
    rows = []
    for p in exports or []:
        p = Path(p)
        if p.is_file():
            rows.append([os.path.relpath(p, out_dir).replace(os.sep, "/"), f"{p.stat().st_size:,}",
                         _short(sha256_file(p))])
        else:
            rows.append([str(p), "missing", "-"])
    if rows:
        doc.table(["file", "bytes", "sha256"], rows, "Files written for other tools")
    else:
        doc.note("Exports: not written.")


# --------------------------------------------------------------------------- entry point

def write_report(out_dir, *, fit_json, samples, sample_dir=None, reference_dir=None, camera_json=None,
                 lamps_json=None, renders: dict | None = None, recovery: dict | None = None,
                 gloss: dict | None = None, exports: list | None = None, poses_image=None, hdr: bool = True,
                 title: str | None = None, log: Callable[[str], None] | None = None) -> tuple[Path, Path]:
    """Write ``out_dir/report.html`` (self-contained) and ``out_dir/report.md`` (figures
    in ``out_dir/report_figures/``); returns their paths.

    ``fit_json``: path of fit.json or its dict. ``samples``: path of samples.parquet
    or the table (a DataFrame; its ``attrs["provenance"]`` is used when present).
    ``sample_dir``, ``reference_dir``: capture folders (HDR images, markers and poses,
    capture tables, truth.json). ``camera_json``, ``lamps_json``: calibration files.
    ``renders``: name -> PNG (``{"sphere": .., "cloth": ..}`` from
    :func:`glossrig.twin.material_renders.render_material_views`). ``recovery``: the
    demo's recovery table. ``gloss``: the gloss units (default: ``fit.json["luminance"]
    ["gloss"]`` when present). ``exports``: files to list. ``poses_image``: a
    diagnostic image already drawn (``calibrate geometry --diagnostic``); otherwise it
    is drawn here when the sample capture and camera.json are given. ``hdr=False``
    skips the HDR images (reading every raw file of the sample capture)."""
    from glossrig.core.fitting import fit_plots
    from glossrig.core.atomic import atomic_write_bytes
    from glossrig.core.report.figures import plot_coverage, coverage_stats, plot_incidence_slices, plot_polar_lobe
    from glossrig.core.samples import read_samples

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError("report folder is a file", path=out)
    out.mkdir(parents=True, exist_ok=True)
    figs = out / FIGURES
    figs.mkdir(exist_ok=True)
    fit = _load_json(fit_json, "fit.json")
    if not isinstance(fit, dict) or not any(isinstance(fit.get(c), dict) for c in ("luminance", "r", "g", "b")):
        raise InputError("fit.json holds no fitted channel", path=None if isinstance(fit_json, dict) else fit_json)
    samples_path = None
    if isinstance(samples, (str, os.PathLike)):
        samples_path = Path(samples)
        df = read_samples(samples_path)
    else:
        df = samples
    samples_prov = df.attrs.get("provenance") if hasattr(df, "attrs") else None
    if samples_prov is None:
        samples_prov = (((fit.get("provenance") or {}).get("inputs") or {}).get("samples") or {}).get("provenance")
    camera = _load_json(camera_json, "camera calibration") if camera_json is not None else None
    lamps = _load_json(lamps_json, "lamp calibration") if lamps_json is not None else None
    truth = _truth(sample_dir)
    tw = _truth_ward(truth)
    if gloss is None and isinstance(fit.get("luminance"), dict):
        gloss = fit["luminance"].get("gloss")
    channel = "luminance" if isinstance(fit.get("luminance"), dict) else next(
        c for c in ("r", "g", "b") if isinstance(fit.get(c), dict))
    fits = fit_from_doc(fit).fits            # the one fit.json reader (core.export)
    if channel not in fits:
        raise InputError(f"fit.json has no {channel!r} fit")
    wfit = fits[channel]
    material = None
    if sample_dir is not None:
        try:
            from glossrig.core.capture import load_manifest

            material = load_manifest(sample_dir).material
        except InputError:
            material = None
    title = title or f"glossrig measurement report: {material or (fit.get('source') or 'material')}"

    doc = _Doc(figs)
    doc.h(1, title)
    p = wfit.params
    doc.p(f"Fitted {channel}: rho_d = {p.rho_d:.4g}, rho_s = {p.rho_s:.4g}, alpha_x = {p.alpha_x:.4g}, "
          f"alpha_y = {p.alpha_y:.4g}, lobe_rotation = {p.lobe_rotation:.4g} rad "
          f"({math.degrees(p.lobe_rotation):.1f} deg), from {len(df)} BRDF samples.")

    inputs = {"fit.json": None if isinstance(fit_json, dict) else _describe(fit_json),
              "samples": _describe(samples_path) if samples_path else None,
              "sample capture": _describe(sample_dir), "reference capture": _describe(reference_dir),
              "camera.json": None if isinstance(camera_json, dict) else _describe(camera_json),
              "lamps.json": None if isinstance(lamps_json, dict) else _describe(lamps_json)}
    _provenance_section(doc, fit, samples_prov, inputs, log)
    _calibration_section(doc, camera, lamps)

    doc.h(2, "The capture")
    _capture_section(doc, "Sample", sample_dir)
    _capture_section(doc, "Reference", reference_dir)
    _poses_section(doc, sample_dir, None if isinstance(camera_json, dict) else camera_json, poses_image, figs, log)
    _hdr_section(doc, sample_dir, figs, hdr, log)

    doc.h(2, "BRDF-space coverage")
    st = coverage_stats(df)
    doc.fig(plot_coverage(df, figs / "coverage.png"),
            "Every sample (up to 6000 per LED drawn) in the half/difference angles (left) and the incident/outgoing "
            "zenith angles (right), coloured by LED.", "coverage")
    doc.table(["quantity", "value"], [
        ["samples", st["n_samples"]], ["LEDs", ", ".join(map(str, st["leds"]))],
        ["rotations (deg)", ", ".join(f"{r:g}" for r in st["rotations"])],
        ["largest theta_h / theta_d (deg)", f"{st['theta_h_max_deg']:.1f} / {st['theta_d_max_deg']:.1f}"],
        ["isotropic coverage (1-degree bins)", f"{100 * st['isotropic']:.3g} % ({st['isotropic_bins']} bins)"],
        ["anisotropic coverage (1-degree bins)", f"{100 * st['anisotropic']:.3g} % ({st['anisotropic_bins']} bins)"],
        ["convention", st["convention"]]], "Coverage of the BRDF space (thesis 7.1.3)")

    doc.h(2, "Slices and lobe")
    doc.fig(plot_incidence_slices(df, wfit, figs / "incidence_slices.png", truth=tw),
            f"{channel} BRDF against the outgoing zenith in the plane of incidence at fixed incident zenith (cf. "
            "thesis fig. 7.1): measured samples near the plane (grey), the fitted model at the bin's centre "
            "theta_in and mean phi_in (red)" + (", the twin's truth (blue, dashed)" if tw else "") + ".",
            "incidence-plane slices")
    doc.fig(plot_polar_lobe(wfit, figs / "polar_lobe.png", truth=tw),
            "The fitted lobe in polar form in the planes of incidence holding the lobe's two principal axes; radius "
            "log10 BRDF (1/sr).", "polar lobe")
    doc.fig(fit_plots.plot_lobe_slices(df, wfit, figs / "lobe_slices.png"),
            "Measured and fitted BRDF against the signed half angle along the fitted lobe's principal axes "
            "(eq. 4.79-4.80).", "lobe slices")
    doc.fig(fit_plots.plot_rig_slices(df, wfit, figs / "rig_slices.png"),
            "Measured (dots) and fitted (lines) BRDF along the sample's central pixel column, per rotation and "
            "LED: the rig's own slices through the lobe.", "rig slices")

    doc.h(2, "Measured against fitted")
    doc.fig(fit_plots.plot_measured_vs_fitted(df, wfit, figs / "measured_vs_fitted.png"),
            "Density of measured against fitted values (log-log); red: identity.", "measured vs fitted")
    doc.fig(fit_plots.plot_residuals(df, wfit, figs / "residuals.png"),
            "Relative residuals against theta_h and phi_h (grey density; red: binned median and quartiles): "
            "structure here is what the model misses.", "residuals")
    _fit_section(doc, fit)
    _gloss_section(doc, gloss)
    _renders_section(doc, renders or {})
    _truth_section(doc, fit, truth, recovery)
    _exports_section(doc, list(exports or []), out)

    html_path, md_path = out / HTML_NAME, out / MD_NAME
    atomic_write_bytes(md_path, _render_md(doc, out).encode())
    atomic_write_bytes(html_path, _render_html(doc, title).encode())
    if log:
        log(f"wrote {html_path} and {md_path}")
    return html_path, md_path
