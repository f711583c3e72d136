"""The cylinder's silhouette as a witness of the sample radius (issue 14, items 3 and 5).

Why. The pipeline casts every pixel's ray onto a cylinder of the rig file's radius (thesis
4.3.2, eq. 4.26-4.30); a wrapped sample thicker or thinner than that (paper and sample
thickness, thesis 4.1.4; the catalogue's ``sample_radius_error``) puts every pixel on another
point with another normal. In BRDF space that is a smooth change of the angles which a real
material's own departure from its model can take up: on the blind study's satin_rosaline
captures without any radius error the material misfit gives the BRDF-space radius a held-out
chi^2 gain of 16-41 % at 0.3-0.6 mm, and a hidden 0.50 mm is read as 0.54 mm with the same kind
of gain (validation/diagnose/blind_study.md).

The signature no material produces. The sample's outline in the image is where its rays graze
the cylinder: a ray whose closest distance to the axis equals the radius. So each image column
that crosses the sample measures the radius directly: find the sub-pixel row of the limb (the
edge between the lit sample and the dark box behind it) and the distance from the cylinder axis
(the calibrated poses) of the ray through it. At scale 0.25 on the thesis rig one pixel at the
limb is 0.15 mm of radius, so a 0.5 mm error moves the limb by about 3.4 pixels, and the few
hundred columns of a limb measure it far below a pixel.

Measurement (:func:`limb_rates`, :func:`silhouette_evidence`). Each LED's exposure sequence is
combined (the pipeline's own HDR, :func:`glossrig.core.extraction.extract.led_rate`) over a box
around the sample; per column, the limb is the outer end of the run of valid rates on the cylinder
(at least RUN rows, the rows beyond it dark: no rate, or below DARK of the sample's). The edge is
placed by the coverage of the partial pixels: each row's rate over the sample's rate extrapolated
from the next rows inside of the same colour (a line through RUN_REF rows of each colour of the
Bayer mosaic), summed - the integral of a blurred step is its position, whatever the blur. A limb
counts only under an LED that lights it well (cos theta_in >= COS_MIN at the limb point): near a
limb the LED grazes, the radiance falls steeply towards the terminator and the coverage reads the
edge too far in (measured on the blind study's satin capture: under an LED at cos theta_in = 0.23
the radius came out 0.14 mm short, at 0.63 within 0.02 mm); an unlit limb shows the terminator, not
the outline. Each (rotation, LED, limb) is cut into two halves of its columns; each half's
estimate is the median of its columns' radius errors, with the median's standard error from their
spread (a half whose columns scatter beyond EDGE_PX is no clean outline - a shadow or a highlight
edge crossing it - and is left out, ``left_out``; measured: an LED moved by 4.6 mm put one half-limb
at -5.2 +- 0.48 mm beside seven at +0.02) combined with EDGE_PX, the edge's model error (the coverage's colour extrapolation and the
grazing radiance left in the partial pixels; on the twin's blind-study captures the limbs read
0.287, 0.496 and 0.216 mm as 0.281, 0.512 and 0.223 mm and two null captures as -0.005 and +0.018 mm:
errors up to 0.12 px). EDGE_PX is systematic - the same edge model at every limb - so the pooled
estimate's standard error keeps it whole rather than averaging it down.

Test. Held out over the units (leave one out: dr from the others predicts it; the gain of its
chi^2 over dr = 0); significant when the pooled estimate lies beyond SIL_Z standard errors of 0, the
pooled held-out gain exceeds GAIN_THRESHOLD, the folds agree
(:func:`glossrig.core.diagnose.catalogue.consistent_folds`) and no unit lies beyond AGREE_Z combined
standard errors from the others (limbs that disagree are a pose error or a sample that is not a
cylinder of one radius, not a radius error). The two limbs of a column move apart with the radius
and together with an error of the cylinder's pose across the image, so where both limbs are lit
their mean measures the radius free of that pose error; where only one is lit (LEDs 6 and 9 of the
thesis rig light only the lower limb well) the pose's error across the image enters whole - the
calibrated poses put the cylinder's axis within a small fraction of a pixel on the twin.

Use (:func:`apply_silhouette_evidence`): a significant silhouette names the BRDF-space
``sample_radius_error`` with its dr (:func:`glossrig.core.diagnose.witness.take_witness_test`,
``direct``: the outline is the sample's own surface, so the rows' test with the radius held at dr -
the lobe re-evaluated at the moved points, scored as the BRDF-space fit is - is recorded as
``fixed_brdf_gain`` but not required); a
silhouette that measures dr consistent with 0 refutes a BRDF-space radius more than BOUND_Z
combined standard errors away. Assumptions, stated: the box behind the sample is dark (no valid
rate there, as in the thesis's black-lined box); the limbs lie along the image's columns or rows
(the cylinder's axis within 45 degrees of one image axis).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from glossrig.core.diagnose.catalogue import GAIN_THRESHOLD, CauseResult, consistent_folds
from glossrig.core.diagnose.witness import BOUND_Z, brdf_cause, refute, single_leds, take_witness_test

EDGE_PX = 0.25       # the limb's model error, pixels (module docstring)
COS_MIN = 0.5        # a limb counts under an LED with cos(theta_in) at least this at the limb point
SIL_Z = 4.0          # the pooled radius must lie this many standard errors from 0
AGREE_Z = 4.0        # a unit this many combined standard errors from the others: the limbs disagree
RUN, RUN_REF = 9, 6  # valid rows a limb's run needs; rows of it the coverage reference is drawn from
DARK = 0.05          # the rows outside a limb: no rate, or below this fraction of the sample's
MARGIN_PX = 28       # rows searched beyond the nominal limb (3 mm of radius at scale 0.25 is ~20 px)
MIN_COLUMNS = 20     # a unit (half a limb) needs this many measured columns
SAMPLE_MARGIN_MM = 2.0  # columns whose limb lies this close to the sample's upper or lower edge are left out


def _frame(geom, K, dist):
    """(camera centre, cylinder-frame ray function) of one rotation's calibrated poses."""
    from glossrig.core.extraction.cylinder import undistorted_rays

    C = -geom.R_hold.T @ geom.t_hold
    o = geom.R_cyl.T @ (C - geom.t_cyl)

    def rays(u, v):
        return (undistorted_rays(K, dist, np.ravel(u), np.ravel(v)) @ geom.R_hold) @ geom.R_cyl
    return o, rays


def axis_distance(geom, K, dist, u, v):
    """Distance (mm) from the cylinder's axis of the rays through pixels (u, v), and the axial
    coordinate y and cylinder-frame point of their closest approach (the limb point of a grazing ray)."""
    o, rays = _frame(geom, K, dist)
    d = rays(u, v)
    dn2 = d[:, 0] ** 2 + d[:, 2] ** 2
    r = np.abs(o[0] * d[:, 2] - o[2] * d[:, 0]) / np.sqrt(dn2)
    t = -(o[0] * d[:, 0] + o[2] * d[:, 2]) / dn2
    p = o[None, :] + t[:, None] * d
    return r, p[:, 1], p


def limb_box(geom, K, dist, radius: float, height: float, size) -> tuple[tuple[int, int, int, int], bool]:
    """The box (x0, y0, x1, y1, even origin) around the sample's outline, MARGIN_PX beyond it, and whether
    the limbs run along the image's rows (``transposed``: the cylinder's axis nearer the image's v)."""
    w, h = size
    # the axis's ends seen from the camera: its direction in the image decides the scan direction
    ends = np.array([[0.0, -height / 2, 0.0], [0.0, height / 2, 0.0]]) @ geom.R_cyl.T + geom.t_cyl
    cam = ends @ geom.R_hold.T + geom.t_hold
    uv = cam[:, :2] / cam[:, 2:3]
    transposed = abs(uv[1, 1] - uv[0, 1]) > abs(uv[1, 0] - uv[0, 0])
    gu, gv = np.meshgrid(np.arange(0, w, 4.0), np.arange(0, h, 4.0))
    r, yy, _ = axis_distance(geom, K, dist, gu, gv)
    on = (r < radius) & (np.abs(yy) < height / 2)
    if not on.any():
        return (0, 0, 0, 0), transposed
    us, vs = gu.ravel()[on], gv.ravel()[on]
    x0, x1 = int(us.min()) - MARGIN_PX, int(us.max()) + MARGIN_PX
    y0, y1 = int(vs.min()) - MARGIN_PX, int(vs.max()) + MARGIN_PX
    x0, y0 = max(0, x0 - x0 % 2), max(0, y0 - y0 % 2)
    return (x0, y0, min(w, x1), min(h, y1)), bool(transposed)


def limb_rates(sample_dir, geometry: dict, camera: tuple, image_size: tuple[int, int]) -> list[dict]:
    """Every LED's HDR rate over the box around the sample's outline (:func:`limb_box`), per
    rotation, in images of ``image_size`` (width, height; the capture's, as ``BrdfData.image_size``
    and the camera calibration carry it): units with ``rotation``, ``led``, ``box``, ``transposed``
    and the rate mosaic ``rate`` (NaN where no exposure gave a valid value)."""
    from glossrig.core.capture import load_manifest
    from glossrig.core.extraction.extract import led_rate, led_sequence
    from glossrig.core.rig import load_rig

    man = load_manifest(Path(sample_dir))
    rig = load_rig(man.folder / "rig.toml")
    K, dist = camera
    units = []
    for rot, g in sorted(geometry.items()):
        leds = single_leds(man, rot)
        if not leds:
            continue
        box, transposed = limb_box(g, K, dist, rig.cylinder_radius, rig.sample_height, image_size)
        if box[2] <= box[0] or box[3] <= box[1]:
            continue
        for led in leds:
            rate = led_rate(man, rig, led_sequence(man, rot, led), box)[0]
            rate = np.where(np.isfinite(rate) & (rate > 0), rate, np.nan).astype(np.float32)
            units.append({"rotation": float(rot), "led": int(led), "box": box, "transposed": transposed,
                          "rate": rate})
    return units


def _edge(col: np.ndarray, start: int, step: int) -> float | None:
    """Sub-pixel position (rows, from index 0 of ``col``, pixel centres at integers) of the outer edge of
    the run of valid values entering ``col`` at ``start`` and going on in direction ``step`` (+1: the run
    lies at larger indices); None where the run is too short or the outside is not dark."""
    n = len(col)
    inner = start + step * np.arange(RUN)
    if inner.min() < 0 or inner.max() >= n or not np.all(np.isfinite(col[inner])):
        return None
    ref_rows = start + step * np.arange(3, 3 + RUN_REF)
    level = float(np.median(col[ref_rows]))
    outside = start - step * np.arange(3, 7)
    outside = outside[(outside >= 0) & (outside < n)]
    if len(outside) < 2 or np.any(col[outside] > DARK * level):
        return None
    cover = 0.0
    for i in start + step * np.arange(-2, 3):
        if not 0 <= i < n or not np.isfinite(col[i]):
            continue
        same = ref_rows[(ref_rows - i) % 2 == 0]              # the same colour of the Bayer mosaic
        k = np.polyfit((same - i).astype(float), col[same].astype(float), 1)
        ref = float(np.polyval(k, 0.0))
        if ref > 0:
            cover += min(max(float(col[i]) / ref, 0.0), 1.2)
    # the rows from start - 2 to start + 2 hold ``cover`` rows' worth of sample: the edge lies that far
    # outwards of the inner border of row start + 2
    return float(start + step * 2.5 - step * cover)


def _limb_columns(unit: dict, geom, K, dist, radius: float, height: float, lamp, grid) -> dict[str, np.ndarray]:
    """Per limb ("low", "high" along the scan), the columns measured: radius error (mm), mm of radius per
    pixel across the limb there, cos(theta_in) at the limb point and the column's index. ``grid``: the
    box's (axis distance, axial coordinate) per pixel, scan-oriented (:func:`_grid`)."""
    x0, y0, _, _ = unit["box"]
    tr = unit["transposed"]
    img = unit["rate"].T if tr else unit["rate"]             # scan along axis 0 of img
    r_grid, y_grid = grid

    def pix(c, r):                                           # img (column, row position) -> full image (u, v)
        c, r = np.asarray(c, float), np.asarray(r, float)
        return (x0 + r, y0 + c) if tr else (x0 + c, y0 + r)

    # the edges first, then one ray cast for all of them (and half a pixel either side: mm per pixel)
    found = []
    for c in range(img.shape[1]):
        col = img[:, c]
        on = (r_grid[:, c] < radius + 3.0) & (np.abs(y_grid[:, c]) < height / 2 - SAMPLE_MARGIN_MM)
        idx = np.flatnonzero(on & np.isfinite(col))
        if len(idx) < 2 * RUN:
            continue
        for side, start, step in (("low", idx.min(), 1), ("high", idx.max(), -1)):
            e = _edge(col, int(start), step)
            if e is not None:
                found.append((side, c, e))
    out: dict[str, np.ndarray] = {"low": np.zeros((0, 4)), "high": np.zeros((0, 4))}
    if not found:
        return out
    cs = np.array([f[1] for f in found], float)
    es = np.array([f[2] for f in found], float)
    u, v = pix(np.repeat(cs, 3), (es[:, None] + np.array([0.0, -0.5, 0.5])).ravel())
    r, y, p = axis_distance(geom, K, dist, u, v)
    r, y, p = r.reshape(-1, 3), y.reshape(-1, 3)[:, 0], p.reshape(-1, 3, 3)[:, 0]
    n = p * np.array([1.0, 0.0, 1.0])
    wi = (geom.R_cyl.T @ (np.asarray(lamp, float) - geom.t_cyl))[None, :] - p
    cos_in = np.sum(n * wi, axis=1) / (np.linalg.norm(n, axis=1) * np.linalg.norm(wi, axis=1))
    rows = np.stack([r[:, 0] - radius, np.abs(r[:, 2] - r[:, 1]), cos_in, cs], axis=1)
    keep = np.abs(y) <= height / 2 - SAMPLE_MARGIN_MM
    sides = np.array([f[0] for f in found])
    return {sd: rows[keep & (sides == sd)] for sd in ("low", "high")}


def _grid(unit: dict, geom, K, dist) -> tuple[np.ndarray, np.ndarray]:
    """Axis distance and axial coordinate of every pixel of a unit's box, oriented like its scan."""
    x0, y0, x1, y1 = unit["box"]
    vv, uu = np.mgrid[y0:y1, x0:x1]
    r, y, _ = axis_distance(geom, K, dist, uu.astype(float), vv.astype(float))
    r, y = r.reshape(uu.shape), y.reshape(uu.shape)
    return (r.T, y.T) if unit["transposed"] else (r, y)


def silhouette_evidence(units: list[dict], geometry: dict, camera: tuple, radius: float, height: float,
                        lamps: dict) -> dict | None:
    """The sample radius error the outline measures (module docstring): ``dr`` (mm), its standard error
    ``se``, the held-out ``gain`` and ``fold_gains``, ``significant`` (``why_not`` where not) and the
    ``units`` (rotation, LED, limb, half, estimate, standard error, columns, cos theta_in). None where
    no lit limb could be measured."""
    K, dist = camera
    parts, grids, skipped = [], {}, []
    for u in units:
        g = geometry.get(u["rotation"])
        if g is None or u["led"] not in lamps:
            continue
        key = (u["rotation"], tuple(u["box"]))
        if key not in grids:
            grids[key] = _grid(u, g, K, dist)
        limbs = _limb_columns(u, g, K, dist, radius, height, lamps[u["led"]], grids[key])
        for side, a in limbs.items():
            a = a[a[:, 2] >= COS_MIN] if len(a) else a
            if len(a) < 2 * MIN_COLUMNS:
                continue
            cut = np.median(a[:, 3])
            for half, sel in (("first", a[:, 3] <= cut), ("second", a[:, 3] > cut)):
                x = a[sel, 0]
                if len(x) < MIN_COLUMNS:
                    continue
                med = float(np.median(x))
                stat = 1.2533 * 1.4826 * float(np.median(np.abs(x - med))) / math.sqrt(len(x))
                floor = EDGE_PX * float(np.median(a[sel, 1]))
                if stat > floor:          # columns scattered beyond the edge model: no clean outline here
                    skipped.append({"rotation": u["rotation"], "led": u["led"], "limb": side, "half": half, "dr": med,
                                    "se_stat": stat, "floor": floor})
                    continue
                parts.append({"rotation": u["rotation"], "led": u["led"], "limb": side, "half": half, "dr": med,
                              "se_stat": stat, "se": math.hypot(stat, floor), "floor": floor,
                              "columns": int(len(x)), "cos_in": float(np.median(a[sel, 2]))})
    if not parts:
        return None
    e = np.array([p["dr"] for p in parts])
    s = np.array([p["se"] for p in parts])
    st = np.array([p["se_stat"] for p in parts])
    w = 1.0 / s ** 2
    dr = float(np.sum(w * e) / np.sum(w))
    # the edge model's error is the same at every limb: it is not averaged down
    se = math.hypot(1.0 / math.sqrt(np.sum(1.0 / np.maximum(st, 1e-9) ** 2)), float(np.median([p["floor"] for p in parts])))
    fold_gains, chi0, chi1, worst = [], 0.0, 0.0, 0.0
    if len(parts) > 1:
        for j in range(len(parts)):
            k = np.arange(len(parts)) != j
            dj = float(np.sum(w[k] * e[k]) / np.sum(w[k]))
            sj = 1.0 / math.sqrt(np.sum(w[k]))
            c0, c1 = (e[j] / s[j]) ** 2, ((e[j] - dj) / s[j]) ** 2
            chi0, chi1 = chi0 + c0, chi1 + c1
            fold_gains.append(1.0 - c1 / c0 if c0 > 0 else 0.0)
            worst = max(worst, abs(e[j] - dj) / math.hypot(s[j], sj))
    gain = 1.0 - chi1 / chi0 if chi0 > 0 else 0.0
    ev: dict = {"dr": dr, "se": se, "gain": gain, "fold_gains": fold_gains, "units": parts, "left_out": skipped,
          "disagreement_z": worst, "limbs": [list(x) for x in sorted({(p["rotation"], p["led"], p["limb"]) for p in parts})],
          "significant": False, "why_not": None}
    if len(parts) < 2:
        ev["why_not"] = "one half-limb measured: no held-out test"
    elif worst > AGREE_Z:
        ev["why_not"] = (f"the limbs disagree ({worst:.1f} combined standard errors): a pose error or a sample that "
                         "is not a cylinder of one radius")
    elif abs(dr) <= SIL_Z * se:
        ev["why_not"] = f"dr within {SIL_Z:g} standard errors of 0"
    elif not (gain > GAIN_THRESHOLD and consistent_folds(fold_gains)):
        ev["why_not"] = "held-out gain not above the threshold in the folds"
    else:
        ev["significant"] = True
    return ev


def apply_silhouette_evidence(m, causes: list[CauseResult], ev: dict | None) -> None:
    """Judge the BRDF-space ``sample_radius_error`` cause by the outline (module docstring), in place;
    ``m``: the model the cause was fitted on (:func:`glossrig.core.diagnose.catalogue.model_of`)."""
    from glossrig.core.diagnose.geometry import Geometry

    c = brdf_cause(causes, "sample_radius_error")
    if c is None or ev is None:
        return
    dr_b = float(c.params.get("dr_mm", float("nan")))
    se_b = float(c.stderr.get("dr_mm", float("nan")) or float("nan")) if isinstance(c.stderr, dict) else float("nan")
    c.params.update({"dr_silhouette": ev["dr"], "dr_silhouette_se": ev["se"], "silhouette": {
        k: ev[k] for k in ("gain", "fold_gains", "limbs", "disagreement_z", "significant", "why_not")}})
    if ev["significant"]:
        def test():
            return Geometry(m).held_test(dr=ev["dr"])
        note = (f"silhouette signature: the sample's outline in its own frames lies where a cylinder of radius "
                f"{ev['dr']:+.3g} +- {ev['se']:.2g} mm from the rig file's grazes the rays (limbs lit by "
                f"{len(ev['limbs'])} LED(s); no material moves an outline; free BRDF-space fit: dr = {dr_b:.3g} mm)")
        if take_witness_test(c, m, ev, "dr_mm", ev["dr"], None, {}, note, "silhouette", test=test, direct=True):
            return
    if (np.isfinite(dr_b) and c.significant and abs(ev["dr"]) < SIL_Z * ev["se"]
            and abs(dr_b - ev["dr"]) > BOUND_Z * math.hypot(ev["se"], se_b if np.isfinite(se_b) else 0.0)):
        refute(c, f"the silhouette refutes it: the sample's outline shows a radius {ev['dr']:+.2g} +- "
                  f"{ev['se']:.2g} mm from the rig file's, the BRDF-space fit needs {dr_b:+.3g} mm")
