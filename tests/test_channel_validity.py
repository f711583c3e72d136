"""Per-channel validity through the pipeline (issue 14, item 1).

A colour channel without a valid HDR value (too dark at the longest exposure, saturated
at the shortest) is NaN in that sample; the sample keeps its other channels, the fits
use each channel's valid rows, luminance fills a missing channel with that channel's own
fit, and extract says which channels ran out of range, where, and what exposure would
have fixed it.

Twin tests: the thesis rig with its exposure table cut at TABLE_MAX_S (the twin's
radiometry measures every channel of these materials with the full 1/4000-30 s table,
as a real camera with a shorter table, or an exposure plan made for green, would not),
LED 9, scale 0.12, one rotation, camera.json/lamps.json from the twin's truth.
"""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from glossrig.core.errors import InputError
from glossrig.core.radiometry import hdr
from glossrig.core.samples import (LUMINANCE_WEIGHTS, channel_weight, valid_channels, validate_samples,
                                   ward_samples)
from glossrig.core.models.ward import WardParams

from conftest import RIG, SHARED, camera_json_from_truth, glossrig_cli, lamps_json_from_truth
from helpers import geometry

RHO_D = (0.45, 0.30, 0.01)
LOBE = dict(rho_s=0.04, alpha_x=0.12, alpha_y=0.08, lobe_rotation=0.5)
WARD_SPEC = "ward:rho_d=0.45/0.30/0.01,rho_s=0.04,alpha_x=0.12,alpha_y=0.08,lobe_rotation=0.5"
FELT = SHARED / "data" / "rgl" / "acrylic_felt_green_rgb.bsdf"
TABLE_MAX_S = {"ward": 0.25, "felt": 0.0666}


def _channel_params():
    return {c: WardParams(rho_d=d, **LOBE) for c, d in zip("rgb", RHO_D)}


# ------------------------------------------------------------------ the table contract

def test_a_missing_channel_is_nan_and_the_row_keeps_the_others():
    df = ward_samples(geometry(), _channel_params()).iloc[:200].copy()
    df.loc[df.index[:50], "b"] = np.nan
    df["weight_b"] = np.where(np.isfinite(df["b"]), 2.0, np.nan)
    out = validate_samples(df)
    assert len(out) == 200 and out["b"].isna().sum() == 50
    ok = valid_channels(out)
    assert ok[:, :2].all() and ok[:, 2].sum() == 150
    assert (channel_weight(out, "b")[:50] == 0).all() and (channel_weight(out, "b")[50:] == 2).all()
    assert (channel_weight(out, "r") == out["weight"]).all()          # no weight_r: the row's weight


# ------------------------------------------------------------------ materials

def test_ward_material_takes_one_rho_d_per_channel():
    from glossrig.core.models.materials import parse_material
    from glossrig.twin.scene import material_bsdf

    m = parse_material(WARD_SPEC)
    assert m.rgb["rho_d"] == RHO_D
    assert m.channel_ward("b") == WardParams(rho_d=0.01, **LOBE)
    # the material's own Ward parameters are its luminance (eq. 4.79 is linear in the albedos)
    assert m.ward.rho_d == pytest.approx(sum(w * d for w, d in zip(LUMINANCE_WEIGHTS, RHO_D)))
    assert m.ward.rho_s == pytest.approx(0.04)
    assert m.to_json()["ward_rgb"]["r"]["rho_d"] == 0.45
    b = material_bsdf(m)
    assert b["rho_d"] == list(RHO_D) and b["rho_s"] == [0.04] * 3
    assert material_bsdf(parse_material("sample_2_6"))["rho_d"] == [0.0518] * 3
    for bad, msg in (("ward:rho_d=0.45/0.3,rho_s=0.04,alpha_x=0.1,alpha_y=0.1", "one value or three"),
                     ("ward:rho_d=0.45/0.3/0.99,rho_s=0.04,alpha_x=0.1,alpha_y=0.1", "b channel.*exceeds 1"),
                     ("ward:rho_d=0.45/x/0.1,rho_s=0.04,alpha_x=0.1,alpha_y=0.1", "not a number"),
                     ("ward:rho_d=0.4/0.3/0.1,rho_s=0.04,alpha_x=0.1,alpha_y=0.1,beta=2", "unknown parameter")):
        with pytest.raises(InputError, match=msg):
            parse_material(bad)


# ------------------------------------------------------------------ HDR: what exposure would have fixed it

def _stack(rates, t, noise, seed=0):
    """A one-repeat exposure stack of pixels of expected ``rates`` (H, W), linearised as
    raw.linearize does (clipped to [0, 1])."""
    rng = np.random.default_rng(seed)
    e = rates[None] * t[:, None, None]
    y = np.clip(e + rng.standard_normal(e.shape) * np.sqrt(noise.variance(e)), 0.0, 1.0).astype(np.float32)
    return hdr.ExposureStack(images=y, exposure_s=t, clipped=y >= 1.0, repeats=1)


def test_exposure_to_fix_is_the_longest_exposure_scaled_by_floor_over_value():
    noise = hdr.NoiseModel(electrons_full_scale=10257.5, read_sigma=2.93e-4)       # the thesis rig at ISO 320
    t = np.array([0.00025 * 2 ** k for k in range(10)])                             # 1/4000 .. 0.128 s
    rates = np.empty((100, 200))
    rates[:, :100] = 0.5 * hdr.LO / t[-1]           # half the floor at the longest exposure
    rates[:, 100:] = 3.0 / t[0]                     # saturated even at the shortest exposure
    rates[:50, 100:] = 0.97 / t[0]                  # above HI at the shortest, below saturation
    st = _stack(rates, t, noise)
    res = hdr.hdr_ml(st.images, t, noise, clipped=st.clipped)
    assert (res.status[:, :100] == hdr.TOO_DARK).mean() > 0.95
    assert (res.status[:50, 100:] == hdr.TOO_BRIGHT).mean() > 0.95      # 2 sigma above HI: a few are valid
    assert (res.status[50:, 100:] == hdr.TOO_BRIGHT).all()
    fix = hdr.exposure_to_fix(st, res.status)
    dark = res.status == hdr.TOO_DARK
    # expected 2 t_max; one pixel's estimate has ~25 % noise: the median over 10^4 pixels is within 2 %
    assert np.median(fix[dark]) == pytest.approx(2 * t[-1], rel=0.02)
    assert np.isnan(fix[res.status == hdr.VALID]).all()
    assert np.nanmedian(fix[:50, 100:]) == pytest.approx(hdr.HI * t[0] / 0.97, rel=0.01)   # HI / rate
    assert np.isnan(fix[50:, 100:]).all()           # saturated at the shortest: only "shorter" is known


def test_block_status_matches_the_blocks_that_lost_a_channel():
    from glossrig.core.extraction.extract import block_status, block_values

    h, w = 40, 60
    cfa = np.array([[0, 1], [1, 2]])
    rate = np.ones((h, w), np.float32)
    status = np.zeros((h, w), np.uint8)
    fix = np.full((h, w), np.nan)
    status[10, 20] = hdr.TOO_DARK          # an R pixel (even, even)
    fix[10, 20] = 4.0
    status[21, 31] = hdr.TOO_BRIGHT        # a B pixel (odd, odd)
    status[0:2, 0:2] = hdr.TOO_DARK        # one whole block, every channel
    rate[status != hdr.VALID] = np.nan
    bi, bj = np.meshgrid(np.arange(h // 2), np.arange(w // 2), indexing="ij")
    idx = (bi.ravel(), bj.ravel())
    vals, _ = block_values(rate, np.ones_like(rate), cfa, idx)
    st, t_fix = block_status(status, fix, cfa, idx)
    # exactly the blocks and channels whose bilinear read touched an invalid pixel
    np.testing.assert_array_equal(st != hdr.VALID, ~np.isfinite(vals))
    r_dark = st[:, 0] == hdr.TOO_DARK
    assert (~np.isfinite(vals[:, 1:]) == (st[:, 1:] != hdr.VALID)).all()
    assert st[np.flatnonzero((idx[0] == 5) & (idx[1] == 10))[0]].tolist() == [hdr.TOO_DARK, 0, 0]
    assert (t_fix[r_dark & ~((idx[0] < 2) & (idx[1] < 2)), 0] == 4.0).all()
    assert (st[:, 2] == hdr.TOO_BRIGHT).sum() == 4 and np.isnan(t_fix[st[:, 2] == hdr.TOO_BRIGHT, 2]).all()
    assert (st[0] == hdr.TOO_DARK).all()   # the dark block misses every channel


# ------------------------------------------------------------------ fits on each channel's valid rows

def test_fits_use_each_channels_valid_rows_and_luminance_predicts_the_missing_one():
    """b missing where its signal is low (true b x cos theta_in, a proxy of the signal,
    below its 60th percentile, as a dark channel is) and r in the brightest 1 % of true
    values (saturated); chosen on the true values, so no noise selection enters (that
    one is the HDR floor's, seen in the twin tests). Every channel recovers its own rho_d
    within 4 of its noise-only standard errors plus 0.5 %, and luminance, fitted on every
    row with the missing channels predicted, recovers the luminance material."""
    from glossrig.core.fitting.fit import fit_samples

    truth = ward_samples(geometry(), _channel_params())
    df = ward_samples(geometry(), _channel_params(), noise=0.02, seed=3)
    signal = truth["b"] * np.cos(truth["theta_in"])
    b_dim = signal < signal.quantile(0.60)
    r_hot = truth["r"] > truth["r"].quantile(0.99)
    df.loc[b_dim, "b"] = np.nan
    df.loc[r_hot, "r"] = np.nan
    m = fit_samples(df, budget=False, footprint=False)
    info = m.options["missing_channels"]
    assert info["rows"] == len(df) and info["rows_with_every_channel"] == int((~b_dim & ~r_hot).sum())
    assert info["b"]["rows"] == int((~b_dim).sum()) and m.fits["b"].n_samples == int((~b_dim).sum())
    assert info["luminance"]["rows"] == len(df) and m.fits["luminance"].n_samples == len(df)
    for c, truth in zip("rgb", RHO_D):
        f = m.fits[c]
        assert abs(f.params.rho_d - truth) < 4 * f.stderr["rho_d"] + 0.005 * truth, (c, f.params, f.stderr)
    y = m.fits["luminance"]
    y_truth = sum(w * d for w, d in zip(LUMINANCE_WEIGHTS, RHO_D))
    assert abs(y.params.rho_d - y_truth) < 4 * y.stderr["rho_d"] + 0.005 * y_truth
    # the shared-lobe albedos use each channel's valid rows too
    assert np.allclose(m.shared_rgb["rho_d"], RHO_D, rtol=0.03)


def test_a_channel_missing_everywhere_is_a_clear_error_and_luminance_falls_back():
    from glossrig.core.fitting.fit import fit_samples

    df = ward_samples(geometry(), _channel_params(), noise=0.02).iloc[:3000].copy()
    df["b"] = np.nan
    df.loc[df.index[:2], "b"] = 0.003               # two rows: too few for a fit of b
    with pytest.raises(InputError, match="b: 2 samples"):
        fit_samples(df, channels=["b"], budget=False, footprint=False)
    m = fit_samples(df, channels=["luminance"], budget=False, footprint=False)
    info = m.options["missing_channels"]
    assert "fit_failed" in info["b"] and info["luminance"]["rows"] == 3000
    assert info["luminance"]["predicted_by"]["b"].startswith("0")       # too dark to fit: taken as 0
    y_truth = sum(w * d for w, d in zip(LUMINANCE_WEIGHTS, RHO_D[:2]))   # b's share lost: 0.0722 x 0.01
    assert m.fits["luminance"].params.rho_d == pytest.approx(y_truth, rel=0.03)
    df["b"] = np.nan
    with pytest.raises(InputError, match="missing in every row"):
        fit_samples(df, channels=["b"], budget=False, footprint=False)
    df["b"] = np.nan
    df.loc[df.index[0], "r"] = np.nan
    df.loc[df.index[0], "g"] = np.nan
    with pytest.raises(InputError, match="no valid colour channel"):
        validate_samples(df)


# ------------------------------------------------------------------ the dynamic-range report

def test_dynamic_range_report_says_which_channel_where_and_what_exposure():
    from glossrig.core.extraction.dynamic_range import dynamic_range_report, log_dynamic_range

    n = 400
    rng = np.random.default_rng(0)
    t = pd.DataFrame({"rotation": 0.0, "led": np.repeat([5, 9], n // 2).astype(np.int32),
                      "theta_h": rng.uniform(0, 1.2, n), "theta_in": rng.uniform(0, 1.4, n),
                      "theta_out": rng.uniform(0, 1.4, n)})
    for c in "rgb":
        t[c] = 1.0
        t[f"status_{c}"] = np.uint8(hdr.VALID)
        t[f"fix_s_{c}"] = np.nan
    dark = (t.led == 5) & (t.theta_in > 0.7)          # LED 5's grazing half: b too dark
    t.loc[dark, "b"] = np.nan
    t.loc[dark, "status_b"] = hdr.TOO_DARK
    t.loc[dark, "fix_s_b"] = np.linspace(0.5, 2.0, int(dark.sum()))
    unlit = t.index[-10:]                             # no channel at all: not a channel's shortfall
    t.loc[unlit, list("rgb")] = np.nan
    for c in "rgb":
        t.loc[unlit, f"status_{c}"] = hdr.TOO_DARK
    rep = dynamic_range_report(t, None, t[np.isfinite(t[list("rgb")]).any(axis=1)],
                               exposures={"sample": [0.00025, 0.25]})
    json.dumps(rep, allow_nan=False)
    (e,) = rep["channel_shortfalls"]
    assert (e["capture"], e["channel"], e["led"], e["reason"]) == ("sample", "b", 5, "too dark")
    assert e["blocks"] == dark.sum() and e["fraction_of_lit_blocks"] == pytest.approx(dark.sum() / (n // 2))
    assert e["theta_in_deg"][0] > math.degrees(0.7)
    assert e["exposure_to_fix_s"]["median"] == pytest.approx(1.25, rel=0.01)
    assert e["exposure_to_fix_s"]["p95"] == pytest.approx(0.5 + 0.95 * 1.5, rel=0.01)
    assert e["longest_exposure_factor"] == pytest.approx(e["exposure_to_fix_s"]["p95"] / 0.25, rel=1e-3)
    (none,) = rep["blocks_without_any_channel"]
    assert none["led"] == 9 and none["blocks"] == 10 and none["all_too_dark"] == 10
    assert rep["samples_table"]["channels"]["b"]["missing"] == dark.sum()
    lines = []
    log_dynamic_range(rep, log=lines.append)
    assert any("channel b too dark" in s and "LED 5" in s and "would give 95 % of them a value" in s for s in lines)


# ------------------------------------------------------------------ the twin

def _short_rig(folder: Path, t_max: float) -> Path:
    """The thesis rig with its exposure table cut after ``t_max`` seconds."""
    text = RIG.read_text()
    m = re.search(r"sequence_times_s = \[([^\]]*)\]", text)
    times = [x for x in m.group(1).split(",") if float(x) <= t_max + 1e-12]
    path = folder / "rig.toml"
    path.write_text(text[:m.start()] + f"sequence_times_s = [{', '.join(x.strip() for x in times)}]" + text[m.end():])
    return path


def _capture_and_extract(folder: Path, material: str, t_max: float):
    """Reference and sample captures on the cut rig, extracted by the CLI with --plots."""
    folder.mkdir(parents=True, exist_ok=True)
    rig = _short_rig(folder, t_max)
    sim = ("--rig", rig, "--repeats", 1, "--scale", 0.12, "--spp", 1, "--rotations", 0, "--leds", "9",
           "--no-progress")
    glossrig_cli("simulate", *sim, "--material", "lambert:0.8", "--seed", 6, "--out", folder / "ref")
    glossrig_cli("simulate", *sim, "--material", material, "--seed", 8, "--out", folder / "sample")
    truth = json.loads((folder / "sample" / "truth.json").read_text())
    (folder / "camera.json").write_text(json.dumps(camera_json_from_truth(truth)))
    (folder / "lamps.json").write_text(json.dumps(lamps_json_from_truth(truth)))
    r = glossrig_cli("extract", folder / "sample", "--reference", folder / "ref", "--camera", folder / "camera.json",
                     "--lamps", folder / "lamps.json", "--out", folder / "samples.parquet", "--plots",
                     folder / "plots", "--no-progress")
    return folder / "samples.parquet", json.loads((folder / "plots" / "dynamic_range.json").read_text()), r.stderr


def _lit_blocks(folder: Path) -> int:
    """Blocks (x LED x rotation) the reference measures in every channel with both
    directions above the surface: what a material of full dynamic range keeps."""
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.calibration.lamps import load_lamps
    from glossrig.core.extraction.extract import measure_capture

    t = measure_capture(folder / "ref", load_camera(folder / "camera.json"), load_lamps(folder / "lamps.json")).table
    return int((np.isfinite(t[list("rgb")]).all(axis=1) & (t.theta_in < math.pi / 2)
                & (t.theta_out < math.pi / 2)).sum())


@pytest.mark.mitsuba
def test_twin_ward_with_a_dark_blue_keeps_its_samples_and_albedos(tmp_path):
    """rho_d = (0.45, 0.30, 0.01) with the table cut at 0.25 s: blue is below the noise
    floor in about a tenth of the blocks (dimly lit, grazing). Every block keeps r and g,
    at least 95 % of the lit blocks are samples (dropping whole samples would keep under
    95 %), each channel's rho_d is within 3 %, and extract names blue, LED 9, the angles
    and an exposure longer than the table's."""
    from glossrig.core.fitting.fit import fit_samples
    from glossrig.core.samples import read_samples

    path, rep, stderr = _capture_and_extract(tmp_path, WARD_SPEC, TABLE_MAX_S["ward"])
    df = read_samples(path)
    lit = _lit_blocks(tmp_path)
    ok = valid_channels(df)
    assert len(df) >= 0.95 * lit, (len(df), lit)
    assert ok.all(axis=1).sum() < 0.95 * lit          # whole-sample dropping would have failed
    assert ok[:, 0].mean() > 0.99 and ok[:, 2].mean() < 0.95
    m = fit_samples(df, budget=False)
    for c, truth in zip("rgb", RHO_D):
        assert abs(m.fits[c].params.rho_d / truth - 1) < 0.03, (c, m.fits[c].params)
    y_truth = sum(w * d for w, d in zip(LUMINANCE_WEIGHTS, RHO_D))
    assert abs(m.fits["luminance"].params.rho_d / y_truth - 1) < 0.03
    e = next(e for e in rep["channel_shortfalls"] if (e["capture"], e["channel"]) == ("sample", "b"))
    assert e["reason"] == "too dark" and e["led"] == 9 and e["fraction_of_lit_blocks"] > 0.05
    assert e["longest_exposure_s"] == TABLE_MAX_S["ward"]
    assert TABLE_MAX_S["ward"] < e["exposure_to_fix_s"]["median"] < 30.0
    assert e["theta_in_deg"][1] > 30            # the dim, obliquely lit part of the sample
    assert "sample channel b too dark" in stderr and "LED 9" in stderr
    assert rep["samples_table"]["channels"]["b"]["missing"] == int((~ok[:, 2]).sum())
    assert (tmp_path / "plots" / "dynamic_range.png").is_file()


@pytest.mark.slow
@pytest.mark.mitsuba
@pytest.mark.needs_shared("data/rgl/acrylic_felt_green_rgb.bsdf")
def test_twin_acrylic_felt_green_keeps_its_samples(tmp_path):
    """The real green felt (RGL, Dupuy & Jakob 2018) with the table cut at 1/15 s: blue
    below the floor in about a tenth of the blocks. At least 95 % of the lit blocks are
    samples. The felt is not a Ward material, so its rho_d is the Ward fit of its true
    BRDF (the twin's own evaluation) at the samples' angles, unweighted as the pipeline's
    fit is here: r and g within 3 % of it; b within 3 % of the same fit at the angles
    where b was measured (what the pipeline controls: noise, selection at the floor).
    Against all angles, b differs by what Ward's misfit at the lost grazing angles moves
    it (about 7 %, reported, not asserted)."""
    from glossrig.core.fitting.fit import fit_samples, fit_ward
    from glossrig.core.models.angles import local_direction
    from glossrig.core.samples import read_samples
    from glossrig.twin.measured_brdf import MeasuredBRDF

    path, rep, _ = _capture_and_extract(tmp_path, f"measured:{FELT}", TABLE_MAX_S["felt"])
    df = read_samples(path)
    lit = _lit_blocks(tmp_path)
    ok = valid_channels(df)
    assert len(df) >= 0.95 * lit, (len(df), lit)
    assert ok.all(axis=1).sum() < 0.95 * lit
    T = MeasuredBRDF(FELT).eval(local_direction(df.theta_in.to_numpy(), df.phi_in.to_numpy()),
                                local_direction(df.theta_out.to_numpy(), df.phi_out.to_numpy()))
    m = fit_samples(df, budget=False, use_weight_column=False)
    got = {}
    for k, c in enumerate("rgb"):
        all_rows = fit_ward(df, T[:, k], channel=c, budget=False).params.rho_d
        valid_rows = fit_ward(df[ok[:, k]], T[ok[:, k], k], channel=c, budget=False).params.rho_d
        got[c] = (m.fits[c].params.rho_d, all_rows, valid_rows)
    print({c: [round(x, 5) for x in v] for c, v in got.items()})
    for c in "rg":
        assert abs(got[c][0] / got[c][1] - 1) < 0.03, (c, got[c])
    assert abs(got["b"][0] / got["b"][2] - 1) < 0.03, got["b"]
    assert any(e["channel"] == "b" and e["reason"] == "too dark" for e in rep["channel_shortfalls"])
