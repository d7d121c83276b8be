"""The geometry artefact's maps: what every later stage reads instead of refitting.

Layout of ``results/geometry/<lens>.nc`` (stage ``geometry``): dimensions
``medium`` (air, water), ``band`` (R, G, B), ``y``, ``x`` (band-image pixels)
and ``coef`` (polynomial coefficients a0, a1, ...):

* ``theta_deg``, ``phi_deg``: viewing direction of every band pixel centre;
* ``solid_angle_sr``: solid angle seen by every band pixel;
* ``poly``, ``xc_px``, ``yc_px``, ``stretch_c``, ``stretch_d``, ``stretch_e``,
  ``half_fov_deg``: the Scaramuzza model, from which :func:`model_from_dataset`
  rebuilds a :class:`~pipeline.geometry.scaramuzza.FisheyeModel` for the
  inverse mapping (direction to pixel).

Conventions of :mod:`pipeline.geometry.scaramuzza` (pixel centres at integer
coordinates, theta from the optical axis, phi from +u towards +v).
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from pipeline.io.bands import BANDS
from pipeline.geometry.maps import solid_angle_map, theta_phi_maps
from pipeline.geometry.scaramuzza import FisheyeModel

MEDIA = ("air", "water")


def maps_dataset(models: dict[tuple[str, str], FisheyeModel], band_shape: tuple[int, int]) -> xr.Dataset:
    """Maps and model parameters for every (medium, band) in ``models``.

    Parameters
    ----------
    models : dict[tuple[str, str], pipeline.geometry.scaramuzza.FisheyeModel]
        (medium, band) -> the fitted fisheye model.
    band_shape : tuple[int, int]
        (rows, columns) of the band images, band pixels.

    Returns
    -------
    xarray.Dataset
        Over (medium, band, y, x): ``theta_deg`` and ``phi_deg`` (each band pixel's viewing direction, degree)
        and ``solid_angle_sr`` (sr), float32, NaN outside the field of view; over (medium, band): the
        polynomial ``poly``, principal point ``xc_px`` and ``yc_px`` (band pixels), stretch ``c``, ``d``, ``e``
        and ``half_fov_deg`` (degree). Media in the order of ``MEDIA``; a (medium, band) without a model is NaN.
    """
    media = [m for m in MEDIA if any(k[0] == m for k in models)]
    n_coef = max(len(m.poly) for m in models.values())
    shape = (len(media), len(BANDS)) + tuple(band_shape)
    theta = np.full(shape, np.nan, dtype=np.float32)
    phi = np.full(shape, np.nan, dtype=np.float32)
    omega = np.full(shape, np.nan, dtype=np.float32)
    poly = np.full((len(media), len(BANDS), n_coef), np.nan)
    scalars = {k: np.full((len(media), len(BANDS)), np.nan)
               for k in ("xc_px", "yc_px", "stretch_c", "stretch_d", "stretch_e", "half_fov_deg")}
    for (medium, band), model in models.items():
        i, j = media.index(medium), BANDS.index(band)
        t, p = theta_phi_maps(model, band_shape)
        theta[i, j], phi[i, j] = t, p
        omega[i, j] = solid_angle_map(model, band_shape)
        poly[i, j, :len(model.poly)] = model.poly
        for key, value in (("xc_px", model.xc), ("yc_px", model.yc), ("stretch_c", model.c),
                           ("stretch_d", model.d), ("stretch_e", model.e),
                           ("half_fov_deg", model.half_fov_deg if model.half_fov_deg else np.nan)):
            scalars[key][i, j] = value
    dims = ("medium", "band", "y", "x")
    ds = xr.Dataset(
        {
            "theta_deg": (dims, theta, {"long_name": "angle of the viewing direction from the optical axis", "units": "degree"}),
            "phi_deg": (dims, phi, {"long_name": "azimuth of the viewing direction (from +x towards +y)", "units": "degree"}),
            "solid_angle_sr": (dims, omega, {"long_name": "solid angle seen by the band pixel", "units": "sr"}),
            "poly": (("medium", "band", "coef"), poly, {"long_name": "Scaramuzza f(rho) coefficients, ascending", "units": "1",
                                                        "comment": "the coefficient of rho^k is in pixel^(1-k) (rho and "
                                                                   "f(rho) in band pixels, a pixel counted as 1)"}),
            "xc_px": (("medium", "band"), scalars["xc_px"], {"long_name": "principal point column", "units": "pixel"}),
            "yc_px": (("medium", "band"), scalars["yc_px"], {"long_name": "principal point row", "units": "pixel"}),
            "stretch_c": (("medium", "band"), scalars["stretch_c"], {"units": "1"}),
            "stretch_d": (("medium", "band"), scalars["stretch_d"], {"units": "1"}),
            "stretch_e": (("medium", "band"), scalars["stretch_e"], {"units": "1"}),
            "half_fov_deg": (("medium", "band"), scalars["half_fov_deg"], {"long_name": "half field of view", "units": "degree"}),
        },
        coords={"medium": list(media), "band": list(BANDS)},
    )
    return ds


def model_from_dataset(ds: xr.Dataset, medium: str, band: str) -> FisheyeModel:
    """The fisheye model of one medium and band, rebuilt from a geometry artefact (the inverse of :func:`maps_dataset`).

    Parameters
    ----------
    ds : xarray.Dataset
        The geometry artefact (or :func:`maps_dataset`'s dataset).
    medium : str
        ``"air"`` or ``"water"``.
    band : str
        ``"R"``, ``"G"`` or ``"B"``.

    Returns
    -------
    pipeline.geometry.scaramuzza.FisheyeModel
        The model: polynomial coefficients (the finite ones), principal point and stretch, the maps' shape and
        half field of view (None when the artefact has NaN).
    """
    sel = ds.sel(medium=medium, band=band)
    poly = [float(a) for a in sel["poly"].values if np.isfinite(a)]
    half = float(sel["half_fov_deg"])
    return FisheyeModel(poly=poly, xc=float(sel["xc_px"]), yc=float(sel["yc_px"]), c=float(sel["stretch_c"]),
                        d=float(sel["stretch_d"]), e=float(sel["stretch_e"]),
                        shape=(ds.sizes["y"], ds.sizes["x"]), half_fov_deg=half if np.isfinite(half) else None)

