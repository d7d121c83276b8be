"""Field match-up stage: the calibration bundle applied to sky frames against a reference radiometer
(Larouche et al. 2024, Sections 2.9 and 3.8, Eq. 12, Fig. 10; Burggraaff et al. 2022, Section 2.6).

For the lens that ``field/frames.csv`` names (the one at the zenith), each
frame is decoded once and checked against the bundle (camera, ISO, exposure);
the measurement chain (:func:`pipeline.bundle.apply.band_radiance`, as one :class:`~pipeline.bundle.apply.BandChain` per band) runs on the crop
of the band images that holds the mask only: theta <= ``field.mask_half_angle_deg``
on the bundle's in-air theta map, or the ``field.min_mask_pixels`` pixels
nearest the axis when the mask holds fewer. Pixels flagged saturated, hot or
outside the image circle are left out. Per frame and band: the mask mean
radiance, its random standard error (the chain's random sigma, independent
between pixels: sqrt(sum sigma^2) / n), its systematic sigma (the mean of the
chain's systematic sigma: common to all frames of a band, kept apart and not
in the match-up weights) and the spatial spread in the mask (standard
deviation of the pixels). The middle frame also goes through the chain over
the whole lens and is binned on the sphere (``field.sky_map_grid_deg``).

Time: DateTimeOriginal (+ SubSecTimeOriginal) is the camera's local clock;
UTC = local - ``camera_clock_utc_offset_h`` (site.yaml).

Reference: samples in [t - w/2, t + w/2] around each frame's UTC time t
(w = ``field.reference_window_s``): mean, standard deviation and count per
channel (drop-outs, NaN, are left out); a frame with fewer than
``field.min_reference_samples`` samples is not a match-up (counted, listed).
The reference's white noise per sample is estimated from successive
differences (von Neumann: var = mean(diff^2) / 2, insensitive to slow
changes); the noise of the window mean is that over the count, and the
reference's true variation within the window (a camera frame samples an
instant, the reference mean a window) is the variance of the samples about
the window's straight line minus the white noise: a steady trend leaves a
centred mean equal to the value at the centre, clouds and steps do not. ``dref_dt`` is the slope of a straight line fitted to the window's
samples (the series smoothed over the window, differentiated).

Two comparisons per band:

* ``nearest``: the channel nearest the band's effective wavelength (bundle);
* ``convolved``: the channels treated as samples of the spectrum at their
  centre wavelengths (10 nm FWHM), interpolated linearly in wavelength onto
  the measured response's wavelengths that lie inside the channels' span and
  averaged with Eq. (3), sum S L / sum S (trapezoid weights, as the spectral
  stage's effective wavelength). Response wavelengths outside the span are
  dropped (no extrapolation); the fraction of the response there is stored
  (``response_outside_reference_fraction``). The convolved value is linear
  in the channel values, so it is formed once per reference sample.

Per band and comparison, every statistic of :mod:`pipeline.stats.matchup`
(MUPD, zeta, SSPB, r, RMSE about the fit and the 1:1 line with paired
bootstrap intervals; OLS and errors-in-both lines) on the match-ups; the
ODR weights are the camera's random standard error and the reference's
window uncertainty (noise of the mean and variation within the window).

Observation table (``obs_frame``, the diagnostics read it like any stage's): one row per match-up and
band; base model camera = k_b x reference (one scale per band, fitted with
:func:`pipeline.stages.observations.fit_with_effects`); ``sigma_dn`` adds the
camera's random standard error, k_b times the reference's window
uncertainty, the mask's sampling term (:func:`mask_sampling_sigma`) and its pointing term
(:func:`mask_pointing_sigma`: the sky's gradient at the mask, fitted to the frame's pixels, times
the bundle's pointing uncertainty) in quadrature, k_b the median camera/reference ratio of the band
(fixed before the fit). With ``spectral_mismatch`` in ``model.effects`` the
prediction is the band-convolved reference, the nearest channel otherwise.
With ``clock_offset`` in the model the camera clock offset c (camera - UTC, s)
is fitted by shifting the reference series: the chi-square of the base model
(profiled over the band scales, each frame's sigma at that shift: the camera's random standard
error, the mask's sampling and pointing terms and the reference's window uncertainty, as the match-ups') is
evaluated on a grid of ``field.clock_offset_grid_s`` steps within +/-
``field.clock_offset_search_s``, minimised per point over the frames that
are match-ups at that shift (reduced chi-square), refined by a bounded scalar
minimisation within one grid step; the standard error is sqrt(2 / chi2'')
from the curvature of a parabola fitted to the total chi-square at five
points one grid step apart around the minimum, times sqrt(reduced chi2) when
that exceeds 1. The reference is then taken at t - c. The profile's interval at
``field.confidence_level``: scanned outward from c in steps of the reference's
sample spacing, the last offsets where the chi-square stays within
chi2_1(level) x the reduced chi-square (when above 1) of its value at c, a
whole grid step beyond lying above (the curve is jagged at the scale of one
sample). Without ``clock_offset`` in the model the same profile is computed
and only recorded, nothing shifted: the curve (``clock_search_reduced_chi2``),
``clock_profile_offset_s`` and its bounds, and constant ``obs_frame`` columns
``clock_profile_offset_s``, ``_se_s``, ``_low_s``, ``_high_s`` from which the
diagnostics' ``clock_offset`` candidate takes its amplitude (its linearised
signature, -k_b dref/dt, holds only for shifts short against the sky's
changes; on the tiny camera's hour with the reference 40 s behind, the
linearised coefficient reads 15 s). On the tiny fixture the profile costs
about 0.03 s of a 1 s stage (the grid is evaluated in one windowed pass per
band).

Scale closure (``obs_scale``, :mod:`pipeline.radiometry.field_scale`): the band scales k_b are the
calibration's absolute claim, which the frame table's free scales do not test. One row per band: ln k_b
against the predicted 0 (k_b = 1 against the reference the model compares with), its noise the relative
budget of the fit's standard error, the chain's systematic sigma over the mask (R^-1, roll-off, flat
field, response corrections), the reference radiometer's calibration (site.yaml
``reference.calibration_relative_sigma``) and, with ``spectral_mismatch``, the convolution's own
uncertainty; and the covariates with which the diagnostics predict the share of each effect the model
lacks (the field frames' exposure, ISO and level against the absolute experiment's, from the bundle).

Stray light from the sun (``stray_light``): every frame counts the band
pixels of the lens near full scale (``field.sun_seen_fraction_of_full_scale``;
the sun is seen with ``field.sun_seen_min_pixels`` or more) and the match-up
table carries the covariate of :mod:`pipeline.radiometry.sun_glare` (band
clear-sky direct irradiance x seen x (Z_ref / Z)^q, the mask at the zenith
being Z from the sun). With the effect in the model its one coefficient is
fitted with the band scales, reported (``stray_light_glare_sr``, sr-1, and
the fitted glare in the mask per frame and band) and taken out of the band
scales; a coefficient ``field.stray_light_negative_sigma`` standard errors
below zero stops the stage (stray light only adds light).
"""

from __future__ import annotations

import importlib
import logging
import threading
from datetime import timedelta
from statistics import NormalDist

import numpy as np
import pandas as pd
import xarray as xr

from pipeline.bundle.apply import EXCLUDED_FROM_GRID, BandChain, bin_on_sphere, check_frame, sphere_coordinates
from pipeline.io.bands import BANDS
from pipeline.io.dataset import REFERENCE_CALIBRATION_RELATIVE_SIGMA, read_reference_radiometer, read_site
from pipeline.errors import ImpossibleResult, InputError
from pipeline.stats.fitting import base_design
from pipeline.io.frames import iter_frames
from pipeline.stages.observations import fit_with_effects, table_to_dataset
from pipeline.radiometry import measurement as mm
from pipeline.radiometry.field_scale import (SCALE_TERMS, mismatch_prediction_relative_sigma,
                                             nearest_channel_relative_sigma, scale_relative_sigma)
from pipeline.radiometry.spectral import band_weights
from pipeline.radiometry.sun_glare import band_direct_irradiance, sun_glare_covariate

log = logging.getLogger("pipeline.stages.field")

STAGE = "field"
MEDIUM = "air"
COMPARISONS = ("nearest", "convolved")
RAD = "W sr-1 m-2 nm-1"
#: the clock-offset profile's columns of ``obs_frame`` without clock_offset in the model (constant over the rows;
#: read by :meth:`pipeline.effects.field.ClockOffset.amplitude`) -> key of :func:`fit_clock_offset`'s result
CLOCK_PROFILE_COLUMNS = {"clock_profile_offset_s": "offset_s", "clock_profile_offset_se_s": "offset_se_s",
                         "clock_profile_offset_low_s": "offset_low_s", "clock_profile_offset_high_s": "offset_high_s"}
CLOCK_PROFILE_LONG_NAMES = {
    "clock_profile_offset_s": "camera clock minus UTC at the minimum of the clock-offset profile (not applied)",
    "clock_profile_offset_se_s": "its standard error (chi-square curvature, times sqrt(reduced chi-square) when > 1)",
    "clock_profile_offset_low_s": "lower bound of the profile's interval at field.confidence_level (NaN: not found)",
    "clock_profile_offset_high_s": "upper bound of the profile's interval at field.confidence_level (NaN: not found)",
    "ref_at_clock_profile": "the reference window mean at the profile's offset (the clock_offset candidate's secant)",
}
#: flags that keep a pixel out of the mask mean
MASK_EXCLUDED = mm.FLAG_SATURATED | mm.FLAG_HOT | mm.FLAG_OUTSIDE_IMAGE_CIRCLE


# --------------------------------------------------------------------------- the mask
def field_masks(bundle: xr.Dataset, lens: str, half_angle_deg: float, min_pixels: int):
    """Per band the mask (theta <= half angle, or the ``min_pixels`` nearest the axis), the sky around it and the crop.

    The sky around the mask, where :func:`sky_gradient` fits the radiance's gradient, is theta <= h + p:
    the mask's half angle h (the largest theta in it) and one band-pixel pitch p = h sqrt(pi / n) (n
    pixels in the mask). Per band also the direction components theta cos(phi), theta sin(phi) (degree)
    of the bundle's map and the pointing uncertainty of the mask: the bundle's theta_deg_sigma at the
    pixel nearest the axis (how far from the zenith the direction the bundle calls the axis may lie;
    0 when the bundle has no uncertainty). The crop holds the masks and the sky around them.

    Searched in a square about the image circle's centre, four times the mask's share of the field wide,
    grown until the masks and the sky around them touch none of its edges (the whole band image is
    some 3 million pixels at the real camera's resolution; the crop about a sixth of them).

    Parameters
    ----------
    bundle : xarray.Dataset
        The calibration bundle (its in-air ``theta_deg``, ``phi_deg`` and ``theta_deg_sigma`` maps, degree;
        ``half_fov_deg`` and ``circle_radius_px``).
    lens : str
        The zenith lens.
    half_angle_deg : float
        The mask's half angle about the axis, degree.
    min_pixels : int
        The fewest band pixels a mask holds.

    Returns
    -------
    masks : dict[str, numpy.ndarray]
        Band -> boolean mask of the crop's shape.
    window : tuple[slice, slice]
        The crop's rows and columns in the band image.
    around : dict[str, tuple]
        Band -> (sky-around mask of the crop, x_deg, y_deg maps of the crop in degree, pointing uncertainty in
        degree).
    """
    g = bundle.sel(lens=lens, medium=MEDIUM, band="G")
    shape = g["theta_deg"].shape
    half_fov = float(g["half_fov_deg"]) if np.isfinite(float(g["half_fov_deg"])) else 90.0
    radius = float(g["circle_radius_px"]) if np.isfinite(float(g["circle_radius_px"])) else max(shape) / 2.0
    half = max(8, int(np.ceil(4.0 * radius * half_angle_deg / half_fov)))
    while True:
        found = _masks_in(bundle, lens, half_angle_deg, min_pixels, _search_window(g, shape, half))
        if found is not None:
            return found
        half *= 2


def _search_window(g, shape, half: int) -> tuple[slice, slice]:
    """The square of half side ``half`` about the image circle's centre (the whole image for a region without one)."""
    xc, yc = float(g["circle_xc_px"]), float(g["circle_yc_px"])
    if not (np.isfinite(xc) and np.isfinite(yc)) or 2 * half >= max(shape):
        return slice(0, shape[0]), slice(0, shape[1])
    return (slice(max(int(yc) - half, 0), min(int(yc) + half + 1, shape[0])),
            slice(max(int(xc) - half, 0), min(int(xc) + half + 1, shape[1])))


def _masks_in(bundle, lens, half_angle_deg, min_pixels, search):
    """:func:`field_masks` within the ``search`` window: None when what it finds touches an edge of the window
    that is not the image's (a larger window is needed)."""
    full, around = {}, {}
    shape = bundle["theta_deg"].shape[-2:]
    whole = search == (slice(0, shape[0]), slice(0, shape[1]))
    for band in BANDS:
        g = bundle.sel(lens=lens, medium=MEDIUM, band=band)
        theta = g["theta_deg"].values[search].astype(float)
        y = np.arange(search[0].start, search[0].stop)[:, None]
        x = np.arange(search[1].start, search[1].stop)[None, :]
        outside = np.hypot(x - float(g["circle_xc_px"]), y - float(g["circle_yc_px"])) > float(g["circle_radius_px"])
        theta = np.where(outside | ~np.isfinite(theta), np.inf, theta)
        mask = theta <= half_angle_deg
        if mask.sum() < min_pixels:
            order = np.argsort(theta, axis=None)[:min_pixels]
            mask = np.zeros(theta.shape, bool)
            mask.flat[order] = True
            mask &= np.isfinite(theta)
        if not mask.any():
            if not whole:
                return None
            raise InputError(None, f"lens {lens}, band {band}: the bundle's theta map has no pixel near the axis")
        full[band] = mask
        h = float(theta[mask].max())
        axis = np.unravel_index(np.argmin(theta), theta.shape)
        pointing = float(g["theta_deg_sigma"].values[search][axis]) if "theta_deg_sigma" in g else 0.0
        around[band] = (theta <= h + h * np.sqrt(np.pi / mask.sum()), theta, pointing if np.isfinite(pointing) else 0.0)
    union = np.logical_or.reduce([a[0] for a in around.values()] + list(full.values()))
    rows, cols = np.flatnonzero(union.any(axis=1)), np.flatnonzero(union.any(axis=0))
    edge = (rows[0] == 0 and search[0].start > 0) or (rows[-1] == union.shape[0] - 1 and search[0].stop < shape[0]) \
        or (cols[0] == 0 and search[1].start > 0) or (cols[-1] == union.shape[1] - 1 and search[1].stop < shape[1])
    if edge and not whole:
        return None
    crop = (slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1))
    window = (slice(search[0].start + crop[0].start, search[0].start + crop[0].stop),
              slice(search[1].start + crop[1].start, search[1].start + crop[1].stop))
    out = {}
    for band, (near, theta, pointing) in around.items():
        # the direction components on the crop only
        phi = np.radians(bundle["phi_deg"].sel(lens=lens, medium=MEDIUM, band=band).values[window].astype(float))
        t = theta[crop]
        out[band] = (near[crop], t * np.cos(phi), t * np.sin(phi), pointing)
    return {band: m[crop] for band, m in full.items()}, window, out


def mask_statistics(m: mm.Measured, mask: np.ndarray) -> dict:
    """Mean, random standard error, systematic sigma and spatial spread of the chain's radiance in the mask.

    Parameters
    ----------
    m : pipeline.radiometry.measurement.Measured
        The measurement chain's output for the crop: value, random and systematic sigmas, flags per pixel.
    mask : numpy.ndarray
        Boolean, the crop's shape: the mask. Pixels flagged as excluded or not finite are left out.

    Returns
    -------
    dict
        ``mean`` (the mask's mean radiance, in the chain's units), ``random_se`` (its random standard error),
        ``systematic`` (the pixels' mean systematic sigma), ``spread`` (standard deviation of the pixels, ddof 1),
        ``n`` (pixels used) and ``n_saturated``; NaN values when no pixel is usable.
    """
    good = mask & ((m.flags & MASK_EXCLUDED) == 0) & np.isfinite(m.value)
    n = int(good.sum())
    if n == 0:
        return {"mean": np.nan, "random_se": np.nan, "systematic": np.nan, "spread": np.nan, "n": 0,
                "n_saturated": int((mask & ((m.flags & mm.FLAG_SATURATED) > 0)).sum())}
    v = m.value[good]
    return {"mean": float(v.mean()), "random_se": float(np.sqrt(np.sum(m.random_sigma[good] ** 2)) / n),
            "systematic": float(m.systematic_sigma[good].mean()),
            "spread": float(v.std(ddof=1)) if n > 1 else np.nan, "n": n,
            "n_saturated": int((mask & ((m.flags & mm.FLAG_SATURATED) > 0)).sum())}


def mask_sampling_sigma(spread, n_pixels):
    """How far the camera's mask mean may sit from the reference's cone mean when the sky varies inside the mask.

    The camera samples the cone at ``n_pixels`` pixel directions, the reference integrates it; with
    structure in the mask (cloud edges) the two means differ by about the standard error of the pixel
    sample, spread / sqrt(n). For a clear sky the spread, hence the term, is small. It is an upper
    estimate for pixels that integrate their whole footprint, whose difference from the cone is
    confined to the pixels on the mask's edge.

    Parameters
    ----------
    spread : array_like
        The radiance's spatial standard deviation over the mask's pixels (NaN counts as 0).
    n_pixels : array_like
        The pixels in the mask (at least 1 is used).

    Returns
    -------
    numpy.ndarray
        The term, in the units of ``spread``, broadcast over both.
    """
    spread = np.nan_to_num(np.asarray(spread, float))
    return spread / np.sqrt(np.maximum(np.asarray(n_pixels, float), 1.0))


def mask_pointing_sigma(gradient, pointing_deg):
    """How far the camera's mask mean may sit from the reference's cone mean because the mask may not point
    where the bundle says: |grad L| (radiance per degree, :func:`sky_gradient`) times the pointing
    uncertainty (degree).

    A mask whose centre lies delta degrees from the cone's averages the sky shifted by delta: grad L . delta.
    For a clear sky the gradient near the zenith is small; at a cloud edge it is large, and with the clouds
    drifting over the cone (frozen advection, dL/dt = -v . grad L) that difference follows the reference's
    dL/dt: left out of the noise, a pointing error looks like a clock offset of delta / |v| (for a cloud
    layer at 1800 m moving at 11 m/s, 2.9 s per degree).

    Parameters
    ----------
    gradient : array_like
        |grad L|, radiance per degree (NaN counts as 0).
    pointing_deg : array_like
        The mask's pointing uncertainty, degree.

    Returns
    -------
    numpy.ndarray
        The term, in radiance units, broadcast over both.
    """
    return np.nan_to_num(np.asarray(gradient, float)) * np.asarray(pointing_deg, float)


def sky_gradient(m: mm.Measured, region: np.ndarray, x_deg: np.ndarray, y_deg: np.ndarray) -> float:
    """|grad L| (radiance per degree) of a plane fitted to the unflagged pixels of ``region``.

    The plane is fitted against the direction's components theta cos(phi), theta sin(phi) (degrees, the
    bundle's map).

    Parameters
    ----------
    m : pipeline.radiometry.measurement.Measured
        The measurement chain's output for the crop.
    region : numpy.ndarray
        Boolean, the crop's shape: the sky around the mask.
    x_deg : numpy.ndarray
        theta cos(phi) of each pixel of the crop, degree.
    y_deg : numpy.ndarray
        theta sin(phi) of each pixel of the crop, degree.

    Returns
    -------
    float
        The gradient's magnitude in the chain's radiance units per degree; NaN with fewer than 4 usable pixels.
    """
    good = region & ((m.flags & MASK_EXCLUDED) == 0) & np.isfinite(m.value)
    if good.sum() < 4:
        return float("nan")
    a = np.column_stack([np.ones(int(good.sum())), x_deg[good], y_deg[good]])
    coef = np.linalg.lstsq(a, m.value[good], rcond=None)[0]
    return float(np.hypot(coef[1], coef[2]))


# --------------------------------------------------------------------------- the reference
def convolution_weights(channels_nm, response_nm, response) -> tuple[np.ndarray, float]:
    """Weights w_c with sum_c w_c L_c = Eq. (3) of the channels interpolated linearly onto the response.

    Only response wavelengths inside [first channel, last channel] are used.

    Parameters
    ----------
    channels_nm : array_like
        The reference radiometer's channel wavelengths, nm (any order).
    response_nm : array_like
        The wavelengths of the band's measured spectral response, nm.
    response : array_like
        The band's relative spectral response there (NaN counts as 0).

    Returns
    -------
    weights : numpy.ndarray
        One weight per channel, in the order of ``channels_nm``.
    outside : float
        The fraction of the response (trapezoid integral) that lies outside the channels' range.

    Raises
    ------
    pipeline.errors.InputError
        If fewer than two response wavelengths lie within the channels' range.
    """
    ch = np.asarray(channels_nm, float)
    order = np.argsort(ch)
    wl = np.asarray(response_nm, float)
    s = np.nan_to_num(np.asarray(response, float))      # as measured: the spectral stage's Eq. (8) uses the same values
    inside = (wl >= ch[order[0]]) & (wl <= ch[order[-1]])
    if inside.sum() < 2:
        raise InputError(None, f"the measured response ({wl.min():g}-{wl.max():g} nm) does not overlap the reference "
                               f"channels ({ch.min():g}-{ch.max():g} nm)")
    k = band_weights(wl[inside], s[inside])
    # linear interpolation as a matrix: row j holds the hat functions of the channels at wl[j]
    eye = np.eye(ch.size)[order]
    hats = np.stack([np.interp(wl[inside], ch[order], eye[:, c]) for c in range(ch.size)], axis=1)
    total = float(np.trapezoid(s, wl)) if wl.size > 1 else 0.0
    kept = float(np.trapezoid(s[inside], wl[inside]))
    return k @ hats, (1.0 - kept / total) if total > 0 else 0.0


class WindowedSeries:
    """Windowed statistics of a time series (times sorted, values with NaN drop-outs) by cumulative sums."""

    def __init__(self, times_s: np.ndarray, values: np.ndarray):
        self.t = np.asarray(times_s, float)
        v = np.asarray(values, float)
        ok = np.isfinite(v)
        z = np.where(ok, v, 0.0)
        tt = self.t - self.t[0]            # numerically small times for the slope sums
        self._t0 = self.t[0]

        def cum(a):
            return np.concatenate([[0.0], np.cumsum(a)])

        self.n, self.s, self.s2 = cum(ok.astype(float)), cum(z), cum(z**2)
        self.st, self.st2, self.stv = cum(np.where(ok, tt, 0.0)), cum(np.where(ok, tt**2, 0.0)), cum(z * tt)
        d = np.diff(v)
        dok = np.isfinite(d)
        self.nd, self.sd2 = cum(dok.astype(float)), cum(np.where(dok, d, 0.0) ** 2)

    def stats(self, centres_s, width_s: float) -> dict:
        """Per centre: count, mean, std (ddof 1), white-noise variance per sample, slope (per s).

        Parameters
        ----------
        centres_s : array_like
            The windows' centres, s on the series' time axis.
        width_s : float
            The windows' full width, s.

        Returns
        -------
        dict
            Arrays over the centres: ``count`` (finite samples), ``mean``, ``std``, ``noise_var`` (white-noise
            variance per sample from successive differences), ``slope`` (per s) and ``line_var`` (the samples'
            variance about the window's straight line); NaN where too few samples give them.
        """
        c = np.asarray(centres_s, float)
        lo = np.searchsorted(self.t, c - width_s / 2.0, "left")
        hi = np.searchsorted(self.t, c + width_s / 2.0, "right")
        n = self.n[hi] - self.n[lo]
        with np.errstate(invalid="ignore", divide="ignore"):
            s, s2 = self.s[hi] - self.s[lo], self.s2[hi] - self.s2[lo]
            mean = s / n
            var = np.clip((s2 - n * mean**2) / (n - 1), 0.0, None)
            # differences between samples lo..hi-1: indices lo..hi-2 of diff
            last = self.nd.size - 1
            dlo = np.minimum(lo, last)
            dhi = np.maximum(np.minimum(hi - 1, last), dlo)
            nd = self.nd[dhi] - self.nd[dlo]
            noise = (self.sd2[dhi] - self.sd2[dlo]) / (2.0 * nd)
            st, st2, stv = self.st[hi] - self.st[lo], self.st2[hi] - self.st2[lo], self.stv[hi] - self.stv[lo]
            sxx = st2 - st**2 / n
            sxy = stv - st * s / n
            slope = sxy / sxx
            # scatter about the window's straight line: what a centred mean does not average out
            line_var = np.clip(((n - 1) * var - sxy**2 / sxx) / (n - 2), 0.0, None)
        fit = (n > 2) & (sxx > 0)
        return {"count": n.astype(int), "mean": np.where(n > 0, mean, np.nan), "std": np.where(n > 1, np.sqrt(var), np.nan),
                "noise_var": np.where(nd > 0, noise, np.nan), "slope": np.where(fit, slope, np.nan),
                "line_var": np.where(fit, line_var, np.nan)}


def window_uncertainty(st: dict) -> np.ndarray:
    """Standard uncertainty of the window mean as the value at the frame's instant.

    In quadrature: the white noise of the mean and the reference's true variation within the window that a
    centred mean does not average out (its scatter about the window's straight line minus the white noise; a
    steady trend averages out, clouds and steps do not).

    Parameters
    ----------
    st : dict
        What :meth:`WindowedSeries.stats` returned.

    Returns
    -------
    numpy.ndarray
        The uncertainty per window, in the series' units.
    """
    noise = np.nan_to_num(st["noise_var"], nan=0.0)
    var = np.nan_to_num(st["line_var"], nan=0.0)
    return np.sqrt(noise / np.maximum(st["count"], 1) + np.clip(var - noise, 0.0, None))


def spectral_slope(channels_nm, spectrum, wavelength_nm: float) -> float:
    """d ln L / d ln lambda of a channel spectrum at ``wavelength_nm``: the slope between the two channels around it.

    Parameters
    ----------
    channels_nm : array_like
        The channels' wavelengths, nm.
    spectrum : array_like
        The radiance in each channel (non-positive or NaN channels are left out).
    wavelength_nm : float
        The wavelength, nm (outside the channels, the slope of the nearest pair).

    Returns
    -------
    float
        The dimensionless slope; NaN with fewer than two usable channels.
    """
    ch = np.asarray(channels_nm, float)
    L = np.asarray(spectrum, float)
    ok = np.isfinite(L) & (L > 0)
    ch, L = ch[ok], L[ok]
    if ch.size < 2:
        return float("nan")
    order = np.argsort(ch)
    ch, L = ch[order], L[order]
    i = int(np.clip(np.searchsorted(ch, wavelength_nm), 1, ch.size - 1))
    return float((np.log(L[i]) - np.log(L[i - 1])) / (np.log(ch[i]) - np.log(ch[i - 1])))


# --------------------------------------------------------------------------- the clock offset
def _profile_chi2(y, sy, series: dict, centres, width, min_samples):
    """chi^2 of camera = k_b x reference per band (k_b profiled out) and its number of points."""
    chi2, n = 0.0, 0
    for band, ws in series.items():
        st = ws.stats(centres, width)
        x = st["mean"]
        ok = (st["count"] >= min_samples) & np.isfinite(y[band]) & np.isfinite(x)
        if ok.sum() < 2:
            continue
        ratio = np.median(y[band][ok] / x[ok])
        s2 = sy[band][ok] ** 2 + (ratio * window_uncertainty(st)[ok]) ** 2
        w = 1.0 / s2
        k = np.sum(w * x[ok] * y[band][ok]) / np.sum(w * x[ok] ** 2)
        chi2 += float(np.sum(w * (y[band][ok] - k * x[ok]) ** 2))
        n += int(ok.sum()) - 1
    return chi2, n


def _profile_chi2_grid(y, sy, series: dict, times_s, offsets_s, width, min_samples):
    """:func:`_profile_chi2` at every offset of ``offsets_s`` at once (one windowed pass per band over all
    the shifted frame times): arrays of chi^2 and of its number of points."""
    offsets = np.asarray(offsets_s, float)
    chi2, n = np.zeros(offsets.size), np.zeros(offsets.size, int)
    for band, ws in series.items():
        st = ws.stats((np.asarray(times_s, float)[None, :] - offsets[:, None]).ravel(), width)
        shape = (offsets.size, len(times_s))
        x = st["mean"].reshape(shape)
        yb = np.broadcast_to(y[band], shape)
        ok = (st["count"].reshape(shape) >= min_samples) & np.isfinite(yb) & np.isfinite(x)
        use = ok.sum(axis=1) >= 2
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.nanmedian(np.where(ok, yb / x, np.nan)[use], axis=1)
            s2 = sy[band] ** 2 + (ratio[:, None] * window_uncertainty(st).reshape(shape)[use]) ** 2
            w = np.where(ok[use], 1.0 / s2, 0.0)
            xo, yo = np.where(ok[use], x[use], 0.0), np.where(ok[use], yb[use], 0.0)
            k = np.sum(w * xo * yo, axis=1) / np.sum(w * xo**2, axis=1)
            chi2[use] += np.sum(w * (yo - k[:, None] * xo) ** 2, axis=1)
        n[use] += ok[use].sum(axis=1) - 1
    return chi2, n


def profile_interval(chi2_at, c, chi2_c, threshold, step_s, scan_s, search_s, dof) -> tuple[float, float]:
    """The offsets on either side of the best ``c`` where the profile's chi-square rises ``threshold`` above
    its value ``chi2_c`` at ``c``.

    Scanned outward from ``c`` in steps of ``scan_s`` (the reference's sample spacing, below which the
    windows' chi-square does not change), the bound is the last point at or below the threshold once a whole
    ``step_s`` (one grid step) beyond it lies above (the curve is jagged at the scale of a sample: one point
    above the threshold does not end the interval). NaN on a side where the scan reaches the search range or
    the number of match-ups changes (chi-square no longer comparable).

    Parameters
    ----------
    chi2_at : callable
        ``chi2_at(offset)`` -> (chi-square, number of points) of the profile at a clock offset in s.
    c : float
        The fitted offset, s.
    chi2_c : float
        The chi-square at ``c``.
    threshold : float
        The rise that bounds the interval.
    step_s : float
        The offset grid's step, s.
    scan_s : float
        The scan's step, s.
    search_s : float
        The largest offset searched, s (either sign).
    dof : int
        The number of points at ``c``.

    Returns
    -------
    tuple[float, float]
        The lower and upper bounds, s.
    """
    patience = max(int(np.ceil(step_s / scan_s)), 1)
    bounds = []
    for sign in (-1.0, 1.0):
        last, above, j = c, 0, 0
        while above < patience:
            j += 1
            p = c + sign * j * scan_s
            if abs(p) > search_s:
                last = float("nan")
                break
            chi2, n = chi2_at(p)
            if n != dof:
                last = float("nan")
                break
            if chi2 - chi2_c <= threshold:
                last, above = p, 0
            else:
                above += 1
        bounds.append(last)
    return bounds[0], bounds[1]


def fit_clock_offset(y, sy, series, times_s, width, min_samples, search_s, step_s, level=None) -> dict:
    """Camera clock minus UTC (s) that makes the shifted reference fit the camera best (see the module docstring).

    Parameters
    ----------
    y : dict[str, numpy.ndarray]
        Band -> each frame's mask radiance.
    sy : dict[str, numpy.ndarray]
        Band -> its standard uncertainty, same units.
    series : dict[str, WindowedSeries]
        Band -> the reference's prediction of that band as a time series.
    times_s : numpy.ndarray
        The frames' camera-clock times on the series' time axis, s.
    width : float
        The reference window's full width, s.
    min_samples : int
        The fewest reference samples a window needs for a match-up.
    search_s : float
        The largest offset searched, s (either sign).
    step_s : float
        The offset grid's step, s.
    level : float or None, optional
        With it also the interval of the profile at that confidence level (``offset_low_s``,
        ``offset_high_s``, :func:`profile_interval`): where the chi-square rises chi2_1(level) times the reduced
        chi-square (when above 1) over its value at the fitted offset, with that offset's match-ups.

    Returns
    -------
    dict
        ``offset_s`` and ``offset_se_s`` (s, the standard error from the chi-square's curvature, scaled by the
        reduced chi-square when above 1), ``grid_s`` and ``reduced_chi2`` (the profile on the grid), ``chi2`` and
        ``dof`` at the offset; with ``level`` also ``offset_low_s``, ``offset_high_s`` (s) and ``level``.

    Raises
    ------
    pipeline.errors.InputError
        If no offset within the search range gives match-ups.
    """
    grid = np.arange(-search_s, search_s + 0.5 * step_s, step_s)

    def reduced(c):
        chi2, dof = _profile_chi2(y, sy, series, times_s - c, width, min_samples)
        return chi2 / dof if dof > 0 else np.inf

    chi2_grid, dof_grid = _profile_chi2_grid(y, sy, series, times_s, grid, width, min_samples)
    with np.errstate(invalid="ignore", divide="ignore"):
        curve = np.where(dof_grid > 0, chi2_grid / np.maximum(dof_grid, 1), np.inf)
    if not np.isfinite(curve).any():
        raise InputError(None, "no match-ups at any clock offset within the search range")
    best = float(grid[int(np.nanargmin(curve))])
    from scipy import optimize

    res = optimize.minimize_scalar(reduced, bounds=(best - step_s, best + step_s), method="bounded")
    c = float(res.x) if res.fun <= reduced(best) else best
    pts = c + step_s * np.arange(-2, 3)
    chi = np.array([_profile_chi2(y, sy, series, times_s - p, width, min_samples)[0] for p in pts])
    a2 = np.polyfit(pts - c, chi, 2)[0]
    chi2, dof = _profile_chi2(y, sy, series, times_s - c, width, min_samples)
    se = float(np.sqrt(2.0 / (2.0 * a2))) if a2 > 0 else float("nan")
    scale = max(chi2 / max(dof, 1), 1.0)
    se *= float(np.sqrt(scale))
    out = {"offset_s": c, "offset_se_s": se, "grid_s": grid, "reduced_chi2": curve, "chi2": chi2, "dof": dof}
    if level is not None:
        spacing = [float(np.median(np.diff(ws.t))) for ws in series.values() if ws.t.size > 1]
        scan = min(min(spacing), step_s) if spacing else step_s
        # chi-square's rise over its value at the fitted offset (points of the jagged curve may dip below it)
        low_high = profile_interval(lambda p: _profile_chi2(y, sy, series, times_s - p, width, min_samples), c,
                                    chi2, NormalDist().inv_cdf(0.5 + level / 2.0) ** 2 * scale, step_s, scan,
                                    search_s, dof)
        out.update(offset_low_s=low_high[0], offset_high_s=low_high[1], level=float(level))
    return out


# --------------------------------------------------------------------------- the stage
#: modules the stage needs only after its frames (the match-up's statistics, the clock fit's minimiser, the
#: sun's position): imported in a thread while the first frames decode, off the job's critical path (about
#: 0.9 s of imports at the start of a job otherwise)
AFTER_FRAMES_MODULES = ("pipeline.stats.matchup", "scipy.optimize", "pvlib.solarposition")


def _import_in_background(names) -> threading.Thread:
    """Import ``names`` in a daemon thread; a failure is left for the import where the module is used."""
    def run():
        for name in names:
            try:
                importlib.import_module(name)
            except Exception:   # noqa: BLE001 (the later import raises it where it matters)
                pass

    thread = threading.Thread(target=run, name="import", daemon=True)
    thread.start()
    return thread


def _sun_position(times_utc: pd.DatetimeIndex, site: dict) -> tuple[np.ndarray, np.ndarray]:
    """Solar zenith angle and apparent elevation (deg) by pvlib's SPA."""
    from pvlib.solarposition import get_solarposition

    pos = get_solarposition(times_utc, site["latitude_deg"], site["longitude_deg"], altitude=site.get("altitude_m"))
    return pos["zenith"].to_numpy(float), pos["apparent_elevation"].to_numpy(float)


def _check_region(ctx) -> None:
    """The lens region of dataset.yaml must be the calibration bundle's."""
    span = ctx.bundle["lens_region_px"].sel(lens=ctx.lens).values
    region = ctx.dataset.lenses[ctx.lens]
    if [list(map(int, region[0])), list(map(int, region[1]))] != [list(map(int, span[0])), list(map(int, span[1]))]:
        raise InputError(ctx.dataset.root / "dataset.yaml", f"lens '{ctx.lens}' region {region} differs from the "
                                                             f"calibration bundle's {span.tolist()}")


def _reduce_frames(ctx, stream, masks, window, grid_deg, negative_sigma, around):
    """Reduce the field frames of ``stream`` (:func:`pipeline.io.frames.iter_frames` of the lens): per frame and
    band the mask numbers; the middle frame's sky map."""
    bundle, lens = ctx.bundle, ctx.lens
    middle = len(ctx.dataset.frames(STAGE)) // 2
    rows, inputs, sky = [], {}, None
    # the bundle's selections and parameter objects of each band made once for all frames
    chains = {band: BandChain(bundle, lens, band, MEDIUM, ctx.effects) for band in BANDS}
    for i, dec in enumerate(stream):
        raw, row = dec.raw, dec.row
        inputs[row["file"]] = raw.sha256
        check_frame(raw, bundle, ctx.effects)
        temp = float(row["temperature_c"]) if "temperature_c" in row and pd.notna(row.get("temperature_c")) else None
        frame = mm.FrameSettings(exposure_s=float(raw.exposure_s), iso=float(raw.iso), temperature_c=temp)
        images = dec.lenses[lens]
        out = {"file": row["file"], "local_time": raw.time, "exposure_s": frame.exposure_s, "iso": frame.iso,
               # the sun disc is the one thing near full scale in a sky frame: it is seen when these are many
               "lens_n_bright": _n_bright(images, raw, float(ctx.params["sun_seen_fraction_of_full_scale"]))}
        for band in BANDS:
            m = chains[band](images, frame, window, negative_sigma=negative_sigma, source=row["path"])
            st = mask_statistics(m, masks[band])
            if st["n"] == 0:
                raise InputError(row["path"], f"band {band}: every pixel of the {ctx.params['mask_half_angle_deg']:g} "
                                              f"degree mask is saturated or flagged ({st['n_saturated']} saturated): "
                                              "choose a shorter exposure")
            if st["mean"] < -negative_sigma * st["random_se"]:
                raise ImpossibleResult(row["path"], f"band {band}: mean radiance {st['mean']:.3g} {RAD} in the mask is "
                                                    f"{-st['mean'] / st['random_se']:.1f} standard errors below zero: "
                                                    "the dark level or the calibration does not fit this frame")
            out.update({f"{k}_{band}": v for k, v in st.items()})
            out[f"gradient_{band}"] = sky_gradient(m, *around[band][:3])
        if i == middle:
            sky = _sky_map(images, chains, frame, grid_deg, row["file"], row["path"])
        rows.append(out)
    if not rows:
        raise InputError(ctx.dataset.root / STAGE / "frames.csv", f"no frames of lens '{lens}'")
    return pd.DataFrame(rows), inputs, sky


def _n_bright(images, raw, fraction: float) -> int:
    """Band pixels of the lens (all bands) at or above ``fraction`` of the full scale above the black level."""
    black = float(raw.black_level)
    level = black + fraction * (float(raw.white_level) - black)
    return int(sum(int(np.count_nonzero(images.bands[b] >= level)) for b in BANDS))


def _sky_map(images, chains, frame, grid_deg, name, source):
    means, counts = [], []
    for band in BANDS:
        chain = chains[band]
        m = chain(images, frame, source=source)
        zen, azi = sphere_coordinates(chain.g["theta_deg"].values, chain.g["phi_deg"].values, True)
        val = np.where((m.flags & EXCLUDED_FROM_GRID) == 0, m.value, np.nan)
        mean, _, count = bin_on_sphere(zen, azi, val, grid_deg)
        means.append(mean)
        counts.append(count)
    return {"mean": np.stack(means), "count": np.stack(counts), "file": name}


def compute(ctx) -> xr.Dataset:
    """The field artefact of the zenith lens (the stage runner's contract).

    The frames reduced to mask radiances, matched to the reference in time, compared per band (the match-up
    statistics), fitted as an observation table, and the band scales closed against the calibration.

    Parameters
    ----------
    ctx : pipeline.runner.workflow.StageContext
        The job: the zenith lens's dataset (field frames, reference radiometer, site), the configuration, the
        model's effects and the calibration bundle.

    Returns
    -------
    xarray.Dataset
        The field artefact: per frame the mask radiances and the reference's prediction, the clock offset and
        its profile, the match-up statistics, the band scales against the reference with their budget, and the
        sun and pointing variables.

    Raises
    ------
    pipeline.errors.InputError
        If there is no calibration bundle or it lacks the lens, the field inputs are unusable, or there are too
        few match-ups.
    """
    cfg = ctx.params
    bundle = ctx.bundle
    if bundle is None:
        raise InputError(None, "the field stage needs the calibration bundle")
    if ctx.lens not in list(bundle["lens"].values):
        raise InputError(None, f"the calibration bundle has no lens '{ctx.lens}'")
    site = read_site(ctx.dataset)
    _check_region(ctx)
    reference, ref_path, channels, frames, masks, window, around, sky = _read_frames_and_reference(ctx)
    utc, t_cam, ref_t, ref_values = _frames_on_the_reference_clock(frames, reference, ref_path, site)
    series = _reference_series(bundle, ctx.lens, channels, ref_t, ref_values)
    width = float(cfg["reference_window_s"])
    predict = "convolved" if "spectral_mismatch" in ctx.effects else "nearest"
    y = {b: frames[f"mean_{b}"].to_numpy(float) for b in BANDS}
    sy = {b: frames[f"random_se_{b}"].to_numpy(float) for b in BANDS}
    pointing = {b: around[b][3] for b in BANDS}
    sampling = _mask_sampling_terms(cfg, frames, pointing)
    # the profile weighs each frame as the match-ups do, the mask's sampling and pointing terms with the camera's
    # noise: a mask pointing delta degrees from the reference's cone sees drifting cloud edges delta / |v| early
    # or late, which a profile weighed by the random noise alone takes for a clock offset
    clock = _clock_profile(ctx, y, {b: np.hypot(sy[b], sampling[b]) for b in BANDS},
                           {b: series["windows"][(predict, b)] for b in BANDS}, t_cam)
    shift = clock["offset_s"] if "clock_offset" in ctx.effects else 0.0
    centres = t_cam - shift
    st = {key: w.stats(centres, width) for key, w in series["windows"].items()}
    channel_st = [WindowedSeries(ref_t, ref_values[:, c]).stats(centres, width) for c in range(channels.size)]
    channel_mean = np.stack([c["mean"] for c in channel_st], axis=1)       # (frame, channel)
    sun = _sun_covariates(cfg, bundle, ctx.lens, frames, utc - pd.to_timedelta(shift, unit="s"), site,
                          series["response_nm"])
    valid, no_reference = _matchups(ctx, frames, st, y, clock)
    stat, n_matchups = _matchup_statistics(cfg, valid, st, y, sy)
    table = _observation_table(ctx, valid, st, y, sy, sampling, t_cam, shift, clock, series, predict, channels,
                               channel_mean, sun)
    _check_enough_matchups(valid, len(frames), ref_path, int(cfg["min_reference_samples"]), width)
    fit, glare, scales = _fit_band_scales(ctx, table)
    scale_table = _scale_table(ctx, frames, table, fit, scales, valid, st, predict, channels, channel_mean,
                               series["effective_wavelength_nm"], series["outside"], site)
    for _, r in scale_table.iterrows():
        log.info("field %s %s: camera / reference %.4g against the predicted 1 (%+.1f %%, %.1f %% stated, z %+.1f)",
                 ctx.lens, r["band"], r["k_b"], 100.0 * np.expm1(r["value_dn"]), 100.0 * r["sigma_dn"],
                 r["value_dn"] / r["sigma_dn"])
    out = _dataset(ctx, frames, utc, t_cam, shift, clock, st, y, sy, valid, no_reference, stat, n_matchups,
                   table, fit, scales, series["nearest_index"], channels, series["effective_wavelength_nm"],
                   series["weights"], series["outside"], sky, predict, sun["zenith_deg"], masks, window)
    _add_sun_and_pointing_variables(out, cfg, frames, pointing, sun, glare)
    return out.merge(_scale_dataset(scale_table))


def _read_frames_and_reference(ctx):
    """Reduce the lens's frames (:func:`_reduce_frames`) and read the reference radiometer's file.

    The first frame decodes (a background thread) while the reference file is read and checked, the masks
    are made and the modules needed after the frames are imported; bad input still stops the stage with its
    message before any frame's numbers are used, and the decoding with it.
    Returns (reference table, its path, its channels (nm), frame table, masks, crop window, sky around the masks, sky map).
    """
    cfg = ctx.params
    with iter_frames(ctx.dataset, STAGE, ctx.dataset.frames(STAGE), lenses=[ctx.lens],
                     progress=ctx.progress) as stream:
        _import_in_background(AFTER_FRAMES_MODULES)
        reference = read_reference_radiometer(ctx.dataset)
        ref_path = ctx.dataset.root / STAGE / "reference_radiometer.csv"
        channels = np.asarray(reference.attrs["channels_nm"], float)
        if len(reference) < 2:
            raise InputError(ref_path, "needs at least two readings")
        masks, window, around = field_masks(ctx.bundle, ctx.lens, float(cfg["mask_half_angle_deg"]),
                                            int(cfg["min_mask_pixels"]))
        frames, inputs, sky = _reduce_frames(ctx, stream, masks, window, float(cfg["sky_map_grid_deg"]),
                                             float(ctx.config["apply"]["negative_mean_sigma"]), around)
    ctx.record_frames(inputs)
    return reference, ref_path, channels, frames, masks, window, around, sky


def _frames_on_the_reference_clock(frames: pd.DataFrame, reference: pd.DataFrame, ref_path, site: dict):
    """The frames' camera times (local) in UTC and both series in seconds since the first frame.

    Returns (frame times in UTC, frame times in s, reference times in s sorted, reference values (sample,
    channel) in that order); the reference must overlap the frames.
    """
    offset_h = float(site["camera_clock_utc_offset_h"])
    utc = pd.DatetimeIndex([t - timedelta(hours=offset_h) for t in frames["local_time"]]).tz_localize("UTC")
    t0 = utc.min()
    t_cam = np.asarray((utc - t0).total_seconds(), float)
    ref_t = np.asarray((pd.DatetimeIndex(reference["time"]) - t0).total_seconds(), float)
    order = np.argsort(ref_t, kind="stable")
    ref_t = ref_t[order]
    ref_values = reference[[c for c in reference.columns if c != "time"]].to_numpy(float)[order]
    if ref_t[-1] < t_cam.min() or ref_t[0] > t_cam.max():
        raise InputError(ref_path, f"covers {reference['time'].min()} to {reference['time'].max()}, none of the frames "
                                   f"({utc.min()} to {utc.max()} UTC after the camera clock's offset of {offset_h:g} h)")
    return utc, t_cam, ref_t, ref_values


def _reference_series(bundle: xr.Dataset, lens: str, channels, ref_t, ref_values) -> dict:
    """The two reference series of each band: the nearest channel and the band-convolved channels.

    Returns a dict: ``effective_wavelength_nm`` (per band), ``response_nm`` (the bundle's response wavelengths),
    ``nearest_index`` and ``weights`` (convolution weights of the channels) and ``outside`` (response fraction
    outside the channels' span) per band, and ``windows``: {(comparison, band): :class:`WindowedSeries`}.
    """
    lam_eff = bundle["effective_wavelength_nm"].sel(lens=lens).values.astype(float)
    resp_nm = bundle["wavelength_nm"].values.astype(float)
    nearest_idx, conv_w, outside = {}, {}, {}
    for j, band in enumerate(BANDS):
        nearest_idx[band] = int(np.argmin(np.abs(channels - lam_eff[j])))
        resp = bundle["response"].sel(lens=lens, band=band).values.astype(float)
        conv_w[band], outside[band] = convolution_weights(channels, resp_nm, resp)
    used_ch = {band: conv_w[band] != 0 for band in BANDS}
    conv_series = {}
    for band in BANDS:
        vals = ref_values[:, used_ch[band]] @ conv_w[band][used_ch[band]]
        conv_series[band] = vals          # NaN where any weighted channel dropped out
    near_series = {band: ref_values[:, nearest_idx[band]] for band in BANDS}
    ws = {("nearest", b): WindowedSeries(ref_t, near_series[b]) for b in BANDS}
    ws.update({("convolved", b): WindowedSeries(ref_t, conv_series[b]) for b in BANDS})
    return {"effective_wavelength_nm": lam_eff, "response_nm": resp_nm, "nearest_index": nearest_idx,
            "weights": conv_w, "outside": outside, "windows": ws}


def _mask_sampling_terms(cfg, frames: pd.DataFrame, pointing: dict) -> dict:
    """Per band and frame the mask's sampling and pointing terms in quadrature (zero without
    ``field.mask_sampling_term``)."""
    return {b: np.hypot(mask_sampling_sigma(frames[f"spread_{b}"].to_numpy(float), frames[f"n_{b}"].to_numpy(float)),
                        mask_pointing_sigma(frames[f"gradient_{b}"].to_numpy(float), pointing[b]))
            if cfg["mask_sampling_term"] else np.zeros(len(frames)) for b in BANDS}


def _clock_profile(ctx, y, sy, series, t_cam) -> dict | None:
    """The camera clock offset's profile (:func:`fit_clock_offset`) against the predicted reference ``series``.

    Fitted and applied with ``clock_offset`` in the model; without it only recorded (obs_frame's
    clock_profile_ columns, for the diagnostics' candidate amplitude) and nothing shifted, and None when
    no offset gives match-ups (the match-up checks say what is wrong).
    """
    cfg = ctx.params
    clock_args = (y, sy, series, t_cam, float(cfg["reference_window_s"]), int(cfg["min_reference_samples"]),
                  float(cfg["clock_offset_search_s"]), float(cfg["clock_offset_grid_s"]))
    if "clock_offset" in ctx.effects:
        return fit_clock_offset(*clock_args, level=float(cfg["confidence_level"]))
    try:
        return fit_clock_offset(*clock_args, level=float(cfg["confidence_level"]))
    except InputError as exc:       # no match-ups at any offset: the match-up checks below say what is wrong
        log.info("field %s: no clock-offset profile (%s)", ctx.lens, exc)
        return None


def _sun_covariates(cfg, bundle: xr.Dataset, lens: str, frames: pd.DataFrame, times_utc: pd.DatetimeIndex,
                    site: dict, resp_nm) -> dict:
    """The sun at each frame's reference time and the stray_light effect's covariate.

    The covariate is the sun's clear-sky direct beam in each band, seen or not, at the mask's angle from the
    sun (:mod:`pipeline.radiometry.sun_glare`). Returns ``zenith_deg`` and ``seen`` per frame, ``direct``
    (band direct irradiance) and ``glare`` (the covariate), both (frame, band).
    """
    sun_zenith, sun_elevation = _sun_position(times_utc, site)
    sun_seen = (frames["lens_n_bright"].to_numpy() >= int(cfg["sun_seen_min_pixels"])).astype(float)
    day = int(times_utc[0].day_of_year)
    sun_direct = np.stack([band_direct_irradiance(resp_nm, bundle["response"].sel(lens=lens, band=b).values,
                                                  90.0 - sun_elevation, day, float(cfg["clear_sky_aod700"]),
                                                  float(cfg["clear_sky_angstrom_exponent"]),
                                                  float(cfg["clear_sky_ozone_atm_cm"])) for b in BANDS], axis=1)
    glare_cov = sun_glare_covariate(sun_direct, sun_seen[:, None], sun_zenith[:, None],
                                    float(cfg["stray_light_angle_exponent"]),
                                    float(cfg["stray_light_reference_angle_deg"]))          # (frame, band)
    return {"zenith_deg": sun_zenith, "seen": sun_seen, "direct": sun_direct, "glare": glare_cov}


def _matchups(ctx, frames: pd.DataFrame, st: dict, y: dict, clock: dict | None):
    """The match-ups: frames with enough reference samples for both comparisons and a camera value.

    Returns ({band: match-up mask over the frames}, mask of the frames that are a match-up in no band).
    """
    min_n, width = int(ctx.params["min_reference_samples"]), float(ctx.params["reference_window_s"])
    valid = {b: (st[("nearest", b)]["count"] >= min_n) & (st[("convolved", b)]["count"] >= min_n) & np.isfinite(y[b])
             for b in BANDS}
    no_reference = ~np.logical_and.reduce([valid[b] for b in BANDS])
    if no_reference.any():
        log.warning("field %s: %d of %d frames have fewer than %d reference samples within %g s and are not "
                    "match-ups: %s", ctx.lens, int(no_reference.sum()), len(frames), min_n, width,
                    ", ".join(frames["file"][no_reference]))
    if clock is not None:
        log.info("field %s: camera clock offset %.2f +- %.2f s (camera minus UTC; %s)", ctx.lens, clock["offset_s"],
                 clock["offset_se_s"], "applied" if "clock_offset" in ctx.effects else "profile only, not applied")
    return valid, no_reference


def _matchup_statistics(cfg, valid: dict, st: dict, y: dict, sy: dict):
    """Every statistic of :func:`pipeline.stats.matchup.matchup_statistics` per band and comparison.

    Returns ({statistic: array (band, comparison)}, number of match-ups (band, comparison)).
    """
    from pipeline.stats.matchup import BOOTSTRAPPED, matchup_statistics

    names = list(BOOTSTRAPPED)
    fits = ("ols", "odr")
    fit_keys = ("slope", "slope_low", "slope_high", "slope_se", "intercept", "intercept_low", "intercept_high", "intercept_se")
    stat = {n: np.full((len(BANDS), 2), np.nan) for n in names + [f"{n}_{e}" for n in names for e in ("low", "high")]
            + [f"{f}_{k}" for f in fits for k in fit_keys]}
    n_matchups = np.zeros((len(BANDS), 2), int)
    level, resamples, seed = float(cfg["confidence_level"]), int(cfg["bootstrap_resamples"]), int(cfg["bootstrap_seed"])
    for j, band in enumerate(BANDS):
        ok = valid[band]
        for c, comp in enumerate(COMPARISONS):
            s = st[(comp, band)]
            x = s["mean"][ok]
            sx = window_uncertainty(s)[ok]
            eps = np.finfo(float).eps
            out = matchup_statistics(y[band][ok], x, np.maximum(sy[band][ok], eps * np.abs(y[band][ok])),
                                     np.maximum(sx, eps * np.abs(x)), level, resamples, seed + 97 * (2 * j + c),
                                     cfg["bootstrap_method"])
            n_matchups[j, c] = out.pop("n")
            for key, value in out.items():
                stat[key][j, c] = value
    return stat, n_matchups


#: the observation table's columns (``obs_frame``) before the fit's
OBS_FRAME_COLUMNS = ["group", "band", "frame", "time_s", "value_dn", "sigma_dn", "x_scale", "ref_nearest",
                     "ref_convolved", "dref_dt", "spectral_slope", "sun_zenith_deg", "sun_seen", "sun_glare_covariate"]


def _observation_table(ctx, valid, st, y, sy, sampling, t_cam, shift, clock, series, predict, channels,
                       channel_mean, sun) -> pd.DataFrame:
    """The observation table (``obs_frame``): one row per match-up and band, camera against the predicted reference.

    ``sigma_dn`` holds the camera's random standard error, the median camera / reference ratio times the
    reference's window uncertainty and the mask's sampling and pointing terms in quadrature. Without ``clock_offset`` in the
    model the clock profile's columns are added (constant), and the reference at the profile's offset.
    """
    lam_eff = series["effective_wavelength_nm"]
    rows = []
    for j, band in enumerate(BANDS):
        pred_series = st[(predict, band)]
        ratio = np.nanmedian(y[band][valid[band]] / pred_series["mean"][valid[band]]) if valid[band].any() else np.nan
        ref_sigma = window_uncertainty(pred_series)
        for f in np.flatnonzero(valid[band]):
            rows.append({
                "group": band, "band": band, "frame": int(f), "time_s": float(t_cam[f] - shift),
                "value_dn": y[band][f],
                "sigma_dn": float(np.sqrt(sy[band][f] ** 2 + (ratio * ref_sigma[f]) ** 2 + sampling[band][f] ** 2)),
                "x_scale": float(pred_series["mean"][f]),
                "ref_nearest": float(st[("nearest", band)]["mean"][f]),
                "ref_convolved": float(st[("convolved", band)]["mean"][f]),
                "dref_dt": float(pred_series["slope"][f]),
                "spectral_slope": spectral_slope(channels, channel_mean[f], lam_eff[j]),
                "sun_zenith_deg": float(sun["zenith_deg"][f]),
                "sun_seen": float(sun["seen"][f]),
                "sun_glare_covariate": float(sun["glare"][f, j]),
            })
    table = pd.DataFrame(rows, columns=OBS_FRAME_COLUMNS)
    if "clock_offset" not in ctx.effects and clock is not None:
        # the clock_offset candidate's amplitude (ClockOffset.amplitude): the profile's fit, valid at any offset
        # within the search, where the linearised signature (-k_b dref/dt) holds only for short shifts
        for col in CLOCK_PROFILE_COLUMNS:
            table[col] = float(clock[CLOCK_PROFILE_COLUMNS[col]])
        # ... and its secant signature: the reference at the profile's offset, each row's own band and frame
        width = float(ctx.params["reference_window_s"])
        at_offset = {b: series["windows"][(predict, b)].stats(t_cam - float(clock["offset_s"]), width)["mean"]
                     for b in BANDS}
        table["ref_at_clock_profile"] = [float(at_offset[b][f]) for b, f in zip(table["band"], table["frame"])]
    return table


def _check_enough_matchups(valid: dict, n_frames: int, ref_path, min_n: int, width: float) -> None:
    """Three match-ups per band at least: the fewest a line with an interval (N - 2 degrees of freedom) needs."""
    few = [b for b in BANDS if valid[b].sum() < 3]
    if few:
        raise InputError(ref_path, f"only {min(int(valid[b].sum()) for b in few)} of {n_frames} frames have "
                                   f"{min_n} or more reference samples within {width:g} s (band {few[0]}): "
                                   "a match-up needs at least 3")


def _fit_band_scales(ctx, table: pd.DataFrame):
    """Fit the observation table (:func:`pipeline.stages.observations.fit_with_effects`) and take the band scales.

    Adds the fit's ``pred_dn`` and ``z`` to ``table``. With ``stray_light`` in the model the fitted sun glare is
    taken out of the band scales; a glare ``field.stray_light_negative_sigma`` standard errors below zero stops
    the stage. Returns (the fit, {coef, se} of the glare or None, scale k_b per band).
    """
    cfg = ctx.params
    fit, coefs = fit_with_effects(table, "frame", ctx.effects, STAGE)
    table["pred_dn"] = fit.pred
    table["z"] = fit.z
    glare = None
    base_pred = table["pred_dn"].to_numpy(float)
    if "stray_light" in coefs:
        coef, se = coefs["stray_light"]
        glare = {"coef": float(coef[0]), "se": float(se[0])}
        base_pred = base_pred - glare["coef"] * table["sun_glare_covariate"].to_numpy(float)
        if glare["coef"] < -float(cfg["stray_light_negative_sigma"]) * glare["se"]:
            raise ImpossibleResult(ctx.dataset.root / STAGE, f"the fitted sun glare is negative ({glare['coef']:.3g} +- "
                                                             f"{glare['se']:.2g} sr-1): stray light only adds light; "
                                                             "something else in the field residuals follows the sun")
        log.info("field %s: sun glare %.3g +- %.2g sr-1 at %g degree from the sun", ctx.lens, glare["coef"],
                 glare["se"], float(cfg["stray_light_reference_angle_deg"]))
    scales = np.array([float(np.nanmean((base_pred / table["x_scale"])[table["band"] == b])) for b in BANDS])
    return fit, glare, scales


def _add_sun_and_pointing_variables(out: xr.Dataset, cfg, frames: pd.DataFrame, pointing: dict, sun: dict,
                                    glare: dict | None) -> None:
    """The artefact's sky gradient, mask pointing, sun and stray-light variables, added to ``out``."""
    out["sky_gradient"] = (("frame", "band"), np.stack([frames[f"gradient_{b}"].to_numpy(float) for b in BANDS], axis=1),
                           _attrs("|grad L| of a plane fitted to the radiance in and one pixel pitch around the mask "
                                  "(the sky's change per degree of pointing)", f"{RAD} degree-1"))
    out["mask_pointing_sigma"] = ("band", np.array([pointing[b] for b in BANDS]), _attrs(
        "pointing uncertainty of the mask: the bundle's theta_deg_sigma at the pixel nearest the axis; times "
        "sky_gradient it is in the match-up noise", "degree"))
    out["sun_seen"] = ("frame", sun["seen"].astype(np.int8),
                       _attrs(f"1: the sun disc is seen (at least {cfg['sun_seen_min_pixels']} band pixels in the "
                              f"lens at {cfg['sun_seen_fraction_of_full_scale']:g} of the full scale or above)", "1"))
    out["lens_n_bright"] = ("frame", frames["lens_n_bright"].to_numpy(int), _attrs(
        f"band pixels in the lens, all bands, at {cfg['sun_seen_fraction_of_full_scale']:g} of the full scale or above",
        "1"))
    out["sun_direct_band_irradiance"] = (("frame", "band"), sun["direct"], _attrs(
        "clear-sky direct-normal irradiance in the band (G173 top of atmosphere, Rayleigh and aerosol, Eq. 3)",
        "W m-2 nm-1"))
    out["sun_glare_covariate"] = (("frame", "band"), sun["glare"], _attrs(
        "stray_light covariate: band direct irradiance x sun seen x (Z_ref / Z)^q", "W m-2 nm-1"))
    if glare is not None:
        z_ref = float(cfg["stray_light_reference_angle_deg"])
        out["stray_light_glare_sr"] = ((), glare["coef"], _attrs(
            f"fitted spread of the sun's direct irradiance into the mask at {z_ref:g} degree from the sun "
            "(glare radiance per unit irradiance)", "sr-1"))
        out["stray_light_glare_sr_sigma"] = ((), glare["se"], _attrs("standard error of stray_light_glare_sr", "sr-1"))
        out["stray_light_mask_glare"] = (("frame", "band"), glare["coef"] * sun["glare"],
                                         _attrs("fitted sun glare in the mask's mean radiance", RAD))


def _scale_table(ctx, frames, table, fit, scales, valid, st, predict, channels, channel_mean, lam_eff, outside,
                 site) -> pd.DataFrame:
    """The field scale closure's rows, one per band (:mod:`pipeline.radiometry.field_scale`): ln k_b against the
    predicted 0, its budget, and the covariates of the effects the model lacks that move the scale."""
    bundle, lens, effects = ctx.bundle, ctx.lens, set(ctx.effects)
    _, names = base_design(table)
    rchi2 = max(fit.chi2 / max(fit.dof, 1), 1.0)
    reference_rel = float(site["reference"].get("calibration_relative_sigma", REFERENCE_CALIBRATION_RELATIVE_SIGMA))
    rows = []
    for j, band in enumerate(BANDS):
        ok = valid[band]
        i = names.index(f"{band}:scale")
        camera = frames[f"mean_{band}"].to_numpy(float)[ok]
        exposure = frames["exposure_s"].to_numpy(float)[ok]
        iso = frames["iso"].to_numpy(float)[ok]
        b = bundle.sel(lens=lens, band=band)
        lam_sigma = float(b["effective_wavelength_nm_sigma"]) if "effective_wavelength_nm_sigma" in b else 0.0
        slope = np.nanmedian([spectral_slope(channels, channel_mean[f], lam_eff[j]) for f in np.flatnonzero(ok)])
        near = np.array([st[("nearest", band)]["mean"][f] for f in np.flatnonzero(ok)])
        conv = np.array([st[("convolved", band)]["mean"][f] for f in np.flatnonzero(ok)])
        mismatch = float(np.mean(conv) / np.mean(near))
        convolved_sigma = mismatch_prediction_relative_sigma(slope, lam_eff[j], lam_sigma, outside[band])
        terms = {
            "fit": float(np.sqrt(max(fit.cov[i, i], 0.0) * rchi2)) / scales[j],
            "camera_calibration": float(np.nanmedian(frames[f"systematic_{band}"].to_numpy(float)[ok] / camera)),
            "reference_calibration": reference_rel,
            # the reference compared with as the band radiance: the nearest channel states its departure from
            # the band-convolved reference (which channel is nearest turns on a few nm of the effective wavelength)
            "spectral_mismatch_prediction": (convolved_sigma if predict == "convolved"
                                             else nearest_channel_relative_sigma(mismatch, convolved_sigma)),
        }
        row = {"group": band, "band": band, "lens": lens, "value_dn": float(np.log(scales[j])),
               "sigma_dn": scale_relative_sigma(terms), "k_b": float(scales[j]), "k_predicted": 1.0,
               "reference": predict, "n_matchups": int(ok.sum()), **{f"sigma_{t}": terms[t] for t in SCALE_TERMS}}
        # covariates of the effects the model lacks (the chain corrects the others): the field frames' setting and
        # level against the absolute experiment's, where R^-1 was made (effects' predicted_shift)
        r_inv = float(b["inverse_responsivity"])
        signal_dn = float(np.mean(camera / r_inv * exposure * iso / 100.0))
        if "shutter_offset" not in effects:
            row["inv_field_exposure_per_s"] = float(np.mean(1.0 / exposure))
            row["calibration_exposure_s"] = float(b["absolute_exposure_s"])
        if "nonlinearity" not in effects:
            row["field_signal_dn"] = signal_dn
            row["calibration_signal_dn"] = float(b["absolute_signal_dn"])
        if "iso_gain" not in effects:
            row["field_iso"] = float(np.median(iso))
            row["calibration_iso"] = float(b["absolute_iso"])
        if "dark_current" not in effects:
            row["field_dark_s_per_dn"] = float(np.mean(iso / 100.0 * exposure) / signal_dn)
        if "spectral_mismatch" not in effects:
            row["mismatch_factor"] = mismatch
        if "stray_light" not in effects:
            cov = table.loc[table["band"] == band, "sun_glare_covariate"].to_numpy(float)
            row["glare_share_sr"] = float(np.mean(cov) / np.mean(camera))
        rows.append(row)
    return pd.DataFrame(rows)


#: units of the scale table's columns (``obs_scale``)
SCALE_UNITS = {"value_dn": "1", "sigma_dn": "1", "k_b": "1", "k_predicted": "1", "n_matchups": "1",
               **{f"sigma_{t}": "1" for t in SCALE_TERMS}, "inv_field_exposure_per_s": "s-1",
               "calibration_exposure_s": "s", "field_signal_dn": "DN", "calibration_signal_dn": "DN", "field_iso": "1",
               "calibration_iso": "1", "field_dark_s_per_dn": "s DN-1", "mismatch_factor": "1", "glare_share_sr": "sr"}
SCALE_LONG_NAMES = {
    "value_dn": "ln of the band's camera / reference scale k_b over its prediction",
    "sigma_dn": "relative standard uncertainty of the scale (the quadrature sum of the sigma_ terms)",
    "k_b": "fitted camera / reference scale of the band (the match-up table's)",
    "k_predicted": "the scale the lab calibration predicts against the reference the model compares with",
    "reference": "the reference the model compares with (nearest channel, or band-convolved with spectral_mismatch)",
    "n_matchups": "match-ups of the band",
    "sigma_fit": "scale term: standard error of k_b from the match-up fit, relative",
    "sigma_camera_calibration": "scale term: the chain's systematic sigma over the mask (R^-1, roll-off, flat "
                                "field, response corrections), relative",
    "sigma_reference_calibration": "scale term: the reference radiometer's calibration (site.yaml), relative",
    "sigma_spectral_mismatch_prediction": "scale term: the reference compared with as the band radiance (response "
                                          "position, response outside the channels; the nearest channel also its "
                                          "departure from the band-convolved reference), relative",
    "inv_field_exposure_per_s": "shutter_offset covariate: mean of 1 / exposure over the band's match-ups",
    "calibration_exposure_s": "shutter_offset covariate: exposure of the absolute experiment's signal frames",
    "field_signal_dn": "nonlinearity covariate: mean dark-subtracted DN in the mask over the match-ups",
    "calibration_signal_dn": "nonlinearity covariate: dark-subtracted DN in the absolute experiment's mask",
    "field_iso": "iso_gain covariate: ISO of the field frames (median)",
    "calibration_iso": "iso_gain covariate: ISO of the absolute experiment's signal frames",
    "field_dark_s_per_dn": "dark_current covariate: mean ISO/100 x exposure over the mask's DN",
    "mismatch_factor": "spectral_mismatch covariate: band-convolved over nearest-channel reference, mean over "
                       "the match-ups",
    "glare_share_sr": "stray_light covariate: mean sun-glare covariate over the mean camera radiance",
}


def _scale_dataset(scale_table: pd.DataFrame) -> xr.Dataset:
    out = table_to_dataset(scale_table, "obs_scale")
    for col in scale_table.columns:
        attrs = {"long_name": f"field scale closure: {SCALE_LONG_NAMES.get(col, col)}"}
        if col in SCALE_UNITS:
            attrs["units"] = SCALE_UNITS[col]
        out[f"obs_scale__{col}"].attrs.update(attrs)
    return out


def _attrs(long_name, units, **extra):
    return {"long_name": long_name, "units": units, **extra}


def _dataset(ctx, frames, utc, t_cam, shift, clock, st, y, sy, valid, no_reference, stat, n_matchups, table, fit,
             scales, nearest_idx, channels, lam_eff, conv_w, outside, sky, predict, sun_zenith, masks, window):
    """The field artefact: per frame the camera and reference values, per band and comparison the match-up
    statistics, the clock profile, the middle frame's sky map and the observation table ``obs_frame``."""
    cfg = ctx.params
    data = _frame_variables(frames, utc, t_cam, st, valid, sun_zenith)
    data.update(_statistic_variables(cfg, stat))
    comp_dims = ("band", "comparison")
    data["n_matchups"] = (comp_dims, n_matchups, _attrs("number of match-ups", "1"))
    data["n_frames_without_reference"] = ((), int(no_reference.sum()),
                                          _attrs(f"frames with fewer than {cfg['min_reference_samples']} reference samples "
                                                 f"in the {cfg['reference_window_s']:g} s window (not match-ups)", "1"))
    data["effective_wavelength_nm"] = ("band", lam_eff, _attrs("effective wavelength of the band (bundle, Eq. 8)", "nm"))
    data["nearest_channel_nm"] = ("band", np.array([channels[nearest_idx[b]] for b in BANDS]),
                                  _attrs("reference channel nearest the effective wavelength", "nm"))
    data["convolution_weight"] = (("band", "channel_nm"), np.stack([conv_w[b] for b in BANDS]),
                                  _attrs("weight of each reference channel in the band-convolved reference", "1"))
    data["response_outside_reference_fraction"] = ("band", np.array([outside[b] for b in BANDS]),
                                                   _attrs("fraction of the measured response outside the channels' span "
                                                          "(left out of the convolution)", "1"))
    data["band_scale"] = ("band", scales, _attrs(f"fitted camera / reference scale k_b (reference: {predict})", "1"))
    data["mask_half_angle_deg"] = ((), float(cfg["mask_half_angle_deg"]), _attrs("averaging mask around the axis", "degree"))
    data["rms_z"] = ((), fit.rms_z, _attrs("RMS of the noise-normalised match-up residuals (1 at the noise floor)", "1"))
    data["clock_offset_s"] = ((), float(shift), _attrs("camera clock minus UTC applied to the reference times "
                                                      "(fitted with clock_offset in the model, 0 otherwise)", "s"))
    coords = {"frame": np.arange(len(frames)), "band": list(BANDS), "comparison": list(COMPARISONS),
              "channel_nm": ("channel_nm", channels, _attrs("reference channel centre wavelength", "nm"))}
    if clock is not None:
        _add_clock_profile(data, coords, clock, "clock_offset" in ctx.effects)
    if sky is not None:
        _add_sky_map(data, coords, sky, float(cfg["sky_map_grid_deg"]))
    ds = xr.Dataset(data, coords=coords, attrs={
        "title": "field match-up of the camera against a reference radiometer (Larouche et al. 2024, Section 2.9)",
        "lens": ctx.lens, "medium": MEDIUM, "prediction": predict,
        "reference_window_s": float(cfg["reference_window_s"]), "confidence_level": float(cfg["confidence_level"]),
        "mask_window_px": f"rows {window[0].start}:{window[0].stop}, cols {window[1].start}:{window[1].stop}",
        "interpolation": "reference channels as samples at their centre wavelengths, linear in wavelength; response "
                         "wavelengths outside the channels' span left out",
    })
    return ds.merge(_obs_frame_dataset(table))


def _frame_variables(frames, utc, t_cam, st, valid, sun_zenith) -> dict:
    """The artefact's per-frame variables: times and settings, the camera's mask numbers per band, and the
    reference's window numbers per band and comparison (``reference_<comparison>...``)."""
    fb = ("frame", "band")

    def per_band(key):
        return np.stack([frames[f"{key}_{b}"].to_numpy(float) for b in BANDS], axis=1)

    def ref(comp, key):
        return np.stack([st[(comp, b)][key] for b in BANDS], axis=1)

    data = {
        "time_utc": ("frame", np.array([t.isoformat() for t in utc], dtype=str),
                     {"long_name": "frame time in UTC (camera clock minus the site's time-zone offset)"}),
        "time_s": ("frame", t_cam, _attrs("frame time since the first frame (camera clock, UTC)", "s")),
        "frame_file": ("frame", frames["file"].to_numpy(str), {"long_name": "raw frame"}),
        "exposure_s": ("frame", frames["exposure_s"].to_numpy(float), _attrs("exposure time (tag)", "s")),
        "iso": ("frame", frames["iso"].to_numpy(float), _attrs("ISO speed (tag)", "1")),
        "sun_zenith_deg": ("frame", sun_zenith, _attrs("solar zenith angle at the frame's reference time (SPA, pvlib)",
                                                       "degree")),
        "camera_radiance": (fb, per_band("mean"), _attrs("camera mean radiance in the mask, inverse of Eq. (4)", RAD)),
        "camera_random_sigma": (fb, per_band("random_se"),
                                _attrs("random standard error of the mask mean (shot, read, dark noise)", RAD)),
        "camera_systematic_sigma": (fb, per_band("systematic"),
                                    _attrs("systematic standard uncertainty (calibration), common to all frames of a band",
                                           RAD)),
        "camera_spatial_spread": (fb, per_band("spread"), _attrs("standard deviation of the pixel radiances in the mask", RAD)),
        "mask_n_pixels": (fb, per_band("n"), _attrs("unflagged band pixels averaged in the mask", "1")),
        "mask_n_saturated": (fb, per_band("n_saturated"), _attrs("saturated band pixels in the mask (left out)", "1")),
        "is_matchup": (fb, np.stack([valid[b] for b in BANDS], axis=1).astype(np.int8),
                       _attrs("1: enough reference samples in the window (a match-up)", "1")),
    }
    for comp in COMPARISONS:
        what = ("channel nearest the band's effective wavelength" if comp == "nearest"
                else "channels interpolated linearly in wavelength and averaged with the measured response, Eq. (3)")
        data[f"reference_{comp}"] = (fb, ref(comp, "mean"), _attrs(f"reference window mean, {what}", RAD))
        data[f"reference_{comp}_std"] = (fb, ref(comp, "std"), _attrs("standard deviation of the reference in the window", RAD))
        data[f"reference_{comp}_count"] = (fb, ref(comp, "count"), _attrs("reference samples in the window", "1"))
        data[f"reference_{comp}_sigma"] = (fb, np.stack([window_uncertainty(st[(comp, b)]) for b in BANDS], axis=1),
                                           _attrs("uncertainty of the window mean as the value at the frame's instant "
                                                  "(noise of the mean, variation about the window's line)", RAD))
        data[f"reference_{comp}_slope"] = (fb, ref(comp, "slope"),
                                           _attrs("d reference / dt from a line fitted to the window's samples",
                                                  "W sr-1 m-2 nm-1 s-1"))
    return data


def _statistic_variables(cfg, stat: dict) -> dict:
    """The match-up statistics as ``stat_<name>`` variables (band, comparison) with their units and long names."""
    from pipeline.stats.matchup import STATISTIC_UNITS

    data = {}
    for name, value in stat.items():
        base = name.rsplit("_", 1)[0] if name.endswith(("_low", "_high")) else name
        if base in STATISTIC_UNITS:
            units = RAD if STATISTIC_UNITS[base] == "data" else STATISTIC_UNITS[base]
            long = base.replace("_", " ")
            if name.endswith("_low") or name.endswith("_high"):
                long = (f"{'lower' if name.endswith('_low') else 'upper'} bound of the paired bootstrap interval of the "
                        f"{long} ({cfg['confidence_level']:g}, {cfg['bootstrap_method']}, "
                        f"{cfg['bootstrap_resamples']} resamples)")
        else:
            fitname, key = name.split("_", 1)
            units = RAD if key.startswith("intercept") else "1"
            long = f"{'ordinary least squares' if fitname == 'ols' else 'errors-in-both (ODR)'} {key.replace('_', ' ')} " \
                   f"of camera against reference (intervals Student-t at {cfg['confidence_level']:g})"
        data[f"stat_{name}"] = (("band", "comparison"), value, _attrs(long, units))
    return data


def _add_clock_profile(data: dict, coords: dict, clock: dict, applied: bool) -> None:
    """The clock offset's profile (chi-square curve, offset, its standard error and interval) into ``data`` and
    ``coords``; ``applied``: clock_offset is in the model (the offset shifted the reference)."""
    if applied:
        data["clock_offset_s_sigma"] = ((), clock["offset_se_s"],
                                        _attrs("standard error of the fitted clock offset (chi-square curvature)", "s"))
    data["clock_search_reduced_chi2"] = ("clock_search_s", clock["reduced_chi2"], _attrs(
        "reduced chi-square of the base model against the clock offset"
        + ("" if applied else " (the profile only: clock_offset is not in the model, no offset applied)"), "1"))
    coords["clock_search_s"] = ("clock_search_s", clock["grid_s"], _attrs("trial camera clock offset", "s"))
    for name, key, what in (("clock_profile_offset_s", "offset_s", "camera clock minus UTC at the profile's minimum"),
                            ("clock_profile_offset_se_s", "offset_se_s", "standard error of the profile's offset "
                             "(chi-square curvature)"),
                            ("clock_profile_offset_low_s", "offset_low_s", "lower bound of the profile's interval "
                             f"(chi-square rise chi2_1({clock['level']:g}) x reduced chi-square; NaN: not found)"),
                            ("clock_profile_offset_high_s", "offset_high_s", "upper bound of the profile's interval "
                             f"(chi-square rise chi2_1({clock['level']:g}) x reduced chi-square; NaN: not found)")):
        data[name] = ((), float(clock[key]), _attrs(
            f"{what}; {'applied' if applied else 'not applied: clock_offset is not in the model'}", "s",
            confidence_level=clock["level"]))


def _add_sky_map(data: dict, coords: dict, sky: dict, grid_deg: float) -> None:
    """The middle frame's all-sky map (zenith, azimuth cells of ``grid_deg``) into ``data`` and ``coords``."""
    n_z, n_a = sky["mean"].shape[1:]
    coords["zenith"] = ("zenith", (np.arange(n_z) + 0.5) * grid_deg, _attrs("zenith angle of the cell centre", "degree"))
    coords["azimuth"] = ("azimuth", (np.arange(n_a) + 0.5) * grid_deg, _attrs("azimuth of the cell centre", "degree"))
    data["sky_radiance"] = (("band", "zenith", "azimuth"), sky["mean"],
                            _attrs("all-sky radiance of the middle frame: mean of the unflagged pixels in the cell", RAD,
                                   frame_file=sky["file"]))
    data["sky_count"] = (("band", "zenith", "azimuth"), sky["count"], _attrs("pixels binned into the cell", "1"))


def _obs_frame_dataset(table: pd.DataFrame) -> xr.Dataset:
    """The observation table as ``obs_frame__<column>`` variables with units and long names."""
    obs = table_to_dataset(table, "obs_frame")
    units = {"value_dn": RAD, "sigma_dn": RAD, "x_scale": RAD, "pred_dn": RAD, "ref_nearest": RAD, "ref_convolved": RAD,
             "dref_dt": "W sr-1 m-2 nm-1 s-1", "spectral_slope": "1", "sun_zenith_deg": "degree", "time_s": "s",
             "z": "1", "frame": "1", "sun_seen": "1", "sun_glare_covariate": "W m-2 nm-1",
             **{col: "s" for col in CLOCK_PROFILE_COLUMNS}, "ref_at_clock_profile": RAD}
    for col, u in units.items():
        if f"obs_frame__{col}" in obs:
            obs[f"obs_frame__{col}"].attrs.update(units=u, long_name=f"match-up table: {col}")
    for col in (*CLOCK_PROFILE_COLUMNS, "ref_at_clock_profile"):
        if f"obs_frame__{col}" in obs:
            obs[f"obs_frame__{col}"].attrs["long_name"] = f"match-up table: {CLOCK_PROFILE_LONG_NAMES[col]}"
    for col in ("group", "band"):
        obs[f"obs_frame__{col}"].attrs.update(long_name=f"match-up table: {col}")
    return obs
