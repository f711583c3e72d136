"""The rig's LEDs' own intensity fluctuations (thesis 4.3.3, fig. 4.12): what a healthy rig does.

The thesis shows the LEDs' output changing fast from image to image (high-frequency
fluctuation) and slowly over tens of minutes (low-frequency fluctuation); the pipeline is built
to remove both - neighbour correction within an exposure sequence (eq. 4.32-4.38) and patch
normalisation between images (eq. 4.45-4.50). Fig. 4.12 gives no numbers to read; these are the
magnitudes the project takes for it. They belong to the rig (its LEDs, their driver, the room): the
rig file states them in ``[leds]`` (``jitter``, ``drift_amplitude``, ``drift_period_s``;
:class:`glossrig.core.rig.Lighting`), and these figures are what a rig file without them gets -
the thesis rig's file states the same. The twin simulates the rig's figures by default
(:func:`glossrig.twin.effects.rig_fluctuations`), and diagnose expects them of a healthy rig (an
LED drift is named only where it exceeds the rig's :func:`drift_slope_rms_per_min`,
:func:`glossrig.core.diagnose.frame_gains.drift_test`). A rig whose LEDs are known to drift more
(or less) when healthy - measured, for example, from repeated white-patch images - should say so
in its file.
"""
from __future__ import annotations

import math

#: relative RMS of an LED's output from frame to frame (high-frequency fluctuation)
LED_JITTER = 0.005
#: relative amplitude of an LED's slow drift, 1 + a sin(2 pi t / P + phase) (low-frequency fluctuation)
LED_DRIFT_AMPLITUDE = 0.01
#: the drift's period P, seconds: drawn uniformly in this range, per LED (warm-up, room temperature)
LED_DRIFT_PERIOD_S = (1200.0, 3600.0)


def drift_slope_rms_per_min(amplitude: float = LED_DRIFT_AMPLITUDE,
                            period_s: tuple[float, float] = LED_DRIFT_PERIOD_S) -> float:
    """RMS over LEDs (random phase and period) of the drift's relative slope, per minute, at any
    moment: the slope is a (2 pi / P) cos(2 pi t / P + phase), so its mean square is
    a^2 (2 pi)^2 E[1 / P^2] / 2 with E[1 / P^2] = 1 / (P_lo P_hi) for P uniform on [P_lo, P_hi].
    For the defaults 0.00128 / min."""
    lo, hi = (p / 60.0 for p in period_s)
    return amplitude * 2.0 * math.pi * math.sqrt(0.5 / (lo * hi))
