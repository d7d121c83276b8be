"""Normalisation of the signal by the exposure parameters, Eq. (2).

Larouche et al. (2024), Section 2.1: every image is dark subtracted and
divided by the exposure time and the gain before any radiometric step,

    y_DN = (y_DN,raw - y_DN,bias) / (t_int * S_ISO * 0.01),

in ADU/s at ISO 100; "0.01 scaling S_ISO relative to x1 instead of x100",
i.e. the gain is ISO / 100 and equals 1 at ISO 100.  The dark model and the
linearity model use the same gain (``b0 + b1 (gain - 1) + D gain t``,
``y = rate * gain * t``).

Units: exposure time in s, ISO as written by the camera, DN in ADU.
"""

from __future__ import annotations

import numpy as np

__all__ = ["UNIT_GAIN_ISO", "gain_from_iso", "exposure_gain_s", "dn_per_second"]

#: ISO speed at which the gain S_ISO * 0.01 of Eq. (2) is 1.
UNIT_GAIN_ISO = 100.0


def gain_from_iso(iso):
    """Gain relative to ISO 100, S_ISO * 0.01 of Eq. (2): ISO / 100 (dimensionless).

    E.g. ISO 100 -> 1, ISO 400 -> 4, ISO 3200 -> 32.

    Parameters
    ----------
    iso : float, numpy.ndarray or pandas.Series
        ISO setting as written by the camera.

    Returns
    -------
    float, numpy.ndarray or pandas.Series
        The gain g (dimensionless), of the type of ``iso``.
    """
    return iso / UNIT_GAIN_ISO


def exposure_gain_s(exposure_s, iso):
    """Denominator of Eq. (2), t_int * S_ISO * 0.01, in s (seconds at ISO 100).

    E.g. 0.1 s at ISO 400 -> 0.4 s.  Dividing a dark-subtracted DN by it
    gives ADU/s at ISO 100.

    Parameters
    ----------
    exposure_s : float or array_like
        Exposure (integration) time t_int (s).
    iso : float or array_like
        ISO setting.

    Returns
    -------
    float or numpy.ndarray
        t_int x ISO / 100 (s), broadcast over the inputs.
    """
    return exposure_s * gain_from_iso(iso)


def dn_per_second(dn_raw, dn_bias, exposure_s, iso):
    """Eq. (2): dark-subtracted DN normalised by exposure and gain, ADU/s at ISO 100.

    y = (dn_raw - dn_bias) / (exposure_s * iso / 100); e.g.
    (2000 - 800) ADU over 0.1 s at ISO 100 -> 12000 ADU/s.

    Parameters
    ----------
    dn_raw : float or array_like
        Raw reading (DN).
    dn_bias : float or array_like
        Dark level to subtract (DN).
    exposure_s : float or array_like
        Exposure time (s).
    iso : float or array_like
        ISO setting.

    Returns
    -------
    numpy.ndarray
        Signal rate y (DN s-1 at ISO 100), broadcast over the inputs.
    """
    return (np.asarray(dn_raw, dtype=float) - np.asarray(dn_bias, dtype=float)) / exposure_gain_s(
        np.asarray(exposure_s, dtype=float), np.asarray(iso, dtype=float)
    )
