"""One function per equation of Larouche et al. (2024), each against a value worked by hand or printed in the paper.

The README's table "Equations and the functions that implement them" lists
the same functions; the stages call these and keep no second copy.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pipeline.radiometry import absolute, exposure
from pipeline.radiometry.exposure import dn_per_second, exposure_gain_s, gain_from_iso


# ----------------------------------------------------------------------------- Eq. (2)
def test_gain_is_iso_over_100():
    # "0.01 scaling S_ISO relative to x1 instead of x100" (Section 2.1)
    assert gain_from_iso(100) == 1.0
    assert np.array_equal(gain_from_iso(np.array([200.0, 400.0, 3200.0])), [2.0, 4.0, 32.0])
    assert list(gain_from_iso(pd.Series([100.0, 800.0]))) == [1.0, 8.0]


def test_exposure_gain_product_table1_setting():
    # Table 1: 0.1 s at "ISO x 0.01 gain" 1.0 -> 0.1 s; 0.05 s at ISO 400 -> 0.2 s
    assert exposure_gain_s(0.1, 100.0) == pytest.approx(0.1, rel=1e-15)
    assert exposure_gain_s(0.05, 400.0) == pytest.approx(0.2, rel=1e-15)


def test_dn_per_second_hand_values_and_single_home():
    # (6900 - 800) ADU / (0.1 s * 1) = 61000 ADU/s, Table 1's red y_DN
    assert dn_per_second(6900.0, 800.0, 0.1, 100.0) == pytest.approx(61e3)
    # the same signal at ISO 200 and half the exposure: same y_DN
    assert dn_per_second(6900.0, 800.0, 0.05, 200.0) == pytest.approx(61e3)
    assert absolute.dn_per_second is exposure.dn_per_second
