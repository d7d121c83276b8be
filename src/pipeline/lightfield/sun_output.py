"""The sun closure of exposure brackets in the light-field output: per bracket variables and the ``obs_sun`` table.

:mod:`pipeline.lightfield.sun` measures and closes; this module runs it on the
shortest exposure of each bracket, chooses each bracket's attitude (the log,
level, or fitted from the sun) and writes the result as variables with units
along ``frame`` and one residual row per bracket and component (``obs_sun``).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import xarray as xr

from pipeline.errors import InputError
from pipeline.lightfield.hdr import exposure_maps
from pipeline.lightfield.sun import FIT_MODELS, SunCentroid, fit_attitude_from_sun, sun_centroid, sun_closure
from pipeline.stages.observations import table_to_dataset

__all__ = ["CENTROID_BAND", "shortest_exposure_sun_centroid", "sun_attitudes", "sun_dataset"]

#: the band whose saturated core and rim give the centroid (the Bayer pattern's densest)
CENTROID_BAND = "G"

_VARS = {
    "camera_zenith_deg": ("sun centroid: zenith angle in the camera's grid frame", "degree"),
    "camera_azimuth_deg": ("sun centroid: azimuth in the camera's grid frame", "degree"),
    "centroid_sigma_deg": ("sun centroid: standard uncertainty from the pixels' weights (noise and the disc's "
                           "unresolved edge), RMS of the two tangent components", "degree"),
    "geometry_sigma_deg": ("sun centroid: the geometry's stated theta uncertainty at the sun", "degree"),
    "measured_zenith_deg": ("sun centroid turned into the earth frame by the attitude: zenith angle", "degree"),
    "measured_azimuth_deg": ("sun centroid in the earth frame: azimuth from north towards east", "degree"),
    "residual_zenith_deg": ("sun closure: measured less solar zenith angle", "degree"),
    "residual_zenith_sigma_deg": ("its standard uncertainty (geometry, centroid, attitude)", "degree"),
    "residual_horizontal_deg": ("sun closure: measured less solar azimuth times sin(solar zenith angle)", "degree"),
    "residual_horizontal_sigma_deg": ("its standard uncertainty (geometry, centroid, attitude)", "degree"),
    "heading_offset_deg": ("sun closure: measured less solar azimuth (what a heading error gives)", "degree"),
    "heading_offset_sigma_deg": ("its standard uncertainty", "degree"),
    "angle_deg": ("sun closure: angle between the measured and the solar direction", "degree"),
    "sigma_deg": ("standard uncertainty of the closure along the residual's direction", "degree"),
    "z": ("sun closure angle over its standard uncertainty", "1"),
    "chi2": ("sun closure chi-squared on 2 degrees of freedom (both components, full covariance)", "1"),
    "p_value": ("probability of a chi-squared this large from the stated uncertainty alone", "1"),
}


def shortest_exposure_sun_centroid(raw, bundle, chains, lenses, medium, effects, zenith_lens, full_scale_dn):
    """The sun's centroid in a bracket's shortest exposure ``raw`` (None where no pixel saturates).

    Parameters
    ----------
    raw : RawFrame
        The bracket's shortest exposure, decoded.
    bundle : xarray.Dataset
        The calibration bundle.
    chains : dict
        ``{(lens, band): BandChain}``, the measurement chain of each lens and band.
    lenses : sequence of str
        The lenses.
    medium : str
        "air" or "water".
    effects : collection of str
        The effects the chain applies.
    zenith_lens : str
        The lens that looks at the grid's zenith.
    full_scale_dn : numpy.ndarray
        The response's full scale, DN, shape ``(lens, band)`` over R, G, B.

    Returns
    -------
    SunCentroid or None
        The centroid in band ``CENTROID_BAND``, or None.
    """
    b = ["R", "G", "B"].index(CENTROID_BAND)
    maps = exposure_maps(raw, bundle, chains, lenses, medium, effects, [CENTROID_BAND])
    return sun_centroid(maps, bundle, lenses, medium, zenith_lens, full_scale_dn[:, b], CENTROID_BAND, 0)


def sun_attitudes(centroids, logged, solar, model: str | None, names):
    """Each bracket's attitude: ``logged`` (from the log or level) or, with ``model``, fitted from the sun.

    Every bracket must show the sun when the attitude is fitted from it.

    Parameters
    ----------
    centroids : list of SunCentroid or None
        Each bracket's sun centroid.
    logged : list of Attitude
        Each bracket's attitude from the log, or level.
    solar : list of tuple of float
        Each bracket's (solar zenith angle, solar azimuth), degree.
    model : str or None
        The attitude-from-sun model (``FIT_MODELS``), or None to keep ``logged``.
    names : list of str
        The brackets' names, for the error messages.

    Returns
    -------
    attitudes : list of Attitude
        Each bracket's attitude.
    fits : list of dict or None
        Each bracket's fit (:func:`pipeline.lightfield.sun.fit_attitude_from_sun`), or None without ``model``.

    Raises
    ------
    InputError
        On an unknown model, a bracket without a saturated sun, or the sun below the horizon.
    """
    if model is None:
        return list(logged), None
    if model not in FIT_MODELS:
        raise InputError(None, f"--attitude-from-sun {model!r}: one of {', '.join(FIT_MODELS)}")
    fits = []
    for name, c, (sz, sa) in zip(names, centroids, solar):
        if c is None:
            raise InputError(name, "no saturated sun in the shortest exposure: the attitude cannot be fitted "
                                   "from the sun")
        if sz >= 90.0:
            raise InputError(name, f"the sun is below the horizon (zenith {sz:.1f} deg) at the site and time")
        fits.append(fit_attitude_from_sun(c, sz, sa, model))
    return [f["attitude"] for f in fits], fits


def sun_dataset(centroids: list[SunCentroid | None], attitudes, solar, names, z_limit: float, fits=None) -> xr.Dataset:
    """The sun variables along ``frame`` and the ``obs_sun`` residual table (two rows per bracket with a sun).

    Parameters
    ----------
    centroids : list of SunCentroid or None
        Each bracket's sun centroid.
    attitudes : list of Attitude
        Each bracket's attitude.
    solar : list of tuple of float
        Each bracket's (solar zenith angle, solar azimuth), degree.
    names : list of str
        The brackets' names.
    z_limit : float
        A closure component beyond this many sigmas names its cause.
    fits : list of dict, optional
        The attitude fits from the sun (:func:`sun_attitudes`).

    Returns
    -------
    xarray.Dataset
        ``sun_*`` variables along ``frame`` (degree, with ``long_name`` and ``units``) and the ``obs_sun`` table.
    """
    n = len(centroids)
    values = {k: np.full(n, np.nan) for k in _VARS}
    lens = np.array([""] * n, dtype=object)
    core = np.zeros(n, np.int32)
    named = np.array([""] * n, dtype=object)
    rows = []
    for f, (c, att, (sz, sa)) in enumerate(zip(centroids, attitudes, solar)):
        if c is None or not np.isfinite(sz):
            continue
        lens[f], core[f] = c.lens, c.core_pixels
        values["camera_zenith_deg"][f], values["camera_azimuth_deg"][f] = c.camera_zenith_deg, c.camera_azimuth_deg
        values["centroid_sigma_deg"][f], values["geometry_sigma_deg"][f] = c.centroid_sigma_deg, c.geometry_sigma_deg
        res = sun_closure(c, att, sz, sa, z_limit)
        for k in _VARS:
            if k in res:
                values[k][f] = res[k]
        named[f] = res["named"]
        for comp in ("zenith", "horizontal"):
            v, s = res[f"residual_{comp}_deg"], res[f"residual_{comp}_sigma_deg"]
            rows.append({"group": "sun", "frame": names[f], "lens": c.lens, "band": c.band, "component": comp,
                         "value_deg": v, "sigma_deg": s, "pred_deg": 0.0, "z": v / s, "used": 1})
    data = {f"sun_{k}": ("frame", v, {"long_name": text, "units": unit}) for k, (text, unit) in _VARS.items()
            for v in [values[k]]}
    data["sun_lens"] = ("frame", lens.astype(str), {"long_name": "lens whose image holds the sun's centroid"})
    data["sun_core_pixels"] = ("frame", core, {"long_name": "band pixels saturated in the sun's core", "units": "1"})
    data["sun_closure_named"] = ("frame", named.astype(str), {
        "long_name": f"cause a closure component beyond {z_limit:g} sigma names (empty: within its uncertainty)"})
    ds = xr.Dataset(data)
    if fits is not None:
        ds["sun_fit_heading_deg"] = ("frame", np.array([x["heading_deg"] for x in fits]),
                                     {"long_name": "heading fitted from the sun", "units": "degree"})
        ds["sun_fit_heading_sigma_deg"] = ("frame", np.array([x["heading_sigma_deg"] for x in fits]),
                                           {"long_name": "its standard uncertainty", "units": "degree"})
        ds["sun_fit_tilt_deg"] = ("frame", np.array([x["tilt_deg"] for x in fits]), {
            "long_name": "tilt of the camera's zenith towards the sun's camera azimuth fitted from the sun "
                         "(0: the horizon level assumed)", "units": "degree"})
        ds["sun_fit_tilt_sigma_deg"] = ("frame", np.array([x["tilt_sigma_deg"] for x in fits]),
                                        {"long_name": "its standard uncertainty", "units": "degree"})
        ds["sun_fit_chi2"] = ("frame", np.array([x["chi2"] for x in fits]), {
            "long_name": "chi-squared of the fit (degrees of freedom: the attribute sun_fit_dof)", "units": "1"})
    if rows:
        obs = table_to_dataset(pd.DataFrame(rows), "obs_sun")
        obs["obs_sun__value_deg"].attrs.update({"long_name": "sun closure residual component", "units": "degree"})
        obs["obs_sun__sigma_deg"].attrs.update({"long_name": "its standard uncertainty", "units": "degree"})
        ds = ds.merge(obs)
    return ds
