"""The geometric calibration against the roll-off's rotation stage (issue 10, item 5: closure across experiments).

Two experiments measure the field angle of the same lens independently: the geometry stage fits the lens
model to chessboard corners (Larouche et al. 2024, Section 2.3), and the roll-off experiment turns the
camera on a rotation stage so that the sphere port sits at a logged angle in one of two azimuth planes
(Sections 2.4 and 3.3; ``rolloff/frames.csv``, ``angle_deg`` and ``azimuth_deg``). The paper converts the stage's
angles with the geometric calibration; here each one is a test of it: the fitted model's direction of the
port spot's centroid (the roll-off stage's ``spot_x_px``, ``spot_y_px``, green band) projected into the
rotation plane, a = atan2(r . e_az, r_z) with r the unit ray and e_az the plane's direction in the image,
against the stage's signed angle.

The table ``closure/field_angle``, one row per roll-off setting of the green band and medium:

* value: a - angle (degree); one free zero per lens, medium and azimuth plane (``x_zero_az<azimuth>``:
  where the stage reads 0 need not be the optical axis to better than the mount's alignment);
* noise: the spot centroid's own error, the roll-off artefact's ``spot_x_sigma_px`` and ``spot_y_sigma_px``
  (computed from the data by the roll-off stage: pixel noise, the frames' scatter through the threshold's cut,
  the pixel grid's sampling; :func:`pipeline.stages.rolloff._add_centroid_sigma`) through the lens model's
  d a / d u and d a / d v (:func:`in_plane_pixel_gradient`), independent from spot to spot; and the geometric model's
  error, common to every spot of a lens and medium, as what it is: whitened nuisance columns
  (``x_geometry_<k>``, the gradient of a with respect to the model's parameters, by central differences,
  times a square root of the geometry artefact's parameter covariance) with one prior row each (kind
  ``geometry_prior``, 0 +/- 1), so that every fit of the table, the diagnostics' too, moves the lens model
  only as far as its stated covariance allows. The chi-square of the rows is then that of generalised
  least squares under the model's covariance plus the centroids' noise.

A rotation stage whose scale is off, a lens model that fails where the boards did not reach (the rim), a
lens that changed between the two sessions (focus, a dome put back differently) or an image circle cut
short all leave structure in angle or medium that the stated noise does not hold. The green band alone:
the spot is found in it, and each band's model maps its own sites (R and B sit a quarter band pixel off).
A rectilinear region (``projection: rectilinear``) or a geometry without the fisheye model's covariance
has no rows. The table tests the geometry; it does not correct it: a flux-weighted centroid sits towards the
axis where the roll-off falls across the port, more so where the threshold cuts the G band's half-lit edge
pixels on the bright side and not on the dim one (up to half a degree for the tiny simulated camera's
6 degree port at 60 to 80 degrees, some hundredths at the small scale's 1.8 degree port), which the stated
centroid noise does not hold as a bias: on the tiny camera the table's chi2 stays some 15 % above its dof
with a centroid noise that holds the errors about their smooth trend (docs/effects-and-diagnostics.md, "Closure and diagnostics").
Nothing here reads a simulator's truth: only the geometry and roll-off artefacts.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import xarray as xr

from pipeline.geometry.scaramuzza import FisheyeModel
from pipeline.geometry.theta_uncertainty import shifted_model
from pipeline.stages.observations import dataset_to_table, datasets_by_lens
from pipeline.stages.geometry_maps import model_from_dataset

__all__ = ["LEVEL", "PRIOR_KIND", "field_angle_table", "in_plane_angle_deg", "in_plane_gradient"]

#: the level of the closure table
LEVEL = "field_angle"
#: kind of the geometry prior's pseudo-measurements
PRIOR_KIND = "geometry_prior"
#: relative central-difference step of the model's parameters (the angle is smooth in all of them)
_STEP = 1.0e-6
#: step (band pixels) of the central differences of the angle in the pixel coordinates
_PIXEL_STEP_PX = 1.0e-3
#: eigenvalues of the parameter covariance below this fraction of the largest carry no direction
_RANK_TOL = 1.0e-12


def in_plane_angle_deg(model: FisheyeModel, u, v, azimuth_deg) -> np.ndarray:
    """Signed angle (degree) from the optical axis of the ray of pixel (u, v), projected into the plane
    that holds the axis and the image direction ``azimuth_deg``: positive towards that azimuth.

    Parameters
    ----------
    model : FisheyeModel
        The lens's geometric model (band pixels).
    u, v : numpy.ndarray
        Band pixel coordinates.
    azimuth_deg : float or numpy.ndarray
        The image direction of the plane, degree (camera azimuth, from +u towards +v).

    Returns
    -------
    numpy.ndarray
        The signed angle, degree.
    """
    ray = model.cam2world(u, v)
    az = np.radians(np.asarray(azimuth_deg, float))
    return np.degrees(np.arctan2(ray[..., 0] * np.cos(az) + ray[..., 1] * np.sin(az), ray[..., 2]))


def _step(model: FisheyeModel, name: str) -> float:
    if name.startswith("a") and name[1:].isdigit():
        k = int(name[1:])
        coef = model.poly[k] if k < len(model.poly) else 0.0
        return _STEP * max(abs(coef), 1e-12)
    return _STEP * (max(abs(model.xc), 1.0) if name in ("xc_px", "yc_px") else 1.0)


def in_plane_gradient(model: FisheyeModel, names, u, v, azimuth_deg) -> np.ndarray:
    """d a / d p (degree per unit of each parameter) of :func:`in_plane_angle_deg`: (len(names), n).

    Parameters
    ----------
    model : FisheyeModel
        The lens's geometric model (band pixels).
    names : sequence of str
        Model parameters (of :func:`pipeline.geometry.theta_uncertainty.parameter_names`).
    u, v : numpy.ndarray
        Band pixel coordinates of the n points.
    azimuth_deg : float or numpy.ndarray
        The image direction of the plane, degree.

    Returns
    -------
    numpy.ndarray
        d a / d p by central differences, degree per unit of each parameter, shape ``(len(names), n)``.
    """
    out = np.empty((len(names), np.size(u)))
    for i, name in enumerate(names):
        h = _step(model, name)
        out[i] = (np.ravel(in_plane_angle_deg(shifted_model(model, name, h), u, v, azimuth_deg))
                  - np.ravel(in_plane_angle_deg(shifted_model(model, name, -h), u, v, azimuth_deg))) / (2 * h)
    return out


def in_plane_pixel_gradient(model: FisheyeModel, u, v, azimuth_deg) -> tuple[np.ndarray, np.ndarray]:
    """(d a / d u, d a / d v) (degree per band pixel) of :func:`in_plane_angle_deg`, by central differences.

    Parameters
    ----------
    model : FisheyeModel
        The lens's geometric model (band pixels).
    u, v : numpy.ndarray
        Band pixel coordinates.
    azimuth_deg : float or numpy.ndarray
        The image direction of the plane, degree (camera azimuth, from +u towards +v).

    Returns
    -------
    d_du : numpy.ndarray
        d a / d u, degree per band pixel, flattened.
    d_dv : numpy.ndarray
        d a / d v, degree per band pixel, flattened.
    """
    h = _PIXEL_STEP_PX
    du = (in_plane_angle_deg(model, u + h, v, azimuth_deg) - in_plane_angle_deg(model, u - h, v, azimuth_deg)) / (2 * h)
    dv = (in_plane_angle_deg(model, u, v + h, azimuth_deg) - in_plane_angle_deg(model, u, v - h, azimuth_deg)) / (2 * h)
    return np.ravel(du), np.ravel(dv)


def _covariance_root(cov: np.ndarray) -> np.ndarray:
    """R with R R^T = cov (p x r), over the directions the covariance holds."""
    w, q = np.linalg.eigh(0.5 * (cov + cov.T))
    keep = w > _RANK_TOL * max(float(w.max()), 0.0)
    return q[:, keep] * np.sqrt(w[keep])


def _lens_rows(lens: str, geo: xr.Dataset, roll: xr.Dataset) -> list[pd.DataFrame]:
    if geo.attrs.get("projection", "fisheye") != "fisheye" or "geometry_parameter_covariance" not in geo:
        return []
    t = dataset_to_table(roll, "obs_setting")
    need = {"kind", "band", "medium", "azimuth_deg", "angle_deg", "spot_x_px", "spot_y_px", "spot_x_sigma_px",
            "spot_y_sigma_px"}
    if not need <= set(t.columns):
        return []
    t = t[(t["kind"].astype(str) == "spot") & (t["band"].astype(str) == "G")]
    t = t[np.isfinite(t["spot_x_px"].astype(float)) & np.isfinite(t["spot_y_px"].astype(float))]
    names = [str(n) for n in geo["geometry_parameter"].values]
    out = []
    for medium, g in t.groupby(t["medium"].astype(str), sort=True):
        if medium not in [str(m) for m in geo["medium"].values]:
            continue
        cov = geo["geometry_parameter_covariance"].sel(medium=medium, band="G").values.astype(float)
        if not np.all(np.isfinite(cov)):
            continue
        model = model_from_dataset(geo, medium, "G")
        u, v = g["spot_x_px"].to_numpy(float), g["spot_y_px"].to_numpy(float)
        az, angle = g["azimuth_deg"].to_numpy(float), g["angle_deg"].to_numpy(float)
        a = np.ravel(in_plane_angle_deg(model, u, v, az))
        # the centroid's own standard uncertainty per axis (roll-off artefact) through the model's d a / d (u, v)
        da_du, da_dv = in_plane_pixel_gradient(model, u, v, az)
        sigma = np.hypot(da_du * g["spot_x_sigma_px"].to_numpy(float), da_dv * g["spot_y_sigma_px"].to_numpy(float))
        root = _covariance_root(cov[:len(names), :len(names)])
        cols = in_plane_gradient(model, names, u, v, az).T @ root            # (n, r)
        rows = pd.DataFrame({
            "lens": lens, "medium": medium, "band": "G", "kind": "spot", "azimuth_deg": az, "angle_deg": angle,
            "spot_x_px": u, "spot_y_px": v, "geometry_angle_deg": a,
            "value_dn": a - angle,
            "sigma_dn": sigma,
            "group": f"{lens}/{medium}",
        })
        for plane in np.unique(az):
            rows[f"x_zero_az{plane:g}"] = (az == plane).astype(float)
        for k in range(cols.shape[1]):
            rows[f"x_geometry_{k + 1}"] = cols[:, k]
        prior = rows.iloc[[0] * cols.shape[1]].copy().reset_index(drop=True)
        for c in [c for c in prior.columns if c.startswith("x_")]:
            prior[c] = 0.0
        for k in range(cols.shape[1]):
            prior.loc[k, f"x_geometry_{k + 1}"] = 1.0
        prior = prior.assign(kind=PRIOR_KIND, value_dn=0.0, sigma_dn=1.0, spot_x_px=np.nan, spot_y_px=np.nan,
                             geometry_angle_deg=np.nan)
        out.append(pd.concat([rows, prior], ignore_index=True))
    return out


def field_angle_table(loaded: dict[str, list[xr.Dataset]], config: dict) -> pd.DataFrame:
    """``closure/field_angle`` (module docstring): the geometry's in-plane angle of each roll-off spot
    against the rotation stage's angle, per lens and medium, with the geometry's error as nuisance columns.

    Parameters
    ----------
    loaded : dict[str, list of xarray.Dataset]
        The stage artefacts per stage (``geometry`` and ``rolloff`` used), one per lens.
    config : dict
        The configuration.

    Returns
    -------
    pandas.DataFrame
        One row per roll-off spot (``kind`` "spot"): ``value_dn`` the geometry's in-plane angle less the
        stage's angle (degree), ``sigma_dn`` its sigma from the spot's centroid (degree), the columns
        ``x_zero_az*`` (one zero per plane) and ``x_geometry_*`` (the geometry's error, whitened); and the
        prior rows of those nuisance parameters (0 +/- 1). Empty when no lens has both artefacts.
    """
    geometry, rolloff = datasets_by_lens(loaded.get("geometry", [])), datasets_by_lens(loaded.get("rolloff", []))
    parts = [p for lens in sorted(set(geometry) & set(rolloff))
             for p in _lens_rows(lens, geometry[lens], rolloff[lens])]
    if not parts:
        return pd.DataFrame()
    out = pd.concat(parts, ignore_index=True)
    x_cols = [c for c in out.columns if c.startswith("x_")]
    out[x_cols] = out[x_cols].fillna(0.0)
    return out
