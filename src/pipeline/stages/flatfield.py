"""Pixel response non-uniformity (flat field) from the linearity exposure sweep.

For each setting of the exposure sweep at the dark frames' lowest ISO, the
frame-averaged image of the photon-transfer region is dark-corrected pixel by
pixel (the dark stage's offset pattern) and a smooth surface (roll-off, a
polynomial in the pixel offsets from the region centre) is removed. What is
left scatters by

    var = temporal variance / n_frames + offset-pattern error + prnu^2 S^2 / sites,

with S the mean signal and ``sites`` the raw pixels averaged in a band pixel.
The flat-field map is the average over the settings of each pixel's relative
residual, weighted by the inverse of its noise variance (the long exposures
carry most of the electrons), and ``flat_field_sigma`` its standard
uncertainty from the same noise: the temporal noise of each setting's mean
(independent between settings) and the error of the dark stage's offset map,
common to every setting (n_dark frames of read noise).
With a fitted nonlinearity (``beta``, ``full_scale_dn``: m = s (1 - beta s / F)) each pixel's
dark-corrected mean is first taken back to the linear signal s and its temporal variance by the
slope ds/dm squared: the sensor bends the sensitivity pattern with the signal (a relative PRNU
delta in s is delta (1 - 2 beta s / F) / (1 - beta s / F) in m, 5 % less variance at 10,000 DN
for beta = 0.05), and the settings that carry most of the electrons sit highest on the curve.
The observation is the spatial variance in excess of the known noise terms,
one row per setting and band (level ``flat``); its expected spread is that of a
sample variance, var sqrt(2 / N), with var the larger of the measured and the
noise-only variance. A flat-field-free model predicts zero; the
``prnu`` effect adds the column ``S^2 / sites`` whose coefficient is prnu^2.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import xarray as xr

from pipeline.io.bands import BANDS
from pipeline.io.frames import SITES_PER_BAND_PIXEL
from pipeline.radiometry.dark import dark_level_dn
from pipeline.radiometry.response import linear_signal


def _smooth_design(y: np.ndarray, x: np.ndarray, polynomial_degree: int | None = None) -> np.ndarray:
    """Columns of the smooth surface removed before the flat field is read.

    Default (a fisheye's photon-transfer region, the inner 30 degrees): a quadratic in the pixel
    offsets from the region centre plus r^4. With ``polynomial_degree`` (a rectilinear region, lit
    to its corners, where vignetting, cos^4 of the field angle times the lens's own fall-off about
    an optical centre off the region's, bends faster and less symmetrically): every monomial
    dx^i dy^j with i + j <= degree.
    """
    dy = (y - y.mean()) / max(np.ptp(y), 1)
    dx = (x - x.mean()) / max(np.ptp(x), 1)
    if polynomial_degree is not None:
        return np.column_stack([dx**i * dy**j for i in range(polynomial_degree + 1)
                                for j in range(polynomial_degree + 1 - i)])
    r2 = dx * dx + dy * dy
    return np.column_stack([np.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy, r2 * r2])


def flatfield(reduced: dict, dark: dict[str, xr.Dataset], iso: float, beta: float = 0.0,
              full_scale_dn: float = float("nan"), offset_var_dn2: dict | None = None,
              rectilinear_degree: int = 6) -> tuple[pd.DataFrame, dict]:
    """Observation table (level ``flat``) and flat-field maps (band, y, x) per lens.

    Parameters
    ----------
    reduced : dict
        What :func:`pipeline.stages.linearity.reduce_linearity` returned (its ``ptc`` regions, ``moments``,
        ``frames`` and ``projection``).
    dark : dict[str, xarray.Dataset]
        Lens -> its dark artefact (fixed pattern, dark level, read noise, hot pixels).
    iso : float
        The exposure sweep's ISO whose settings are used.
    beta : float, default 0.0
        The linearity model's fitted nonlinearity (0: none).
    full_scale_dn : float, default nan
        Its full scale, DN.
    offset_var_dn2 : dict or None, optional
        (lens, band, (iso, exposure_s)) -> DN^2, with ``bias_drift``: the sample variance of the frames' common
        black-level offsets in a setting, which every pixel's temporal variance holds but which adds no
        spatial variance to the setting's mean image: taken out of the noise.
    rectilinear_degree : int, default 6
        A rectilinear lens region (``reduced["projection"]``) has its smooth surface as a 2-D polynomial of
        this degree (:func:`_smooth_design`).

    Returns
    -------
    table : pandas.DataFrame
        One row per lens, band and unsaturated setting of the exposure sweep: the spatial variance of the
        residual about the smooth surface and the part the noise leaves there (DN^2), ``value_dn`` their
        difference (DN^2) and its ``sigma_dn``, the signal (DN).
    maps : dict[str, tuple[numpy.ndarray, numpy.ndarray]]
        Lens -> (flat field, its standard uncertainty), each float32 (band, y, x), relative (1 on the smooth
        surface), NaN outside the photon-transfer region and on hot pixels.
    """
    offset_var_dn2 = offset_var_dn2 or {}
    rows, maps = [], {}
    fr = reduced["frames"]
    sat = fr[fr["saturated"]]
    saturated = {(r.lens, r.band, (float(r.iso), round(float(r.exposure_s), 9))) for r in sat.itertuples()}
    for lens, per_band in reduced["ptc"].items():
        d = dark[lens]
        shape = per_band["G"][0].shape
        fmap = np.full((len(BANDS),) + shape, np.nan, dtype=np.float32)
        fsig = np.full((len(BANDS),) + shape, np.nan, dtype=np.float32)
        for bi, band in enumerate(BANDS):
            region = per_band[band][0] & (d["hot_pixel_mask"].sel(band=band).values == 0)
            yy, xx = np.nonzero(per_band[band][0])
            keep = region[per_band[band][0]]
            y, x = yy[keep], xx[keep]
            projection = reduced.get("projection", {}).get(lens, "fisheye")
            X = _smooth_design(y.astype(float), x.astype(float),
                               rectilinear_degree if projection == "rectilinear" else None)
            # the least-squares solution of every setting from one pseudo-inverse (the same pixels each time;
            # singular values below the size times the machine epsilon dropped, as lstsq's default)
            X_pinv = np.linalg.pinv(X)
            fpn = d["fpn_map_dn"].sel(band=band).values[y, x]
            read = float(d["read_noise_dn"].sel(band=band).sel(iso=iso, method="nearest"))
            n_dark = int(d["obs_setting__n_frames"].values.min()) if "obs_setting__n_frames" in d else 1
            sites = SITES_PER_BAND_PIXEL[band]
            # error of the dark stage's offset map in one band pixel (DN^2): read noise over its dark frames
            offset_var = read**2 / sites / max(n_dark, 1)
            ratios = []
            for (l2, b2, sweep, key), mom in reduced["moments"].items():
                if l2 != lens or b2 != band or sweep != "exposure" or key[0] != iso:
                    continue
                if mom.n < 2 or (lens, band, key) in saturated:
                    continue
                # dark-corrected pixel means, back on the linear signal (and their temporal variance with them)
                mean, slope = linear_signal(mom.mean()[keep] - fpn - dark_level_dn(d, band, key[0], key[1]),
                                            beta, full_scale_dn)
                common = max(float(offset_var_dn2.get((lens, band, key), 0.0)), 0.0)
                var_t = np.maximum(mom.variance()[keep] - common, 0.0) * slope**2
                smooth = X @ (X_pinv @ mean)
                resid = mean - smooth
                signal = smooth
                level = float(np.mean(signal))
                noise_var = float(var_t.mean()) / mom.n + offset_var * float(np.mean(slope**2))
                n = resid.size
                measured = float(np.sum(resid**2) / max(n - X.shape[1], 1))
                rows.append({"lens": lens, "band": band, "sweep": sweep, "iso": key[0], "exposure_s": key[1],
                             "n_pixels": n, "spatial_var_dn2": measured, "noise_var_dn2": noise_var,
                             "signal_dn": level, "signal_sq_per_site_dn2": float(np.mean(signal**2)) / sites})
                s_pos = np.maximum(signal, 1e-9)
                # per pixel: variance of the relative residual from this setting's temporal noise alone (the
                # setting's mean temporal variance: a pixel's own, from a few frames, is too noisy to weight by)
                ratios.append((resid / s_pos, float(var_t.mean()) / mom.n / s_pos**2, 1.0 / s_pos))
            if ratios:
                r, v, inv_s = (np.stack([q[k] for q in ratios]) for k in range(3))
                w = 1.0 / np.maximum(v + offset_var * inv_s**2, 1e-30)
                wsum = np.sum(w, axis=0)
                fmap[bi][y, x] = 1.0 + np.sum(w * r, axis=0) / wsum
                # independent temporal parts, plus the offset map's error common to the settings
                common = np.sum(w * inv_s, axis=0) / wsum
                fsig[bi][y, x] = np.sqrt(np.sum(w**2 * v, axis=0) / wsum**2 + offset_var * common**2)
        maps[lens] = (fmap, fsig)
    table = pd.DataFrame(rows)
    if len(table):
        table["value_dn"] = table["spatial_var_dn2"] - table["noise_var_dn2"]
        # spread of a sample variance of N roughly Gaussian values: var sqrt(2 / N),
        # with var the variance actually there (noise plus any flat-field pattern)
        table["sigma_dn"] = np.maximum(table["spatial_var_dn2"], table["noise_var_dn2"]) * np.sqrt(2.0 / table["n_pixels"])
        table["group"] = table["lens"] + "/" + table["band"]
    return table, maps
