"""The sun's direction measured in a bracket, its closure against the solar position, and the attitude fitted from it.

Centroid (the shortest exposure of a bracket, one band, default G): the sun's
image is the largest 4-connected run of band pixels saturated in that exposure
(its core) and the ring of band pixels 4-adjacent to it (its rim). Each pixel
i of core and rim has a weight w_i: 1 in the core, clip((s_i - b) / (F - b), 0, 1)
on the rim (s_i the signal in DN above dark, F the response's full scale, b
the median signal of the ring two to three pixels out: the sky beside the
sun). The sun's direction is the normalised weighted mean of the pixels' unit
vectors d_i, c = sum w_i d_i / |sum w_i d_i|, each d_i from the bundle's
calibrated theta and phi maps by apply's sphere convention (so c is in the
camera's grid frame: zenith angle and azimuth of the grid before any
attitude). Its covariance in the plane tangent at c (components along the
camera zenith angle and azimuth) is the sum of

- the weights' uncertainty, sum_i var(w_i) x_i x_i^T / W^2 (x_i the tangent
  offset of d_i from c, W = sum w_i): for a rim pixel its noise by the chain's
  noise model, (read variance + shot * s_i) / (F - b)^2; and for every pixel
  on the edge of the disc (a core pixel with a pixel outside the core as
  4-neighbour, and every rim pixel) 1/12: where the disc's edge crosses such
  a pixel is not resolved (uniform over the pixel: a pixel reads the sun at
  its centre, or clips where a small part of it sees the sun);
- the geometry's: the bundle's ``theta_deg_sigma`` (the fit's covariance,
  centre included) averaged over the core, in both tangent directions (a
  centre shift moves a direction about as much across the radius as along it
  over the small disc; the map states only the radial part).

Closure: the solar position (pvlib, apparent zenith and azimuth at the site
and the bracket's first frame's UTC time) against c turned into the earth
frame by the frame's attitude. The residual (measured less solar) has two
components in the plane tangent at the solar direction: along the zenith
angle and horizontal (the azimuth difference times sin of the zenith angle);
its covariance adds the attitude's (roll, pitch and heading sigmas through
the numerical derivative of the earth direction of c) to the centroid's and
geometry's turned into that plane. The geometry's deviation is one draw for
all frames of a camera at the sun's field angle: over many frames it shows
as a common offset, not as spread; the residual and the frame-to-frame
covariance are therefore also given in the camera's tangent plane. Reported: the angle, its sigma along the
residual's direction, chi^2 on 2 degrees of freedom and its p value, and per
component the residual over its sigma; a component beyond
``lightfield.sun_closure_z`` names its cause: the horizontal one the
attitude's heading (a heading error moves the sun in azimuth only), the one
along the zenith angle the tilt (roll, pitch) or the geometry's theta.

Attitude from the sun (no log): one direction fixes two angles, not three.
``heading``: the horizon level assumed (roll = pitch = 0), the heading fitted
(weighted least squares of both residual components; one degree of freedom
left, whose chi^2 checks the level assumption). ``heading_tilt``: the heading
and the tilt of the camera's zenith towards the sun's camera azimuth a_s
(roll = t sin a_s, pitch = -t cos a_s), the tilt across that plane assumed 0;
an exact fit (no degree of freedom left). The sigmas from the fit's Jacobian
and the measurement covariance.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares
from scipy.stats import chi2 as chi2_dist

from pipeline.geometry.sphere import sphere_coordinates
from pipeline.lightfield.attitude import Attitude, camera_to_earth_directions

__all__ = ["SunCentroid", "sun_centroid", "sun_closure", "fit_attitude_from_sun", "FIT_MODELS", "unit_vector",
           "tangent_basis"]

FIT_MODELS = ("heading", "heading_tilt")
_EDGE_VAR = 1.0 / 12.0
_ATT_STEP_DEG = 0.05


def unit_vector(zenith_deg, azimuth_deg) -> np.ndarray:
    """Grid components (sin z cos a, sin z sin a, cos z) of directions (..., 3).

    Parameters
    ----------
    zenith_deg : numpy.ndarray
        Zenith angles, degree.
    azimuth_deg : numpy.ndarray
        Azimuths, degree.

    Returns
    -------
    numpy.ndarray
        Unit vectors, shape ``(..., 3)``.
    """
    z, a = np.radians(np.asarray(zenith_deg, float)), np.radians(np.asarray(azimuth_deg, float))
    return np.stack([np.sin(z) * np.cos(a), np.sin(z) * np.sin(a), np.cos(z)], axis=-1)


def _angles(v) -> tuple[float, float]:
    v = np.asarray(v, float) / np.linalg.norm(v)
    return float(np.degrees(np.arccos(np.clip(v[2], -1, 1)))), float(np.degrees(np.arctan2(v[1], v[0])) % 360.0)


def tangent_basis(zenith_deg: float, azimuth_deg: float) -> np.ndarray:
    """(2, 3): unit vectors along increasing zenith angle and increasing azimuth at a direction.

    Parameters
    ----------
    zenith_deg : float
        Zenith angle of the direction, degree.
    azimuth_deg : float
        Azimuth of the direction, degree.

    Returns
    -------
    numpy.ndarray
        Shape ``(2, 3)``: the unit vectors along increasing zenith angle and along increasing azimuth.
    """
    z, a = np.radians(zenith_deg), np.radians(azimuth_deg)
    return np.array([[np.cos(z) * np.cos(a), np.cos(z) * np.sin(a), -np.sin(z)],
                     [-np.sin(a), np.cos(a), 0.0]])


@dataclass(frozen=True)
class SunCentroid:
    """The sun's centroid in one frame: camera-frame direction and its covariance (deg^2) in the tangent plane
    (along the camera zenith angle, along the azimuth)."""

    file: str
    lens: str
    band: str
    exposure_s: float
    core_pixels: int
    rim_pixels: int
    camera_zenith_deg: float
    camera_azimuth_deg: float
    centroid_cov_deg2: np.ndarray
    geometry_sigma_deg: float

    @property
    def vector(self) -> np.ndarray:
        return unit_vector(self.camera_zenith_deg, self.camera_azimuth_deg)

    @property
    def cov_deg2(self) -> np.ndarray:
        """Centroid and geometry together (the measurement's covariance, before any attitude)."""
        return self.centroid_cov_deg2 + np.eye(2) * self.geometry_sigma_deg ** 2

    @property
    def centroid_sigma_deg(self) -> float:
        """RMS of the two tangent components' centroid sigmas."""
        return float(np.sqrt(np.trace(self.centroid_cov_deg2) / 2.0))


def sun_centroid(maps, bundle, lenses, medium: str, zenith_lens: str, full_scale_dn, band: str = "G",
                 band_index: int | None = None) -> SunCentroid | None:
    """The sun's centroid (module docstring) in one frame's chain output.

    Parameters
    ----------
    maps : ExposureMaps
        The frame through the chain (:class:`pipeline.lightfield.hdr.ExposureMaps`) of ``lenses`` and one or all
        bands.
    bundle : xarray.Dataset
        The calibration bundle (its ``theta_deg``, ``phi_deg`` and ``theta_deg_sigma`` maps).
    lenses : sequence of str
        The lenses of the maps' lens axis.
    medium : str
        "air" or "water": the bundle's geometry used.
    zenith_lens : str
        The lens that looks at the grid's zenith.
    full_scale_dn : numpy.ndarray
        ``full_scale_dn[lens]``: the response's full scale of the band (nonlinearity full scale, else saturation
        level), DN.
    band : str, default "G"
        The band whose saturated core and rim give the centroid.
    band_index : int, optional
        The band's position on the maps' band axis; default that of ``band`` among R, G, B when the maps hold
        them all, else 0.

    Returns
    -------
    SunCentroid or None
        The centroid's camera-frame zenith angle and azimuth (degree), its covariance (degree^2) and the
        geometry's sigma (degree); None when no pixel is saturated.
    """
    b = band_index if band_index is not None else (0 if maps.radiance.shape[1] == 1 else
                                                    ["R", "G", "B"].index(band))
    best = None
    for i in range(len(lenses)):
        core_all = maps.saturated[i, b] & maps.usable[i, b]
        if not core_all.any():
            continue
        labels, n = ndimage.label(core_all)
        sizes = ndimage.sum_labels(core_all, labels, np.arange(1, n + 1))
        core = labels == (int(np.argmax(sizes)) + 1)
        if best is None or core.sum() > best[1].sum():
            best = (i, core)
    if best is None:
        return None
    i, core = best
    lens = lenses[i]
    usable = maps.usable[i, b]
    rim = ndimage.binary_dilation(core) & ~core & usable
    ring = ndimage.binary_dilation(core, iterations=3) & ~ndimage.binary_dilation(core, iterations=2) & usable
    signal = np.asarray(maps.signal_dn[i, b], float)
    background = float(np.median(signal[ring])) if ring.any() else 0.0
    full = float(np.asarray(full_scale_dn)[i])
    span = max(full - background, 1.0)
    weight = np.where(core, 1.0, np.clip((signal - background) / span, 0.0, 1.0))
    noise_var = (float(maps.read_var_dn2[i, b]) + float(maps.shot_dn[i, b]) * np.clip(signal, 0, None)) / span ** 2
    edge = (core & ndimage.binary_dilation(~core)) | rim
    var_w = np.where(rim, noise_var, 0.0) + np.where(edge, _EDGE_VAR, 0.0)
    g = bundle.sel(lens=lens, medium=medium, band=band)
    z, a = sphere_coordinates(np.asarray(g["theta_deg"].values, float), np.asarray(g["phi_deg"].values, float),
                              lens == zenith_lens)
    used = core | rim
    d = unit_vector(z[used], a[used])
    w = weight[used]
    total = d.T @ w
    cz, ca = _angles(total)
    basis = tangent_basis(cz, ca)
    x = np.degrees(d @ basis.T)                     # tangent offsets from c (deg; c itself has none)
    W = float(w.sum())
    cov = (x.T * var_w[used]) @ x / W ** 2
    geo = float(np.nanmean(np.asarray(g["theta_deg_sigma"].values, float)[core])) if "theta_deg_sigma" in g else 0.0
    return SunCentroid(str(maps.file), lens, band, float(maps.exposure_s), int(core.sum()), int(rim.sum()), cz, ca,
                       cov, geo if np.isfinite(geo) else 0.0)


def _earth_residual(att: Attitude, camera_vector, solar_zenith_deg, solar_azimuth_deg) -> np.ndarray:
    """Measured less solar direction in the plane tangent at the solar direction (deg): (zenith, horizontal)."""
    e = camera_to_earth_directions(att, np.asarray(camera_vector, float)[None])[0]
    return np.degrees(tangent_basis(solar_zenith_deg, solar_azimuth_deg) @ e)


def _to_earth(att: Attitude, centroid: SunCentroid, solar_zenith_deg, solar_azimuth_deg) -> np.ndarray:
    """(2, 2): the camera tangent components at c to the earth tangent components at the solar direction."""
    cam = tangent_basis(centroid.camera_zenith_deg, centroid.camera_azimuth_deg)
    earth = camera_to_earth_directions(att, cam)
    return tangent_basis(solar_zenith_deg, solar_azimuth_deg) @ earth.T


def _attitude_jacobian(att: Attitude, vector, sz, sa) -> np.ndarray:
    """(2, 3): d residual / d (roll, pitch, heading), central differences."""
    cols = []
    for name in ("roll_deg", "pitch_deg", "heading_deg"):
        v = getattr(att, name)
        hi = _earth_residual(replace(att, **{name: v + _ATT_STEP_DEG}), vector, sz, sa)
        lo = _earth_residual(replace(att, **{name: v - _ATT_STEP_DEG}), vector, sz, sa)
        cols.append((hi - lo) / (2 * _ATT_STEP_DEG))
    return np.stack(cols, axis=1)


def sun_closure(centroid: SunCentroid, att: Attitude, solar_zenith_deg: float, solar_azimuth_deg: float,
                z_limit: float) -> dict:
    """The closure of one frame (module docstring): a dict of the residual and its uncertainty.

    Parameters
    ----------
    centroid : SunCentroid
        The sun's centroid in the frame, camera grid frame, degree.
    att : Attitude
        The frame's attitude, degree.
    solar_zenith_deg : float
        Apparent solar zenith angle, degree.
    solar_azimuth_deg : float
        Solar azimuth, degree from north towards east.
    z_limit : float
        A residual component beyond this many sigmas names its cause (``lightfield.sun_closure_z``).

    Returns
    -------
    dict
        The measured earth-frame zenith angle and azimuth; the residual's components along the zenith angle and
        horizontal and their sigmas; the heading offset and its sigma; the angle, its sigma along the residual,
        z, chi^2 on 2 degrees of freedom and its p value (all angles in degree); the attitude's and the
        measurement's sigma; the named causes (str); and in the camera's tangent plane the residual
        (``residual_camera_deg``, degree, shape ``(2,)``) and the frame-to-frame covariance
        (``frame_cov_camera_deg2``, degree^2, shape ``(2, 2)``).
    """
    r = _earth_residual(att, centroid.vector, solar_zenith_deg, solar_azimuth_deg)
    m = _to_earth(att, centroid, solar_zenith_deg, solar_azimuth_deg)
    c_meas = m @ centroid.cov_deg2 @ m.T
    j = _attitude_jacobian(att, centroid.vector, solar_zenith_deg, solar_azimuth_deg)
    c_att = j @ np.diag([att.roll_sigma_deg ** 2, att.pitch_sigma_deg ** 2, att.heading_sigma_deg ** 2]) @ j.T
    cov = c_meas + c_att
    angle = float(np.hypot(*r))
    u = r / angle if angle > 0 else np.array([1.0, 0.0])
    sigma = float(np.sqrt(u @ cov @ u))
    chi2 = float(r @ np.linalg.solve(cov, r))
    me = camera_to_earth_directions(att, centroid.vector[None])[0]
    mz, ma = _angles(me)
    sin_z = max(np.sin(np.radians(solar_zenith_deg)), 1e-6)
    z = r / np.sqrt(np.diag(cov))
    named = []
    if abs(z[1]) > z_limit:
        named.append("attitude heading")
    if abs(z[0]) > z_limit:
        named.append("tilt (roll, pitch) or geometry theta")
    return {
        "measured_zenith_deg": mz, "measured_azimuth_deg": ma,
        "residual_zenith_deg": float(r[0]), "residual_zenith_sigma_deg": float(np.sqrt(cov[0, 0])),
        "residual_horizontal_deg": float(r[1]), "residual_horizontal_sigma_deg": float(np.sqrt(cov[1, 1])),
        "heading_offset_deg": float(r[1] / sin_z), "heading_offset_sigma_deg": float(np.sqrt(cov[1, 1]) / sin_z),
        "angle_deg": angle, "sigma_deg": sigma, "z": angle / sigma if sigma > 0 else np.inf, "chi2": chi2,
        "p_value": float(chi2_dist.sf(chi2, 2)), "z_zenith": float(z[0]), "z_horizontal": float(z[1]),
        "attitude_sigma_deg": float(np.sqrt(u @ c_att @ u)), "measurement_sigma_deg": float(np.sqrt(u @ c_meas @ u)),
        "named": ", ".join(named),
        # in the camera's tangent plane at c: the residual and the covariance of the terms that differ from frame
        # to frame (centroid, attitude), apart from the geometry's, which is the same in frames of one camera
        "residual_camera_deg": np.linalg.solve(m, r),
        "frame_cov_camera_deg2": centroid.centroid_cov_deg2 + np.linalg.solve(m, np.linalg.solve(m, c_att).T),
    }


def _model_attitude(model: str, params, sun_camera_azimuth_deg: float) -> Attitude:
    if model == "heading":
        return Attitude(0.0, 0.0, float(params[0]) % 360.0)
    t, a = float(params[1]), np.radians(sun_camera_azimuth_deg)
    return Attitude(t * np.sin(a), -t * np.cos(a), float(params[0]) % 360.0)


def fit_attitude_from_sun(centroid: SunCentroid, solar_zenith_deg: float, solar_azimuth_deg: float,
                          model: str = "heading") -> dict:
    """Attitude fitted from the sun (module docstring): the fitted attitude (its sigmas set from the fit),
    the fitted parameters with their sigmas, and the fit's chi^2 and degrees of freedom.

    Parameters
    ----------
    centroid : SunCentroid
        The sun's centroid in the frame, camera grid frame, degree.
    solar_zenith_deg : float
        Apparent solar zenith angle, degree.
    solar_azimuth_deg : float
        Solar azimuth, degree from north towards east.
    model : str, default "heading"
        "heading" (level assumed) or "heading_tilt" (``FIT_MODELS``).

    Returns
    -------
    dict
        ``"model"``; ``"heading_deg"``, ``"heading_sigma_deg"``, ``"tilt_deg"``, ``"tilt_sigma_deg"`` (degree);
        ``"chi2"`` and ``"dof"``; ``"attitude"``: the fitted :class:`Attitude`.

    Raises
    ------
    ValueError
        On an unknown model.
    """
    if model not in FIT_MODELS:
        raise ValueError(f"attitude-from-sun model {model!r}: one of {', '.join(FIT_MODELS)}")
    h0 = (solar_azimuth_deg - centroid.camera_azimuth_deg) % 360.0
    x0 = [h0] if model == "heading" else [h0, 0.0]

    def whiten(params):
        att = _model_attitude(model, params, centroid.camera_azimuth_deg)
        m = _to_earth(att, centroid, solar_zenith_deg, solar_azimuth_deg)
        chol = np.linalg.cholesky(m @ centroid.cov_deg2 @ m.T)
        return np.linalg.solve(chol, _earth_residual(att, centroid.vector, solar_zenith_deg, solar_azimuth_deg))
    fit = least_squares(whiten, x0, x_scale=1.0, diff_step=1e-6)
    cov = np.linalg.inv(fit.jac.T @ fit.jac)
    sig = np.sqrt(np.diag(cov))
    att = _model_attitude(model, fit.x, centroid.camera_azimuth_deg)
    chi2 = float(np.sum(fit.fun ** 2))
    out = {"model": model, "heading_deg": float(fit.x[0]) % 360.0, "heading_sigma_deg": float(sig[0]),
           "chi2": chi2, "dof": 2 - len(x0)}
    if model == "heading":
        att = replace(att, heading_sigma_deg=float(sig[0]))
        out["tilt_deg"], out["tilt_sigma_deg"] = 0.0, 0.0
    else:
        a = np.radians(centroid.camera_azimuth_deg)
        st = float(sig[1])
        att = replace(att, heading_sigma_deg=float(sig[0]), roll_sigma_deg=abs(st * np.sin(a)),
                      pitch_sigma_deg=abs(st * np.cos(a)))
        out["tilt_deg"], out["tilt_sigma_deg"] = float(fit.x[1]), st
    out["attitude"] = att
    return out
