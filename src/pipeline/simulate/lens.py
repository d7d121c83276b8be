"""The default camera's lenses: published geometry and roll-off, in air and in water.

Facts from ``docs/design.md`` ("The simulator's default camera") and
Larouche et al. (2024):

* geometry (Sections 2.3 and 3.2): OCamCalib fits
  f(rho) = a0 + a2 rho^2 + a3 rho^3 + a4 rho^4 on the full 3456-pixel raw
  lens image, half field of view 91 degrees in air and 76 in water. The
  published centres are taken as 0-based pixel-centre coordinates of that
  image (conventions of :mod:`pipeline.geometry.scaramuzza`);
* roll-off (Section 3.3, Eq. 13): in air the authors' fits of each lens and
  band from their calibration files (:mod:`pipeline.simulate.camera_data`),
  normalised to g(0) = 1; in water the in-air curve through the in-water
  geometry and the Fresnel transmissions of the front surface (not the
  authors' in-water fits, see :func:`default_rolloff`).
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import numpy as np

from pipeline.geometry.scaramuzza import FisheyeModel, fit_poly_to_theta
from pipeline.radiometry.immersion_rolloff import water_rolloff_factor
from pipeline.radiometry.rolloff import N_COEFFICIENTS, evaluate_rolloff
from pipeline.simulate.camera import RAW_SIZE_PX
from pipeline.simulate.camera_data import authors_rolloff


#: Published OCamCalib fits on the raw 3456 x 3456 lens image (green band, air).
#: Coefficients ascending, a1 = 0; centre (xc, yc) in raw pixels.
PUBLISHED_FITS = {
    "close": {
        "poly": (1019.25, 0.0, -3.0382e-4, -2.1491e-8, -2.8016e-11),
        "centre": (1731.51, 1710.86),
    },
    "far": {
        "poly": (1016.48, 0.0, -3.9436e-4, 1.5171e-7, -1.1177e-10),
        "centre": (1743.76, 1724.99),
    },
}

#: Half field of view (degrees) at the edge of the image circle, per medium.
HALF_FOV_DEG = {"air": 91.0, "water": 76.0}


def water_model(air: FisheyeModel, half_fov_water_deg: float = HALF_FOV_DEG["water"],
                degree: int = 4) -> FisheyeModel:
    """In-water model derived from an in-air model with a half FOV.

    A flat port cannot give the measured 76 degrees (Snell at a flat
    interface caps the in-water field at asin(1/1.333) = 48.6 degrees); the
    camera's curved front element loses part of its power instead. We model
    this as a uniform compression of the field angle,
    theta_water(rho) = theta_air(rho) * 76 / 91, with the image circle
    unchanged on the sensor, and refit the Scaramuzza polynomial to it.
    """
    if air.half_fov_deg is None:
        raise ValueError("air model needs half_fov_deg")
    r_circle = air.image_circle_radius()
    k = half_fov_water_deg / air.half_fov_deg
    rho = np.linspace(0.0, 1.05 * r_circle, 400)
    theta_w = air.theta_of_rho(rho) * k
    poly = fit_poly_to_theta(rho, theta_w, degree)
    return replace(air, poly=poly, half_fov_deg=half_fov_water_deg)


def default_model(lens: str = "close", medium: str = "air",
                  band_shape: tuple[int, int] | int = (1728, 1728)) -> FisheyeModel:
    """Default model of one lens in one medium for a band image of band_shape.

    Built from the published raw 3456-pixel fit: band images of size N are
    the raw lens image scaled by s = N / 3456 (N = 1728 are the true 2 x 2
    super-pixels). Stretch is identity (not published). The image circle is
    where the air model reaches 91 degrees (about 1600 raw pixels for the
    close lens); in water the same circle sees 76 degrees.
    """
    if lens not in PUBLISHED_FITS:
        raise ValueError(f"lens must be one of {sorted(PUBLISHED_FITS)}, got {lens!r}")
    if medium not in HALF_FOV_DEG:
        raise ValueError(f"medium must be one of {sorted(HALF_FOV_DEG)}, got {medium!r}")
    if np.isscalar(band_shape):
        band_shape = (int(band_shape), int(band_shape))
    fit = PUBLISHED_FITS[lens]
    raw = FisheyeModel(poly=fit["poly"], xc=fit["centre"][0], yc=fit["centre"][1],
                       shape=(RAW_SIZE_PX, RAW_SIZE_PX), half_fov_deg=HALF_FOV_DEG["air"])
    s = band_shape[1] / RAW_SIZE_PX
    model = raw.scaled(s, shape=tuple(band_shape))
    if medium == "water":
        model = water_model(model)
    return replace(model, meta={"lens": lens, "medium": medium})


#: Close lens, air, red band (supplement Table S2 of Larouche et al. 2024).
PUBLISHED_RED_AIR_CLOSE_LENS = np.array([0.99726, -7.806e-5, 4.074e-9, -4.884e-13, 2.406e-17])

#: largest departure of the stored in-water polynomial from the physics it is fitted to (0 to 76 deg)
WATER_FIT_MAX_ERROR = 1e-4
#: Lawson reweightings of the in-water fit (the plain least squares departs up to 1.04e-4 for the far lens)
LAWSON_ITERATIONS = 20

#: Published roll-off values (Section 3.3): (medium, band) -> {theta_deg: g}.
#: The in-water values are not used: the physics of water_rolloff_from_air gives 0.548, 0.612, 0.618
#: (R, G, B) at 70 deg against the published 0.491, 0.562, 0.570 (12, 9 and 8 % higher), see
#: default_rolloff.
PUBLISHED_ROLLOFF_POINTS = {
    ("air", "B"): {70.0: 0.728, 80.0: 0.645},
    ("air", "G"): {70.0: 0.719, 80.0: 0.637},
    ("air", "R"): {70.0: 0.669, 80.0: 0.577},
    ("water", "B"): {70.0: 0.570},
    ("water", "G"): {70.0: 0.562},
    ("water", "R"): {70.0: 0.491},
}


@lru_cache(maxsize=None)
def _default_table():
    # Air: the authors' fits of each lens (Larouche et al.'s calibration files, camera_data) divided by
    # their a0 (0.997 close, 0.97 far), so that g(0) = 1. The close lens's match the published 70 and
    # 80 deg values (PUBLISHED_ROLLOFF_POINTS) within 0.004.
    # Water: not the authors' in-water fits (the far lens's is not normalised and goes negative beyond
    # 76 deg), but the in-air curve through the in-water geometry and the outer surface's Fresnel
    # transmissions (radiometry.immersion_rolloff): the pixel that sees theta_w in water sees
    # theta_a = theta_w 91 / 76 in air (water_model), and
    # g_w(theta_w) = g_air(theta_a) T_wg(i_w) T_ag(0) / (T_wg(0) T_ag(i_a)), with the tank's water and the
    # front surface's index of the immersion experiment. Stored as the even 8th-degree polynomial of
    # Eq. (13) with g(0) = 1, fitted on 0 to 76 deg (largest departure from the physics under 1e-4,
    # WATER_FIT_MAX_ERROR).
    table = {}
    for lens in PUBLISHED_FITS:
        air = {}
        for band in ("R", "G", "B"):
            a = authors_rolloff(lens, "air", band)
            air[band] = a / a[0]
        water = {band: water_rolloff_from_air(a, band) for band, a in air.items()}
        table[lens] = {"air": air, "water": water}
    return table


def water_rolloff_from_air(coef_air, band: str) -> np.ndarray:
    """In-water roll-off coefficients (a0..a8, g(0) = 1) of one band from its in-air coefficients.

    The physics of :func:`pipeline.radiometry.immersion_rolloff.water_rolloff_factor` on the
    default camera's geometry (theta_a = theta_w * 91 / 76, :func:`water_model`), the water of the
    immersion experiment (n_w from Quan and Fry at the band's wavelength, 25 C, 0 PSU) and the front
    surface's index of that experiment (n_g = 1.60, 1.63, 1.58), fitted by the even polynomial.
    """
    from pipeline.simulate.immersion import true_immersion_factors  # noqa: PLC0415 (immersion imports the plan)

    true = true_immersion_factors()
    theta_w = np.linspace(0.0, HALF_FOV_DEG["water"], 400)
    theta_a = theta_w * HALF_FOV_DEG["air"] / HALF_FOV_DEG["water"]
    g = evaluate_rolloff(coef_air, theta_a) * water_rolloff_factor(theta_a, theta_w, true["n_w"][band],
                                                                   true["n_g"][band])
    powers = 2 * np.arange(1, N_COEFFICIENTS)
    u = theta_w / 90.0
    design = u[:, None] ** powers
    # least squares, then a few of Lawson's reweightings towards the smallest largest departure
    weight = np.ones_like(theta_w)
    for _ in range(LAWSON_ITERATIONS + 1):
        c = np.linalg.lstsq(design * np.sqrt(weight)[:, None], (g - 1.0) * np.sqrt(weight), rcond=None)[0]
        residual = np.abs(design @ c - (g - 1.0))
        weight = weight * residual / np.sum(weight * residual)
    coef = np.concatenate([[1.0], c / 90.0**powers])
    err = float(np.max(np.abs(evaluate_rolloff(coef, theta_w) - g)))
    if err > WATER_FIT_MAX_ERROR:
        raise RuntimeError(f"in-water roll-off polynomial departs {err:.2e} from its physics ({band})")
    return coef


def default_rolloff(band, medium="air", lens="close"):
    """Default "true" roll-off coefficients (a0..a8, theta in degrees) for the simulator.

    * air: the real camera's roll-off, the authors' fit of that lens and band
      (:func:`pipeline.simulate.camera_data.authors_rolloff`, Larouche et al.'s calibration files,
      MIT licence, (c) 2021 Raphael Larouche) divided by its a0 (0.997 for the close lens, 0.97 for the
      far one). The close lens's red fit is the published one (PUBLISHED_RED_AIR_CLOSE_LENS); its
      values at 70 and 80 deg are within 0.004 of the published ones (PUBLISHED_ROLLOFF_POINTS).
    * water: from the in-air curve through the in-water geometry and the Fresnel
      transmissions of the front surface (:func:`water_rolloff_from_air`), not the authors' in-water
      fits: the far lens's is not normalised (a0 about 0.90) and goes negative beyond 76 deg, and the
      published close-lens values at 70 deg (0.491, 0.562, 0.570) are lower by 10 to 12 % than this
      physics gives: the published curve is more compressed (g_air(k theta) with k = 1.26-1.27) than the
      published half fields of view allow (91 / 76 = 1.20). We keep the physics, so that the simulated
      camera obeys the model the pipeline tests; a camera like the published one would show the
      difference as an in-water effect.

    Monotone decreasing from 0 to 91 deg (air) and 0 to 76 deg (water).

    Parameters
    ----------
    band : str
        ``"R"``, ``"G"`` or ``"B"`` (any case).
    medium : str
        ``"air"`` or ``"water"`` (any case).
    lens : str
        ``"close"`` (the default) or ``"far"``.

    Returns
    -------
    ndarray
        A new (5,) array with g(0) = 1.
    """
    band = band.upper()
    medium = medium.lower()
    table = _default_table()
    if lens not in table:
        raise ValueError(f"lens must be one of {sorted(table)}, not {lens!r}")
    if medium not in table[lens]:
        raise ValueError(f"medium must be 'air' or 'water', not {medium!r}")
    if band not in table[lens][medium]:
        raise ValueError(f"band must be 'R', 'G' or 'B', not {band!r}")
    return table[lens][medium][band].copy()
