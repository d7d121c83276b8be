"""Bracket consistency: where two exposures of a bracket both measure a pixel, the response model must agree.

Two consecutive exposures t_s < t_l of a bracket that both measure a pixel
unsaturated must give the same radiance: the ratio L_l / L_s is one for a
right response model (the band-common terms and the pixel's fixed pattern
are the same in both and cancel; the random and per-exposure systematic
sigmas of :mod:`pipeline.lightfield.hdr` do not). The pixels of one exposure
pair, lens and band are chosen and binned by their level measured by the
bracket's *other* exposures (a cut on the pair's own noisy readings would
bias their ratio: a pixel whose short reading fluctuated down has a smaller
shot noise and passes a signal-to-noise cut more often), read at a
signal-to-noise ratio of at least ``lightfield.bracket_closure_min_snr`` by
each of the pair as their noise models predict for that level, and with the long exposure's predicted signal
at most ``lightfield.bracket_closure_max_signal_fraction`` of the full scale,
in ``lightfield.bracket_closure_signal_bins`` bins; each bin gives one row,
ln(sum L_l / sum L_s) over its pixels, with the variance of the two sums'
random noise plus the pixels' mean per-exposure relative variances (common
to a frame's pixels, they do not average down). The rows form the residual table ``obs_bracket`` of the experiment
``lightfield``, in the form of the stages' tables (``value_dn`` the log
ratio, ``sigma_dn``, ``pred_dn`` 0, ``z``, the block ``frame`` = the exposure
pair), so that the diagnostics' residual test and the effects' signatures
take it:

- ``nonlinearity`` (a response m = s (1 - beta s / F)) leaves
  ln(L_l / L_s) = -beta (s_l - s_s) / F: it grows with the signal level within
  a pair;
- ``shutter_offset`` (true exposure t + dt, the chain dividing by t) leaves
  ln((1 + dt / t_l) / (1 + dt / t_s)), about dt (1 / t_l - 1 / t_s): one value
  per pair, the same at every signal level.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.io.bands import BANDS
from pipeline.diagnostics.missing_effects import rank_missing_effects
from pipeline.diagnostics.tables import Observations
from pipeline.lightfield.hdr import ExposureMaps

__all__ = ["EXPERIMENT", "LEVEL", "bracket_table", "bracket_consistency"]

EXPERIMENT, LEVEL = "lightfield", "bracket"


def _proxy(maps: list[ExposureMaps], usable: np.ndarray, skip: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel the inverse-variance mean radiance of the bracket's exposures other than ``skip``, and its
    random sigma: a level independent of the pair's own noise (NaN where no other exposure measures it)."""
    num = den = den2 = 0.0
    for k, m in enumerate(maps):
        if k in skip:
            continue
        var = m.random_sigma ** 2 + m.exposure_sigma ** 2
        ok = usable & ~m.saturated & np.isfinite(m.radiance) & np.isfinite(var) & (var > 0)
        w = np.where(ok, 1.0 / np.where(ok, var, 1.0), 0.0)
        num = num + w * np.where(ok, m.radiance, 0.0)
        den = den + w
        den2 = den2 + w ** 2 * np.where(ok, m.random_sigma, 0.0) ** 2
    if np.ndim(den) == 0:                       # a bracket of two exposures: no other exposure measures the pair
        nan = np.full(np.shape(maps[0].radiance), np.nan)
        return nan, nan.copy()
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / den, np.nan), np.where(den > 0, np.sqrt(den2) / den, np.nan)


def bracket_table(maps: list[ExposureMaps], bracket: str, lenses, full_scale_dn, min_snr: float,
                  n_bins: int, max_signal_fraction: float, bands=BANDS) -> pd.DataFrame:
    """The ``obs_bracket`` rows of one bracket (``maps`` by exposure; ``full_scale_dn[lens, band]`` the
    response's full scale, the bundle's nonlinearity full scale or saturation level; ``lenses`` and ``bands``
    name the maps' lens and band axes).

    A pixel enters the pair (k, k + 1) by its level P measured by the bracket's other exposures (never by
    the pair's own readings, whose noise a cut would turn into a bias of the ratio): P at least
    ``min_snr`` times its own random sigma and read by each of the pair at a signal-to-noise ratio of at least
    ``min_snr`` by their noise models (:meth:`ExposureMaps.predicted_snr`), and P's predicted long-exposure signal at most
    ``max_signal_fraction`` of the full scale; both readings unsaturated. The pixels are binned by P; a
    row is ln(sum L_l / sum L_s) over its pixels (equal weights, so that the estimate's bias is that of a
    sum of many pixels), its variance sum r_l^2 / (sum L_l)^2 + sum r_s^2 / (sum L_s)^2 plus the pixels'
    mean per-exposure relative variances (common to a frame's pixels: they do not average down).

    Parameters
    ----------
    maps : list of ExposureMaps
        The bracket's frames through the chain, by exposure.
    bracket : str
        The bracket's name.
    lenses : sequence of str
        The maps' lens axis.
    full_scale_dn : numpy.ndarray
        ``full_scale_dn[lens, band]``, DN.
    min_snr : float
        Least signal-to-noise ratio of the level and of each reading.
    n_bins : int
        Bins of the level per lens, band and pair (quantiles of the level).
    max_signal_fraction : float
        Largest predicted long-exposure signal, as a fraction of the full scale.
    bands : sequence of str, default BANDS
        The maps' band axis.

    Returns
    -------
    pandas.DataFrame
        One row per pair of consecutive exposures, lens, band and bin: ``value_dn`` ln(sum L_l / sum L_s)
        (dimensionless), ``sigma_dn`` its standard uncertainty, the exposures (s), the mean signals above dark
        (DN), the full scale (DN) and the number of pixels.
    """
    rows = []
    usable = np.logical_and.reduce([m.usable for m in maps])
    for k in range(len(maps) - 1):
        s, lo = maps[k], maps[k + 1]
        level, level_sigma = _proxy(maps, usable, (k, k + 1))
        # the pair's signal-to-noise ratios predicted for the level by each exposure's noise model (never the
        # sigmas of their own readings, which carry those readings' noise through the shot term)
        snr_s, snr_l = s.predicted_snr(level), lo.predicted_snr(level)
        for i, lens in enumerate(lenses):
            for b, band in enumerate(bands):
                Ls, Ll, P = s.radiance[i, b].astype(float), lo.radiance[i, b].astype(float), level[i, b]
                rs, rl = s.random_sigma[i, b], lo.random_sigma[i, b]
                ok = usable[i, b] & ~s.saturated[i, b] & ~lo.saturated[i, b] & np.isfinite(Ls) & np.isfinite(Ll)
                with np.errstate(invalid="ignore", divide="ignore"):
                    dn_per_radiance = lo.signal_dn[i, b] / Ll
                    ok &= np.isfinite(P) & (P >= min_snr * level_sigma[i, b])
                    ok &= (snr_s[i, b] >= min_snr) & (snr_l[i, b] >= min_snr)
                    ok &= (P * dn_per_radiance <= max_signal_fraction * float(full_scale_dn[i, b]))
                    ok &= np.isfinite(dn_per_radiance) & (dn_per_radiance > 0)
                if ok.sum() < n_bins:
                    continue
                p = P[ok]
                edges = np.quantile(p, np.linspace(0.0, 1.0, n_bins + 1))
                which = np.clip(np.searchsorted(edges, p, side="right") - 1, 0, n_bins - 1)
                cols = {name: x[ok] for name, x in (("Ls", Ls), ("Ll", Ll), ("rs", rs), ("rl", rl),
                                                    ("sig_s", s.signal_dn[i, b]), ("sig_l", lo.signal_dn[i, b]),
                                                    ("es", s.exposure_sigma[i, b]), ("el", lo.exposure_sigma[i, b]))}
                for j in range(n_bins):
                    sel = which == j
                    if not sel.any():
                        continue
                    c = {name: x[sel] for name, x in cols.items()}
                    sum_l, sum_s = c["Ll"].sum(), c["Ls"].sum()
                    if sum_l <= 0 or sum_s <= 0:
                        continue
                    value = float(np.log(sum_l / sum_s))
                    var = (np.sum(c["rl"] ** 2) / sum_l ** 2 + np.sum(c["rs"] ** 2) / sum_s ** 2
                           + np.mean((c["el"] / c["Ll"]) ** 2 + (c["es"] / c["Ls"]) ** 2))
                    sigma = float(np.sqrt(var))
                    rows.append({
                        "group": "bracket", "bracket": bracket, "lens": str(lens), "band": band,
                        "frame": f"{bracket}:{k}-{k + 1}", "bin": j,
                        "exposure_short_s": s.exposure_s, "exposure_long_s": lo.exposure_s,
                        "signal_short_dn": float(np.mean(c["sig_s"])), "signal_long_dn": float(np.mean(c["sig_l"])),
                        "full_scale_dn": float(full_scale_dn[i, b]), "n_pixels": int(sel.sum()),
                        "value_dn": value, "sigma_dn": sigma, "pred_dn": 0.0, "z": value / sigma, "used": 1,
                    })
    return pd.DataFrame(rows)


def bracket_consistency(table: pd.DataFrame, model_effects, config: dict) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The diagnostics on the ``obs_bracket`` table: (ranked missing effects, residual test), as for the
    stages' tables (:func:`pipeline.diagnostics.missing_effects.rank_missing_effects`).

    Parameters
    ----------
    table : pandas.DataFrame
        The ``obs_bracket`` rows (:func:`bracket_table`).
    model_effects : iterable of str
        The effects the chain models.
    config : dict
        The run's configuration (its diagnostic thresholds).

    Returns
    -------
    ranked : pandas.DataFrame
        The candidate missing effects, ranked.
    tests : pandas.DataFrame
        The residual tests.
    """
    obs = [Observations(EXPERIMENT, LEVEL, table.reset_index(drop=True), "1")]
    ranked, _, tests = rank_missing_effects(obs, list(model_effects), config, with_tests=True)
    return ranked, tests
