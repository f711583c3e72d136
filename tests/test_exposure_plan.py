"""Exposure planning (issue 8): glossrig.core.radiometry.exposure_plan, the [led_exposures_s] plan
table and `glossrig design exposures`."""
from __future__ import annotations

import itertools
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from glossrig.core.errors import InputError
from glossrig.core.radiometry.exposure_plan import plan_exposures, plan_led, rate_bins
from glossrig.core.design.fisher import HdrNoise
from glossrig.core.models.materials import parse_material
from glossrig.core.rig import load_rig
from glossrig.hardware.plan import THESIS_OVERHEAD_S, THESIS_SEQUENCE_S, load_plan

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "scenes/thesis_rig.toml"


@pytest.fixture(scope="module")
def rig():
    return load_rig(RIG)


@pytest.fixture(scope="module")
def noise(rig):
    return HdrNoise.from_rig(rig, led_rel=0.0)


def rates_log_uniform(lo, hi, n=4000, seed=0):
    return np.exp(np.random.default_rng(seed).uniform(np.log(lo), np.log(hi), n))


def requirement_met(times, rates, noise, target, margin, tail=2.0):
    """Re-check a plan pixel by pixel (not through the planner's bins)."""
    r = np.asarray(rates)
    hi, lo = r * margin, r / margin
    full = noise.sensor_relative(lo, THESIS_SEQUENCE_S, hi)
    got = noise.sensor_relative(lo, times, hi)
    bound = np.maximum(target, tail * full)
    return bool(np.all(got[np.isfinite(full)] <= bound[np.isfinite(full)] * (1 + 1e-9)))


def test_plan_meets_the_noise_target_and_keeps_the_peak_unsaturated(noise):
    rates = rates_log_uniform(50.0, 5e6)
    times, st = plan_led(rates, THESIS_SEQUENCE_S, noise, target=0.03, margin=1.1, overhead_s=THESIS_OVERHEAD_S)
    assert requirement_met(times, rates, noise, 0.03, 1.1)
    cap = noise.usable_fraction * noise.saturation_e
    assert min(times) * rates.max() * 1.1 < cap              # the brightest pixel has an unsaturated shot
    assert st["unmeasured_fraction"] == st["unmeasured_fraction_full"] == 0.0
    assert len(times) < 8                                   # far fewer than the 18 of table 4.1


def test_plan_is_the_cheapest_subset_of_a_small_table(noise):
    table = (0.004, 0.0166, 0.0666, 0.25, 1.0, 4.0, 15.0)
    rates = rates_log_uniform(300.0, 3e5, seed=2)
    oh = 5.0
    times, _ = plan_led(rates, table, noise, target=0.03, margin=1.1, overhead_s=oh)
    # brute force over every subset, checked on the planner's conservative bins
    hi, lo, _ = rate_bins(rates, 1.1)
    full_table = noise.sensor_relative(lo, table, hi)
    best = min(sum(s) + oh * len(s) for k in range(1, len(table) + 1) for s in itertools.combinations(table, k)
               if np.all(noise.sensor_relative(lo, s, hi) <= np.maximum(0.03, 2 * full_table) * (1 + 1e-9))
               and np.all(((hi[None] * np.array(s)[:, None] < noise.usable_fraction * noise.saturation_e)
                           & (lo[None] * np.array(s)[:, None] >= 0.002 * noise.saturation_e)).any(axis=0)))
    assert sum(times) + oh * len(times) == pytest.approx(best, rel=1e-12)


def test_tighter_target_costs_more_time(noise):
    rates = rates_log_uniform(100.0, 1e6, seed=3)
    cost = [sum(t) + THESIS_OVERHEAD_S * len(t) for t in
            (plan_led(rates, THESIS_SEQUENCE_S, noise, target=x, overhead_s=THESIS_OVERHEAD_S)[0]
             for x in (0.05, 0.03, 0.015))]
    assert cost[0] <= cost[1] <= cost[2]
    assert cost[2] > cost[0]


def test_bad_inputs_are_refused(noise):
    with pytest.raises(InputError, match="noise target"):
        plan_led([1.0], THESIS_SEQUENCE_S, noise, target=0.0)
    with pytest.raises(InputError, match="margin"):
        plan_led([1.0], THESIS_SEQUENCE_S, noise, target=0.03, margin=0.5)
    with pytest.raises(InputError, match="measured"):
        plan_exposures(load_rig(RIG), parse_material("measured:x.bsdf"), [6], [0.0], scale=0.05, overhead_s=1.0)


def test_thesis_rig_plan_for_a_table_9_1_material_fits_in_15_minutes(rig):
    p = plan_exposures(rig, parse_material("sample_2_6"), rig.select_leds("middle"), [0.0], scale=0.1,
                       overhead_s=THESIS_OVERHEAD_S)
    full = 8 * 3 * (sum(THESIS_SEQUENCE_S) + 18 * THESIS_OVERHEAD_S)      # the thesis plan, one rotation
    assert p.time_s_per_rotation() <= 15 * 60 < full
    assert all(e.worst_noise <= 0.03 * (1 + 1e-9) for e in p.leds)
    assert all(e.unmeasured_fraction <= e.unmeasured_fraction_full for e in p.leds)
    # a brighter material starts with shorter exposures
    bright = plan_exposures(rig, parse_material("lambert:0.8"), [8], [0.0], scale=0.1, overhead_s=THESIS_OVERHEAD_S)
    dark = plan_exposures(rig, parse_material("lambert:0.05"), [8], [0.0], scale=0.1, overhead_s=THESIS_OVERHEAD_S)
    assert min(bright.leds[0].exposures_s) < min(dark.leds[0].exposures_s)


def test_cli_writes_a_plan_the_hardware_layer_loads(tmp_path):
    out = tmp_path / "plan.toml"
    r = subprocess.run([sys.executable, "-m", "glossrig.cli.main", "design", "exposures", "--rig", str(RIG),
                        "--material", "sample_2_6", "--leds", "6,10", "--rotations=0,45", "--scale", "0.1",
                        "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    plan = load_plan(out)
    assert plan.leds == (6, 10) and plan.rotations == (0.0, 45.0) and plan.repeats == 1
    seq = [s for s in plan.shots() if s.role == "sequence"]
    for led in (6, 10):
        times = tuple(s.exposure_s for s in seq if s.leds == (led,) and s.rotation == 0.0)
        assert times == plan.led_exposures_s[led] and 0 < len(times) < 18
    assert len(seq) == 2 * sum(len(v) for v in plan.led_exposures_s.values())
    assert plan.estimate().estimate_s < 2 * 2 * (sum(THESIS_SEQUENCE_S) + 18 * THESIS_OVERHEAD_S)
    assert "time per rotation" in r.stdout


def test_plan_loader_checks_led_exposures(tmp_path):
    base = f'rig = "{RIG}"\nsample = "x"\nleds = [6, 10]\n'
    p = tmp_path / "p.toml"
    p.write_text(base + "[led_exposures_s]\n7 = [1.0]\n")
    with pytest.raises(InputError, match="not one of the plan's LEDs"):
        load_plan(p)
    p.write_text(base + "[led_exposures_s]\n6 = [1.0, -2.0]\n")
    with pytest.raises(InputError, match="led_exposures_s.6"):
        load_plan(p)
    p.write_text(base + "exposures_s = [0.5]\n[led_exposures_s]\n6 = [1.0, 2.0]\n")
    shots = [(s.leds, s.exposure_s) for s in load_plan(p).shots() if s.role == "sequence" and s.repeat == 0
             and s.rotation == load_plan(p).rotations[0]]
    assert shots == [((6,), 1.0), ((6,), 2.0), ((10,), 0.5)]


# ------------------------------------------------ requirement 3: LED jitter and neighbour correction

def _jittered_stack(rates_e, times, noise, gains):
    """Noise-free linearised frames (fractions of the range) of pixels at ``rates_e``
    (e-/s), frame k scaled by its LED gain ``gains[k]``; clipped at 1 as a sensor does."""
    t = np.asarray(times, float)[:, None, None]
    y = np.asarray(gains, float)[:, None, None] * rates_e[None] * t / noise.saturation_e
    return np.minimum(y, 1.0).astype(np.float32)


@pytest.mark.parametrize("times", [(0.0666, 0.25, 2.0, 15.0), (0.25, 0.5, 1.0, 2.0, 4.0, 15.0),
                                   (0.001, 0.004, 0.0333, 0.25, 2.0, 15.0), (0.004, 0.125, 2.0, 15.0)])
def test_neighbour_links_predict_the_pipelines_correction(noise, times):
    """Which frames hdr.neighbour_correct ties to the reference, predicted from the rates
    alone: the same frames as the pipeline finds on the (noise-free, jittered) images."""
    from glossrig.core.radiometry import hdr
    from glossrig.core.radiometry.exposure_plan import neighbour_links

    rates = rates_log_uniform(100.0, 2e6, n=60 * 60, seed=5).reshape(60, 60)
    gains = 1 + 0.005 * np.random.default_rng(1).standard_normal(len(times))
    _, rep = hdr.neighbour_correct(_jittered_stack(rates, times, noise, gains), times)
    r = rates.ravel()
    linked, chain = neighbour_links(times, r, r, np.ones(r.size), noise)          # one pixel per "bin"
    got = np.array([k == rep.reference or rep.partner[k] >= 0 for k in range(len(times))])
    assert linked.tolist() == got.tolist(), (rep.pixels, rep.skipped)
    assert np.all(np.isfinite(chain[linked])) and np.all(np.isinf(chain[~linked]))


def test_gain_error_matches_monte_carlo_of_the_pipeline(noise):
    """The predicted frame-gain error of each pixel's HDR value (gain_relative) against
    the pipeline (neighbour_correct + hdr_ml, then divided by the reference frame's gain,
    as patch normalisation does) over 300 jitter draws, noise-free sensor."""
    from glossrig.core.radiometry import hdr
    from glossrig.core.radiometry.exposure_plan import gain_relative, neighbour_links

    times = (0.004, 0.125, 2.0, 15.0)                       # 30x and 16x apart: frames 0 and 1 cannot link
    rates = rates_log_uniform(300.0, 1e5, n=80 * 80, seed=7).reshape(80, 80)
    hi = lo = rates.ravel()                                  # one pixel per "bin"
    linked, chain = neighbour_links(times, hi, lo, np.ones(hi.size), noise)
    assert not linked[:2].any() and linked[2:].all()
    t = np.asarray(times)[:, None]
    usable = hi[None] * t < noise.usable_fraction * noise.saturation_e
    var = (lo[None] * t + noise.dark_current_e_s * t + noise.read_noise_e ** 2 + noise.conversion_gain ** 2 / 12) / t ** 2
    pred = gain_relative(np.where(usable, 1 / var, 0.0), linked, np.zeros(len(times)), 0.005)
    model = hdr.NoiseModel(electrons_full_scale=noise.saturation_e,
                           read_sigma=noise.read_noise_e / noise.saturation_e)
    rng = np.random.default_rng(3)
    errs = []
    for _ in range(300):
        g = 1 + 0.005 * rng.standard_normal(len(times))
        y, rep = hdr.neighbour_correct(_jittered_stack(rates, times, noise, g), times)
        r = hdr.hdr_ml(y, times, model).rate.ravel()
        errs.append(r * noise.saturation_e / rates.ravel() / g[rep.reference] - 1)
    mc = np.nanstd(np.array(errs), axis=0)
    ok = np.isfinite(mc) & np.isfinite(pred)
    assert ok.sum() > 5000
    assert np.median(np.abs(mc[ok] / pred[ok] - 1)) < 0.1
    assert pred[ok].max() > 0.005 and pred[ok].min() < 0.002      # some pixels lean on unlinked frames, some hardly


def test_jitter_requirement_ties_the_frames_together(noise):
    """With the LED jitter in the target the plan costs more and its frames are tied to
    the reference wherever the whole table's are; without it a 4-shot plan leaves most
    frames to their own gain."""
    rates = rates_log_uniform(300.0, 3e5, n=20000, seed=11)
    t0, s0 = plan_led(rates, THESIS_SEQUENCE_S, noise, target=0.03, overhead_s=THESIS_OVERHEAD_S)
    t1, s1 = plan_led(rates, THESIS_SEQUENCE_S, noise, target=0.03, overhead_s=THESIS_OVERHEAD_S, jitter=0.005)
    assert sum(t1) + THESIS_OVERHEAD_S * len(t1) > sum(t0) + THESIS_OVERHEAD_S * len(t0)
    assert s1["gain_noise_worst"] <= max(0.001, 2 * s1["gain_noise_worst_full"]) * (1 + 1e-9)
    _, s0j = plan_led(rates, t0, noise, target=0.03, overhead_s=THESIS_OVERHEAD_S, jitter=0.005)
    assert s0j["gain_noise_worst"] > 3 * s1["gain_noise_worst"]
    assert requirement_met(t1, rates, noise, 0.03, 1.1)       # the sensor requirement still holds
