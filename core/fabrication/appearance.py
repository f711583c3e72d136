"""How the print will look: the predicted gloss of the halftoned sheet, lit and rendered
beside the target (``preview_render.png``; thesis 7.2.5, fig. 7.7), and how much of the
target's detail the halftone can carry at the chosen width.

**What is predicted.** The reproduction model (thesis ch. 6) describes a region
halftoned at nominal coverage ``cn`` (scratched area fraction, base 2) by the *BRDF mix*

    f = (1 - ce) f_b1 + ce f_b2,        ce = ETN^-1(cn)            (eq. 6.1-6.4)

of its two extended-Ward bases (:mod:`glossrig.core.models.ward`, eq. 4.79-4.80), ``ce``
being the effective coverage. The thesis stresses that Ward *parameters* do not mix
(6.1), so the prediction is this mix of BRDF values, not a Ward lobe with interpolated
parameters. ``cn`` is what the halftone actually lays down: the scratched fraction of
the ``b x T`` cells around each cell (:func:`printed_coverage`), the smallest window in
which juxtaposed halftoning carries a tone (an axis-aligned ``b x T`` window holds every
position of the screen element exactly once, :mod:`.halftone`), so nearest-level
quantisation, clipped ETN values and lost detail all show.

Where the bases and the ETN come from (:func:`load_gloss_model`):

* ``--model`` holding ``base1.ward`` / ``base2.ward`` (the ``model.json`` that
  ``core/reproduction/model.py`` writes): those bases, and the inverse of its ETN;
* ``--model`` with an ETN only: the thesis's bases (``scenes/materials/base_1.toml``,
  sample 0/6, and ``base_2.toml``, the fitted second base of thesis 6.2) and the
  inverse of the model's ETN;
* no model: the thesis's bases and the thesis's own nominal -> effective relation,
  interpolated piecewise linearly through the fitted pairs of thesis Table 6.4
  (:data:`TABLE_6_4_NOMINAL`, :data:`TABLE_6_4_EFFECTIVE`) - an assumption: the user's
  sheet and scalpel behave as the thesis's did.

``ETN^-1`` is tabulated on 2001 effective coverages in [0, 1] (the ETN is monotone,
being a sigmoid); a nominal coverage beyond the ETN's range on [0, 1] maps to the end
of [0, 1] (the print can be no glossier than base 1 nor duller than base 2).

**Orientation of the lobes on the print.** The bases' Ward frames are those of the
measured samples; the print's scratches run along the halftone's discrete lines,
direction ``(b, a)`` in image (column, row) coordinates. Scratches (grooves) spread the
micro-normals, hence the half vector, across the groove, so the scratched base's lobe
is broad perpendicular to the scratches and narrow along them (Ward 1992, brushed
metal; the highlight of a brushed surface is a streak across the brushing). The sheet's
tangent frame is therefore turned so that base 2's narrow lobe axis (after its
``lobe_rotation``, eq. 4.80) runs along the scratch lines; base 1 shares that frame, as
all samples were measured in one frame (thesis 6.2). Assumption stated: the scratch
direction of the measured samples is base 2's narrow axis.

**Rendering** (:func:`render_print`), the setup of the thesis's photographs of printed
samples (figs. 7.5, 7.7c-d, 7.8b-c): a flat sheet, a point light and a camera. For a
flat sheet lit by one point source there is no interreflection and no occlusion, so
the radiance leaving a point ``x`` towards the camera is exactly

    L(x) = f(wi(x), wo(x)) I cos(theta_i(x)) / |x_light - x|^2

(the rendering equation with a single point light, e.g. Pharr, Jakob & Humphreys,
*PBRT* 3rd ed., 12.2). It is evaluated per output pixel with the per-pixel light and
view directions and the per-pixel BRDF mix, each base through
:func:`glossrig.core.models.ward.ward_local`, the project's one Ward evaluation; this is what a
path tracer (Mitsuba and the project's ``glossrig_ward`` plugin, ``twin/``) would
converge to for this scene, so no renderer is needed and the preview stays in ``core``.
The radiance is drawn on the sheet's own pixel grid (the photograph rectified onto the
sheet plane, so it lines up with the target); a pixel records radiance, which does not
depend on the projection. Default geometry (:class:`Lighting`): camera beyond the
print's bottom edge and the light beyond its top edge, both 30 degrees from the normal
and 3 print sizes from the centre, in mirror configuration, so the specular highlight
sits at the print's centre and falls off towards the edges as it does on a desk.
Display: Reinhard et al.'s global operator with burn-out ("Photographic tone
reproduction for digital images", SIGGRAPH 2002, eq. 1-4; key 0.18, white = the
brightest pixel so nothing clips), then the sRGB transfer function (IEC 61966-2-1);
it is monotone, so brighter stays brighter.

**Detail** (:func:`detail_loss`). Juxtaposed halftoning carries tone per screen element
(``b x T`` cells), so image detail finer than one element cannot print. The fraction of
the image's contrast energy (variance about its mean) that is lost is estimated by
area-averaging the image onto the grid of screen elements the print holds and
interpolating it back (bilinear): ``sum (I - I_low)^2 / sum (I - mean I)^2``. The width
that keeps all but :data:`DETAIL_LOSS_LIMIT` of it is found by growing the element
count; one element per image pixel keeps everything. Images above
:data:`DETAIL_MAX_PX` pixels on a side are first area-averaged down to it (detail finer
than that is ignored).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.models.ward import WardParams, ward_local
from glossrig.core.fabrication.machine import ScreenParams
from glossrig.core.reproduction.model import load_bases

#: thesis Table 6.4, second base: nominal coverage -> fitted effective coverage of the samples
#: (sample 4/6 was excluded from the thesis's fit)
TABLE_6_4_NOMINAL = (0.0, 0.17, 0.33, 0.4, 0.5, 0.7, 0.83, 1.0)
TABLE_6_4_EFFECTIVE = (0.0, 0.39, 0.63, 0.72, 0.76, 0.86, 1.0, 1.0)
#: the share of the image's contrast energy finer than one screen element above which
#: ``fabricate`` warns
DETAIL_LOSS_LIMIT = 0.10
DETAIL_MAX_PX = 1024
PANEL_HEIGHT = 400
PANEL_MAX_WIDTH = 800


@dataclass(frozen=True)
class GlossModel:
    """What the preview predicts with: two bases and the nominal -> effective map."""

    base1: WardParams
    base2: WardParams
    nominal: tuple[float, ...]          # tabulated nominal coverages (increasing) ...
    effective: tuple[float, ...]        # ... and their effective coverages
    source: str                         # words for the summary
    label: str = ""                     # a short caption

    def effective_coverage(self, nominal) -> np.ndarray:
        """``ce = ETN^-1(cn)`` (or the Table 6.4 interpolation), clamped to [0, 1]."""
        return np.interp(np.asarray(nominal, dtype=np.float64), self.nominal, self.effective)

    def to_json(self) -> dict:
        return {"source": self.source, "base1": self.base1.as_dict(), "base2": self.base2.as_dict(),
                "mix": "f = (1 - ce) f_b1 + ce f_b2, ce = ETN^-1(nominal printed coverage) (thesis eq. 6.1-6.4)"}


def _thesis_bases() -> tuple[WardParams, WardParams]:
    from glossrig.core.models.materials import parse_material

    b1, b2 = parse_material("base_1").ward, parse_material("base_2").ward
    assert b1 is not None and b2 is not None        # the packaged thesis bases are Ward materials
    return b1, b2


def _inverse_table(etn) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(nominal, effective) tabulating ``ETN^-1`` on [0, 1], nominal increasing."""
    x = np.linspace(0.0, 1.0, 2001)
    y = np.asarray(etn(x), dtype=np.float64)            # clipped to [0, 1]
    if not np.all(np.isfinite(y)):
        raise InputError("ETN is not finite on [0, 1]", path=getattr(etn, "source", None) or None)
    if y[-1] < y[0]:
        x, y = x[::-1], y[::-1]
    y = np.maximum.accumulate(y)            # a monotone sigmoid; guards rounding only
    return tuple(y.tolist()), tuple(x.tolist())


def load_gloss_model(model: str | Path | None = None, etn=None) -> GlossModel:
    """The bases and nominal -> effective map for the preview (module docstring).

    ``model``: the ``--model`` file, read for ``base1.ward`` and ``base2.ward``
    (:func:`glossrig.core.reproduction.model.load_bases`); ``etn``: its ETN
    (:func:`glossrig.core.reproduction.model.load_etn`), which the caller has already read
    and checked. Malformed bases raise ``InputError`` naming the file."""
    b1, b2 = _thesis_bases()
    where = ("thesis bases (scenes/materials/base_1.toml = sample 0/6, base_2.toml = the fitted second base of "
             "thesis 6.2; both thesis Table 9.1)")
    if model is not None:
        bases = load_bases(model)
        if bases is not None:
            b1, b2 = bases
            where = f"bases of {Path(model).name}"
    short = "thesis bases" if model is None or where.startswith("thesis") else f"bases of {Path(model).name}"
    if etn is not None:
        assert model is not None, "etn is the model's ETN: pass the model too"
        nominal, effective = _inverse_table(etn)
        return GlossModel(b1, b2, nominal, effective, f"{where}; effective = inverse of the model's ETN (eq. 6.7)",
                          f"{short}, ETN of {Path(model).name}")
    return GlossModel(b1, b2, TABLE_6_4_NOMINAL, TABLE_6_4_EFFECTIVE,
                      f"{where}; effective = thesis Table 6.4 (nominal -> effective, piecewise linear)",
                      f"{short}, nominal -> effective: thesis Table 6.4")


# ------------------------------------------------------------------------ printed coverage

def printed_coverage(bitmap: np.ndarray, screen: ScreenParams) -> np.ndarray:
    """Scratched fraction of the ``T x b`` window (rows x columns) around every cell of
    the halftone ``bitmap`` (True = scratch): the nominal coverage the print lays down.

    Each such window holds every position of a screen element exactly once (it spans
    ``b`` consecutive columns, so every ``x mod b``, and in each column ``T`` consecutive
    rows, so every line index mod ``T``), so a region halftoned at level ``n`` gives
    exactly ``n / (b T)``. Windows are taken whole: a cell nearer the edge than half a
    window takes the value of the nearest whole window."""
    bm = np.asarray(bitmap, dtype=np.float64)
    rows, cols = bm.shape
    h, w = min(screen.T, rows), min(screen.b, cols)
    S = np.zeros((rows + 1, cols + 1))
    S[1:, 1:] = bm.cumsum(0).cumsum(1)
    win = (S[h:, w:] - S[:-h, w:] - S[h:, :-w] + S[:-h, :-w]) / (h * w)
    top, left = (h - 1) // 2, (w - 1) // 2
    return np.pad(win, ((top, h - 1 - top), (left, w - 1 - left)), mode="edge")


# ------------------------------------------------------------------------ rendering

@dataclass(frozen=True)
class Lighting:
    """Point light and camera over the print (module docstring). Zenith angles from the
    sheet normal; the camera lies beyond the print's bottom edge (image rows grow towards
    it), the light beyond the top edge when ``light_azimuth_deg`` is 0 (mirror
    configuration), turning anticlockwise seen from the camera side for other values.
    Distances are in print sizes (the larger of width and height) from the centre."""

    view_zenith_deg: float = 30.0
    light_zenith_deg: float = 30.0
    light_azimuth_deg: float = 0.0
    view_distance: float = 3.0
    light_distance: float = 3.0
    intensity: float = 1.0              # W/sr; only relative values are drawn

    def positions(self, size_mm: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
        """(light, camera) positions in mm; sheet in z = 0, centred, x right, y up."""
        S = max(size_mm)
        tv, tl = math.radians(self.view_zenith_deg), math.radians(self.light_zenith_deg)
        pl = math.radians(90.0 + self.light_azimuth_deg)
        cam = self.view_distance * S * np.array([0.0, -math.sin(tv), math.cos(tv)])
        light = self.light_distance * S * np.array([math.sin(tl) * math.cos(pl), math.sin(tl) * math.sin(pl),
                                                    math.cos(tl)])
        return light, cam

    def describe(self) -> str:
        az = "" if self.light_azimuth_deg == 0 else f", azimuth {self.light_azimuth_deg:g} deg"
        return (f"point light {self.light_zenith_deg:g} deg from the normal beyond the top edge{az}, camera "
                f"{self.view_zenith_deg:g} deg beyond the bottom edge, at {self.light_distance:g} and "
                f"{self.view_distance:g} print sizes")

    def to_json(self) -> dict:
        return {**{k: getattr(self, k) for k in self.__dataclass_fields__}, "description": self.describe(),
                "frame": "sheet in z = 0, x along image columns, y up the image (against rows), z towards camera"}


def scratch_frame_angle(model: GlossModel, screen: ScreenParams) -> float:
    """World angle ``psi`` (radians, from the image's x axis, anticlockwise seen from the
    camera) of the Ward tangent of the print: base 2's narrow lobe axis along the scratch
    lines (module docstring)."""
    sigma = math.atan2(-screen.a, screen.b)           # lines (b, a) in (column, row-down) = (b, -a) with y up
    b2 = model.base2
    rot = b2.lobe_rotation
    # ward_local: the alpha_x axis is (cos rot, -sin rot) in the local frame, alpha_y (sin rot, cos rot)
    narrow = -rot if b2.alpha_x < b2.alpha_y else math.pi / 2 - rot
    return sigma - narrow


def render_print(effective: np.ndarray, size_mm: tuple[float, float], model: GlossModel, screen: ScreenParams,
                 lighting: Lighting = Lighting(), shape: tuple[int, int] | None = None) -> np.ndarray:
    """Radiance (W sr^-1 m^-2 per W sr^-1 of the light, with lengths in mm) leaving the
    print towards the camera, on a ``shape`` (rows, cols) grid over the sheet
    (module docstring). ``effective``: effective coverage per halftone cell."""
    ce: np.ndarray = np.asarray(effective, dtype=np.float64)
    if shape is None:
        shape = ce.shape
    rows, cols = shape
    W, H = size_mm
    if tuple(shape) != ce.shape:
        shrink = rows * cols < ce.size
        ce = cv2.resize(ce, (cols, rows), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    x = ((np.arange(cols) + 0.5) / cols - 0.5) * W
    y = (0.5 - (np.arange(rows) + 0.5) / rows) * H
    P = np.zeros((rows, cols, 3))
    P[..., 0], P[..., 1] = x[None, :], y[:, None]
    light, cam = lighting.positions(size_mm)
    to_l, to_c = light - P, cam - P
    r2 = np.sum(to_l ** 2, axis=-1)
    wi = to_l / np.sqrt(r2)[..., None]
    wo = to_c / np.linalg.norm(to_c, axis=-1, keepdims=True)
    psi = scratch_frame_angle(model, screen)
    c, s = math.cos(psi), math.sin(psi)

    def local(w):
        return np.stack([c * w[..., 0] + s * w[..., 1], -s * w[..., 0] + c * w[..., 1], w[..., 2]], axis=-1)

    wi_l, wo_l = local(wi), local(wo)
    f = (1.0 - ce) * ward_local(wi_l, wo_l, model.base1) + ce * ward_local(wi_l, wo_l, model.base2)
    return f * lighting.intensity * np.maximum(wi[..., 2], 0.0) / r2


def tone_map(radiance: np.ndarray, key: float = 0.18) -> np.ndarray:
    """Reinhard et al. 2002 (eq. 1-4) with white = the brightest pixel, then sRGB encoding;
    returns uint8. Monotone in radiance."""
    L = np.maximum(np.asarray(radiance, dtype=np.float64), 0.0)
    if not np.any(L > 0):
        return np.zeros(L.shape, np.uint8)
    logavg = math.exp(float(np.mean(np.log(1e-12 + L))))
    Lm = key / logavg * L
    white = float(Lm.max())
    Ld = Lm * (1.0 + Lm / white ** 2) / (1.0 + Lm)
    Ld = np.clip(Ld, 0.0, 1.0)
    srgb = np.where(Ld <= 0.0031308, 12.92 * Ld, 1.055 * np.power(Ld, 1 / 2.4) - 0.055)
    return np.clip(np.rint(srgb * 255), 0, 255).astype(np.uint8)


def _labelled(img: np.ndarray, lines: list[str]) -> np.ndarray:
    """``img`` (RGB) under a white strip holding ``lines``."""
    strip = np.full((10 + 16 * len(lines), img.shape[1], 3), 255, np.uint8)
    for i, t in enumerate(lines):
        cv2.putText(strip, t, (6, 18 + 16 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([strip, img], axis=0)


def panel_shape(size_mm: tuple[float, float]) -> tuple[int, int]:
    """(rows, cols) of a preview panel with the print's aspect ratio."""
    W, H = size_mm
    rows, cols = PANEL_HEIGHT, max(1, round(PANEL_HEIGHT * W / H))
    if cols > PANEL_MAX_WIDTH:
        rows, cols = max(1, round(PANEL_MAX_WIDTH * H / W)), PANEL_MAX_WIDTH
    return rows, cols


def preview_render(target: np.ndarray, bitmap: np.ndarray, screen: ScreenParams, size_mm: tuple[float, float],
                   model: GlossModel, *, lighting: Lighting = Lighting(),
                   target_label: str = "target (grey = coverage, white = scratched)") -> tuple[np.ndarray, dict]:
    """``preview_render.png``: the target image beside the predicted print lit and
    rendered (module docstring). Returns (RGB uint8 image, summary dict)."""
    rows, cols = panel_shape(size_mm)
    cn = printed_coverage(bitmap, screen)
    ce = model.effective_coverage(cn)
    radiance = render_print(ce, size_mm, model, screen, lighting, (rows, cols))
    t = np.asarray(target, dtype=np.float64)
    t8: np.ndarray = np.clip(np.rint(t * 255), 0, 255).astype(np.uint8)
    t8 = cv2.resize(t8, (cols, rows), interpolation=cv2.INTER_AREA if t.size > rows * cols else cv2.INTER_NEAREST)
    left = cv2.cvtColor(t8, cv2.COLOR_GRAY2RGB)
    right = cv2.cvtColor(tone_map(radiance), cv2.COLOR_GRAY2RGB)
    W, H = size_mm
    lines_r = ["predicted print, rendered (Ward mix, eq. 6.3)",
               f"{lighting.light_zenith_deg:g} deg light above top, {lighting.view_zenith_deg:g} deg camera below",
               f"{(model.label or model.source)[:60]}"]
    lines_l = [target_label[:60], f"print {W:.1f} x {H:.1f} mm", "halftoned, then predicted ->"]
    a, b = _labelled(left, lines_l), _labelled(right, lines_r)
    gap = np.full((a.shape[0], 10, 3), 255, np.uint8)
    img = np.concatenate([a, gap, b], axis=1)
    info = {"file": "preview_render.png", "panels": ["target", "predicted print"],
            "panel_px": [rows, cols],
            "method": "numpy: exact single-bounce radiance of a flat sheet under one point light "
                      "(L = f I cos(theta_i) / r^2), per-pixel directions; no Mitsuba needed for a flat sheet",
            "model": model.to_json(), "lighting": lighting.to_json(),
            "scratch_frame_angle_rad": scratch_frame_angle(model, screen),
            "printed_coverage": "scratched fraction of the T x b cells around each cell",
            "tone_map": "Reinhard et al. 2002 global operator (key 0.18, white = brightest pixel), sRGB encoded",
            "radiance_range": [float(radiance.min()), float(radiance.max())],
            "effective_coverage_mean": float(ce.mean())}
    return img, info


# ------------------------------------------------------------------------ detail

def _lost(img: np.ndarray, er: int, ec: int) -> float:
    var = float(np.sum((img - img.mean()) ** 2))
    if var <= 1e-12 * img.size:             # a flat image (std < 1e-6): no detail to lose
        return 0.0
    if er >= img.shape[0] and ec >= img.shape[1]:
        return 0.0
    low = cv2.resize(img, (max(1, ec), max(1, er)), interpolation=cv2.INTER_AREA)
    back = cv2.resize(low, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_LINEAR)
    return float(np.sum((img - back) ** 2)) / var


def detail_loss(image: np.ndarray, grid: tuple[int, int], screen: ScreenParams, cell_mm: float,
                limit: float = DETAIL_LOSS_LIMIT) -> dict:
    """How much of ``image``'s contrast the halftone grid ``grid`` (rows, cols of cells)
    can carry (module docstring). Returns the numbers and, when the loss exceeds
    ``limit``, the width that would keep all but ``limit``."""
    img: np.ndarray = np.asarray(image, dtype=np.float64)
    h, w = img.shape
    scale = min(1.0, DETAIL_MAX_PX / max(h, w))
    if scale < 1.0:
        img = cv2.resize(img, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
    rows, cols = grid
    er, ec = max(1, rows // screen.T), max(1, cols // screen.b)
    lost = _lost(img, er, ec)
    out = {"image_px": [h, w], "screen_elements": [er, ec],
           "element_mm": [screen.T * cell_mm, screen.b * cell_mm],
           "lost_fraction": lost, "limit": limit,
           "measure": "share of the image's variance finer than one screen element (b x T cells): "
                      "area-averaged onto the element grid and interpolated back"}
    per_elem_mm = screen.b * cell_mm
    out["width_one_element_per_pixel_mm"] = w * per_elem_mm
    if lost > limit:
        # smallest element count across (rows in proportion) whose loss is within the limit:
        # grow geometrically past it, then bisect (the loss falls as the grid grows)
        aspect = er / ec

        def ok(n: int) -> bool:
            return _lost(img, max(1, round(n * aspect)), n) <= limit

        lo, hi = ec, ec
        while hi < w and not ok(hi):
            lo, hi = hi, min(w, math.ceil(hi * 1.25))
        while hi - lo > 1:
            mid = (lo + hi) // 2
            lo, hi = (lo, mid) if ok(mid) else (mid, hi)
        out["width_to_keep_mm"] = hi * per_elem_mm
    return out


def detail_warning(d: dict, width_mm: float) -> str | None:
    """The warning text for :func:`detail_loss`'s result, or None when within the limit."""
    if d["lost_fraction"] <= d["limit"]:
        return None
    er, ec = d["screen_elements"]
    h, w = d["image_px"]
    return (f"--width-mm {width_mm:g} leaves {ec} x {er} halftone screen elements (the halftone's tone resolution, "
            f"{d['element_mm'][1] * 1000:.0f} x {d['element_mm'][0] * 1000:.0f} um each) for a {w} x {h} px image: "
            f"{d['lost_fraction']:.0%} of the image's contrast is finer than one element and will not print; "
            f"a width of about {math.ceil(d['width_to_keep_mm']):d} mm keeps all but {d['limit']:.0%} of it "
            f"({math.ceil(d['width_one_element_per_pixel_mm']):d} mm gives one element per image pixel)")
