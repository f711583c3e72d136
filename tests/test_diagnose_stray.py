"""Stray light's frame-space signature (issue 14; glossrig.core.diagnose.stray_light): the dark
pixels bound the veil from above and carry it where it is real."""
from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pandas as pd

from glossrig.core.diagnose.catalogue import BrdfModel, CauseResult, _linear_cause, stray_extra
from glossrig.core.diagnose.data import FrameData, LedFrames
from glossrig.core.diagnose.report import verdict
from glossrig.core.diagnose.stray_light import apply_frame_evidence, dark_veil, frame_evidence

K, READ, BLACK, WHITE = 0.69, 2.0, 600.0, 15520.0
EXPOSURES = np.array([2.5e-4 * 2 ** k for k in range(17)])      # 1/4000 s .. 16 s, as the rig's table
P_RATE = 2.0e5          # white patch (DN/s)


def _frames(seed: int, veil_dn_s: float, offset_dn: float = 0.0) -> tuple[FrameData, dict]:
    """One LED's crop (64 x 64, RGGB): a white patch, a lit sample and a background that sees nothing
    (radiance 0), plus a uniform veil (DN/s) on every pixel; shot and read noise (EMVA 1288),
    clipping at white, ``offset_dn`` added to every raw value (a black-level error)."""
    rng = np.random.default_rng(seed)
    h = w = 64
    rate = np.zeros((h, w))
    rate[8:28, 36:60] = P_RATE
    yy, xx = np.mgrid[0:h, 0:w]
    rate[30:56, 4:60] = 2.0e4 * (1 + 0.5 * np.sin(xx[30:56, 4:60] / 9.0))
    rate += veil_dn_s
    patch = np.zeros((h, w), bool)
    patch[10:26, 38:58] = True
    e = rng.poisson(rate[None] * EXPOSURES[:, None, None] * K) / K
    dn = np.minimum(BLACK + offset_dn + e + rng.normal(0, READ, e.shape), WHITE).astype(np.float32)
    lf = LedFrames(6, 0.0, dn, EXPOSURES.copy(), np.arange(len(EXPOSURES)) * 10.0, np.full((h, w), BLACK),
                   (0, 0), cfa=np.array([[0, 1], [1, 2]]))
    return FrameData([lf], WHITE, K, READ), {0.0: SimpleNamespace(patch_mask=patch)}


def test_dark_veil_recovers_a_veil_and_reads_none_without_one():
    """The veil in patch-normalised units within 4 of its standard errors; none read (within 4 se)
    where the background is dark, a black-level error included (it adds DN, not DN/s)."""
    for veil, off in ((400.0, 0.0), (0.0, 0.0), (0.0, 8.0)):
        fd, geo = _frames(3, veil, off)
        (ent,) = dark_veil(fd, geo)
        for c in range(3):
            v, se = ent["veil"][c], ent["veil_se"][c]
            assert v is not None and se > 0
            truth = veil / (P_RATE + veil)          # the patch reads the veil too
            assert abs(v - truth) < 4 * se, (veil, off, c, v, truth, se)
            assert se < 1e-4                        # the bound is tight: 1e-4 of the patch
        if off:
            assert np.allclose(ent["offset_dn"], off, atol=1.0)


# ------------------------------------------------------------------ the BRDF-space cause judged

LAMPS = {6: np.array([250.0, 80.0, 0.0]), 9: np.array([-60.0, 300.0, 40.0])}


def _model(seed: int, veil_s: float, grazing: float, bump: float) -> BrdfModel:
    """A BRDF-space model of two LEDs' rows: Ward-like lobe L, plus stray light's term of ``veil_s``,
    a material rise toward grazing incidence in theta_in alone (``grazing``, the shape of a
    non-reciprocal measured BRDF) and a material bump in theta_h (``bump``); 1 % noise."""
    rng = np.random.default_rng(seed)
    n = 3000
    led = np.repeat([6, 9], n // 2)
    phi = rng.uniform(-1, 1, n)
    pts = np.stack([30 * np.cos(phi), 30 * np.sin(phi), rng.uniform(-20, 20, n)], axis=1)
    cos_in = rng.uniform(0.08, 1.0, n)
    th = rng.uniform(0, 0.8, n)
    L = np.exp(-(th / 0.15) ** 2) / (4 * math.pi * 0.15 ** 2)
    table = pd.DataFrame({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]})
    cols = {"L": L, "cos_in": cos_in, "led": led.astype(float), "theta_h": th, "v": rng.uniform(0, 100, n)}
    m = BrdfModel(SimpleNamespace(table=table, lamps=LAMPS), None, np.arange(n), cols)
    extra = stray_extra(m)
    y = 0.5 / math.pi + 0.05 * L + veil_s * extra + grazing * (1 / cos_in - 1) + bump * np.exp(-((th - 0.5) / 0.1) ** 2)
    cols["sigma"] = 0.01 * y
    cols["y"] = y + cols["sigma"] * rng.normal(size=n)
    cols["bump"] = np.exp(-((th - 0.5) / 0.1) ** 2)
    return m


def _causes(m: BrdfModel) -> tuple[BrdfModel, list[CauseResult]]:
    """A material model with the theta_h bump and the stray-light cause fitted on top of it, as
    catalogue.brdf_causes fits an instrument cause (catalogue.instrument_bases: the material's columns
    join every solve); returns that conditioned model and the two causes."""
    c = m.cols
    one = np.full_like(c["L"], 1 / np.pi)
    mat = _linear_cause(m, "ggx_lobe", "material", [one, c["L"], c["bump"]], "b", "")
    mi = dataclasses.replace(m, flexible=True)
    mi.flexible_columns = lambda train: c["bump"][:, None]          # the material's own column
    stray = _linear_cause(mi, "stray_light", "stray", [one, c["L"], stray_extra(mi)], "s", "fraction")
    return mi, [stray, mat]


def _evidence(s: float, se: float) -> dict:
    return {"s": s, "se": se, "se_noise": se, "spread": 0.02, "unit": "fraction", "units": [
        {"led": 6, "rotation": 0.0, "s": s, "se": se, "n_dark": 500}]}


def test_dark_frames_refute_a_grazing_material_blamed_on_stray_light():
    """A material rising toward grazing theta_in alone fits the stray-light term (significant in BRDF
    space: the old verdict), but the frames' dark pixels read no veil: refuted, not named."""
    m, causes = _causes(_model(1, 0.0, 0.004, 0.0))
    stray = causes[0]
    assert stray.significant and stray.params["s"] > 0.003 and verdict(causes) == "stray_light"
    apply_frame_evidence(m, causes, _evidence(1e-6, 1e-6))
    assert stray.refuted and not stray.significant and not stray.eligible
    assert verdict(causes) != "stray_light"
    assert "refute" in stray.note


def test_frames_carrying_the_veil_name_stray_light_over_a_material_model():
    """Stray light hidden under a larger material departure, fitted on top of the material model: the
    frames carry the veil and the BRDF data agree with it held fixed: stray light is named, first, with
    the frames' s and its frame signature."""
    s_true = 0.008
    m, causes = _causes(_model(2, s_true, 0.0, 0.03))
    stray = causes[0]
    assert causes[1].significant                     # the material departure is there
    apply_frame_evidence(m, causes, _evidence(s_true, 2e-5))
    assert stray.frame_signature and stray.eligible and verdict(causes) == "stray_light"
    assert stray.params["s"] == s_true and stray.params["fixed_by"] == "frames"


def test_a_veil_the_brdf_data_do_not_show_is_not_named():
    """Frames that read a veil the BRDF data contradict (none there): the fixed-veil test fails, so the
    frame evidence alone names nothing."""
    m, causes = _causes(_model(3, 0.0, 0.0, 0.03))
    apply_frame_evidence(m, causes, _evidence(0.02, 2e-5))
    assert not causes[0].significant and verdict(causes) != "stray_light"


def test_frame_evidence_converts_the_veil_with_the_reference_calibration():
    """s = pi D^2 v / ((1 - v) median(S d^2 / (f cos theta_in))): a veil V / P = s k I / (pi D^2 P), read
    as v = V / (P + V) (the patch carries it too), gives back s whatever the sample's BRDF (rows with f
    and S of a reference-normalised table)."""
    rng = np.random.default_rng(4)
    n = 400
    lamp = LAMPS[6]
    pts = rng.normal(0, 20, (n, 3))
    cos_in = rng.uniform(0.2, 1, n)
    kIP = 3.7                                  # k I / P of the LED (patch units)
    f = rng.uniform(0.05, 0.5, (n, 3))
    d2 = np.sum((lamp - pts) ** 2, axis=1)
    S = f * (cos_in * kIP / d2)[:, None]       # S = f cos k I / (P d^2)
    t = pd.DataFrame({"led": 6, "rotation": 0.0, "x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "cos_in": cos_in})
    for k, c in enumerate("rgb"):
        t[c], t[f"S_{c}"] = f[:, k], S[:, k]
    s = 0.006
    V = s * kIP / (math.pi * float(lamp @ lamp))      # V / P
    v = V / (1 + V)                                   # the patch reads the veil too
    ev = frame_evidence([{"led": 6, "rotation": 0.0, "veil": [v] * 3, "veil_se": [v / 100] * 3, "n_dark": [50] * 3}],
                        t, LAMPS)
    assert ev is not None and abs(ev["s"] / s - 1) < 1e-9 and ev["spread"] < 1e-9


def test_report_says_what_the_frames_show(tmp_path):
    """report.json keeps the refutation with the cause and the frames' s in meta; report.md says both."""
    from glossrig.core.diagnose.report import read_report, write_report

    m, causes = _causes(_model(1, 0.0, 0.004, 0.0))
    ev = _evidence(1e-6, 1e-6)
    apply_frame_evidence(m, causes, ev)
    write_report(tmp_path, causes, {"brdf": causes[0].base_error}, {}, {"stray_light_frames": ev}, plots=False)
    rep = read_report(tmp_path)
    stray = next(c for c in rep["causes"] if c["name"] == "stray_light")
    assert stray["refuted"] and not stray["significant"] and rep["meta"]["stray_light_frames"]["s"] == 1e-6
    md = (tmp_path / "report.md").read_text()
    assert "Stray light in the frames" in md and "the frames refute it" in md
