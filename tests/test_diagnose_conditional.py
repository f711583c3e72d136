"""Explaining away among the frame-space causes (issue 14; :mod:`glossrig.core.diagnose.conditional`):
forward stepwise selection, each remaining cause re-fitted on top of the strongest and kept only
where it still gains significantly on held-out exposures.

Stacks: :func:`test_diagnose.synthetic_frames` (photon-transfer noise, two LEDs, 60 x 80 pixels,
16 exposures). Tolerances:

* A cause conditioned on the true model is a nested parameter whose true value is zero: its
  conditional held-out gain is a null gain. With the fixed EMVA variances of :class:`FrameSet`
  the null gains of frame-space causes stay below :data:`NULL_GAIN` = 0.02 % (the null spread
  the frame-space threshold of :data:`glossrig.core.diagnose.catalogue.THRESHOLDS` was
  calibrated on, quoted there); the pure-noise scale is smaller still, p / N ~ 1e-5 for p = 1
  and N ~ 7.7e4 held-out DN per fold (Akaike's over-fit cost of a parameter).
* The non-linearity re-fitted on top of the black offset recovers its c within 25 % (the
  tolerance of the common non-linearity's own recovery test in tests/test_diagnose.py on the same
  stacks), where alone it absorbs the offset too and comes out ~2 x too large (measured: 0.056
  for c = 0.026 with a 6.1 DN offset).
"""
from __future__ import annotations

import numpy as np
import pytest

from glossrig.core.diagnose.catalogue import THRESHOLDS
from glossrig.core.diagnose.frames import frame_causes

from test_diagnose import synthetic_frames, winner

NULL_GAIN = 2e-4        # upper null spread of a frame-space held-out gain (catalogue.THRESHOLDS' calibration)


def _by_name(causes):
    return {c.name: c for c in causes}


def _table(causes):
    return [(c.name, round(c.gain, 6), c.significant, c.blocked_by, c.params.get("conditional", {}).get("gain"))
            for c in causes]


@pytest.mark.parametrize("seed", [2, 3])
def test_black_offset_explains_shutter_error_and_led_drift_away(seed):
    """A black offset alone (3-15 DN): fitted alone, shutter_error and led_drift also gain far above
    the threshold (both bend the short exposures of dark pixels) - their tests pass, and only their check
    (the gains' structure common to the LEDs per exposure time, which the offset makes) stops them; fitted
    on top of the offset they gain nothing beyond the null spread, so they are blocked by it and the
    offset stays named."""
    b = float(np.random.default_rng(seed).uniform(3, 15))
    causes = frame_causes(synthetic_frames(seed, black_offset=b))
    by = _by_name(causes)
    w = winner(causes)
    assert w is not None and w.name == "black_level_offset" and w.eligible, _table(causes)
    assert abs(w.params["b_dn"] - b) < 1.0
    # the drift's test on the frame gains: alone it passes by far (the failure the conditioning removes), and
    # its check fails: the offset bends every LED's gains alike ...
    d = by["led_drift"]
    assert d.significant_without_check and d.test["chi2"] > 10 * d.test["bound"] and not d.check["passed"]
    for name in ("shutter_error", "led_drift"):
        c = by[name]
        if not c.significant_without_check:   # the shutter's test alone: the offset bends its term less than 4 sigma
            assert c.eligible is False and "conditional" not in c.params
            continue
        cond = c.params["conditional"]
        # ... on top of the offset it is a null parameter: its test, taken again on the frames with the
        # offset undone, does not pass
        assert not c.eligible and c.blocked_by == "black_level_offset", _table(causes)
        assert cond["on"] == ["black_level_offset"] and not cond["significant"]
        assert not cond["test"]["passed"], cond["test"]
        assert "explained by black_level_offset" in c.note


def test_black_offset_and_nonlinearity_both_stay_named():
    """A black offset and a real compressive non-linearity: the non-linearity still gains far above
    the threshold on top of the offset and stays eligible beside it, with its c recovered by the
    joint re-fit; shutter_error and led_drift are explained by the offset, or by the two together."""
    rng = np.random.default_rng(2)
    b, c_true = float(rng.uniform(3, 15)), float(rng.uniform(0.02, 0.06))
    causes = frame_causes(synthetic_frames(2, black_offset=b, nonlin=c_true))
    by = _by_name(causes)
    assert winner(causes).name == "black_level_offset"
    nl = by["sensor_nonlinearity"]
    cond = nl.params["conditional"]
    assert nl.eligible and nl.blocked_by is None, _table(causes)
    assert cond["on"] == ["black_level_offset"] and cond["significant"]
    assert cond["gain"] > THRESHOLDS["frames"][0] and all(g > 0 for g in cond["fold_gains"])
    assert abs(cond["estimate"][0] - c_true) < 0.25 * c_true, (cond, c_true)
    assert abs(cond["estimate"][0] - c_true) < abs(nl.params["c"] - c_true), (cond, nl.params, c_true)
    assert "still gains" in nl.note
    for name in ("shutter_error", "led_drift"):
        c = by[name]
        assert c.significant_without_check, _table(causes)        # alone: it absorbs part of both effects
        # on top of the offset alone, or of the offset and the compression, its own test (the frame gains) or
        # its check (their structure common to the LEDs, which the compression left undone still makes) fails
        assert c.blocked_by in ("black_level_offset", "black_level_offset + sensor_nonlinearity"), _table(causes)
        assert not c.params["conditional"]["significant"]


def test_channel_response_explains_the_common_nonlinearity_away():
    """One channel compresses: the per-channel response wins and the common non-linearity - nested
    in it (all c_k equal) - gains nothing on top of it."""
    c = np.array([0.0, 0.045, 0.0])
    causes = frame_causes(synthetic_frames(60, nonlin=c))
    by = _by_name(causes)
    assert winner(causes).name == "channel_response", _table(causes)
    nl = by["sensor_nonlinearity"]
    assert nl.significant and not nl.eligible and nl.blocked_by == "channel_response", _table(causes)
    assert abs(nl.params["conditional"]["gain"]) < NULL_GAIN
    assert [x.name for x in causes if x.space == "frames" and x.eligible] == ["channel_response"], _table(causes)
