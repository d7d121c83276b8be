"""Saturation found in the data of a sweep: full well before the ADC, the ADC, or not reached.

The sweeps here are written by the test from the photon-transfer relation itself
(var = K S + r^2 with K = 0.8 DN/e-, read noise 2 DN), clipped by a full well in a
form the package does not use (a smooth per-pixel ceiling, so the mean bends into
its plateau over one setting and the variance falls), not by the simulator.
"""

from __future__ import annotations

import numpy as np

from pipeline.radiometry.saturation import saturated_settings

K_DN_PER_E = 0.8
READ_DN = 2.0


def _sweep(full_well_dn: float | None, times=(8.33e-3, 16.67e-3, 33.33e-3, 66.67e-3, 0.1, 0.2, 0.5), rate=60000.0,
           nonlinearity=0.0):
    rng = np.random.default_rng(4)
    signal, variance = [], []
    for t in times:
        s = rate * t * (1 - nonlinearity * rate * t / 30000.0)
        pixels = s + rng.normal(0, np.sqrt(K_DN_PER_E * s + READ_DN**2), 20000)
        if full_well_dn is not None:
            # a soft ceiling per pixel (pixels differ by 1 % in well depth)
            well = full_well_dn * (1 + 0.01 * rng.standard_normal(pixels.size))
            pixels = np.minimum(pixels, well)
        signal.append(pixels.mean())
        variance.append(np.var(pixels))
    return np.array(times), np.array(signal), np.array(variance)


def test_full_well_before_the_adc_is_found():
    t, s, v = _sweep(full_well_dn=15000.0, rate=100000.0)
    flags = saturated_settings(t, s, v, 0.5, 0.5)
    # 100000 DN/s: 0.2 s (20000 DN) and 0.5 s exceed the 15000 DN well, 0.1 s (10000 DN) does not
    assert flags.tolist() == [False, False, False, False, False, True, True]


def test_nothing_saturates_below_the_well():
    t, s, v = _sweep(full_well_dn=None)
    assert not saturated_settings(t, s, v, 0.5, 0.5).any()


def test_a_nonlinearity_is_not_taken_for_saturation():
    # the response bends by 24 % at the top of the sweep (docs/design.md: the published camera at ISO 100)
    t, s, v = _sweep(full_well_dn=None, rate=20000.0, nonlinearity=0.24 * 30000.0 / 10000.0)
    assert s[-1] / (20000.0 * t[-1]) < 0.8
    assert not saturated_settings(t, s, v, 0.5, 0.5).any()


def test_clipped_settings_and_those_above_are_saturated_in_any_order():
    t, s, v = _sweep(full_well_dn=None)
    clipped = np.array([False, False, False, False, True, False, False])
    order = np.array([6, 2, 0, 4, 1, 5, 3])
    flags = saturated_settings(t[order], s[order], v[order], 0.5, 0.5, clipped=clipped[order])
    assert flags.tolist() == [t[i] >= 0.1 for i in order]
