"""Scaramuzza (OCamCalib) omnidirectional camera model for fisheye lenses.

Conventions (used by every module of :mod:`pipeline.geometry`):

- Pixel coordinates ``(u, v)`` are continuous, in pixels of the image the
  model belongs to: ``u`` along columns (to the right), ``v`` along rows
  (downwards). The *centre* of pixel ``[row, col]`` is at ``(u, v) = (col,
  row)``; the image spans ``-0.5 .. width - 0.5``.
- Camera frame: x to the right (+u), y downwards (+v), z along the optical
  axis, out of the lens into the scene. A pixel sees the ray
  ``(x', y', f(rho))`` where ``[u - xc, v - yc] = A [x', y']``,
  ``A = [[c, d], [e, 1]]``, ``rho = hypot(x', y')`` and
  ``f(rho) = a0 + a1 rho + a2 rho^2 + ...`` (``a1 = 0``). Hence
  ``tan(theta) = rho / f(rho)``; theta exceeds 90 degrees where f < 0.
- ``theta`` is the angle from the optical axis, ``phi`` the azimuth
  ``atan2(y, x)`` in the camera frame (from +u towards +v), in
  ``(-180, 180]`` degrees.
- Scaling an image by ``s`` keeps its outer edges fixed:
  ``u_new + 0.5 = s (u_old + 0.5)``; coefficients ``a_k -> a_k s^(1-k)``.
- Band images are the 2 x 2 Bayer super-pixels of the raw mosaic: band pixel
  ``i`` covers raw pixels ``2i`` and ``2i + 1``, so its centre is raw
  coordinate ``2i + 0.5``, i.e. ``u_band = (u_raw - 0.5) / 2`` (the same rule
  as scaling by ``s = 1/2``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np

#: Number of samples of the theta(rho) lookup table used to invert f(rho).
_LUT_SAMPLES = 512


@lru_cache(maxsize=64)
def _derivative(poly: tuple[float, ...]) -> np.ndarray:
    """Ascending coefficients of f'(rho) (kept per polynomial: a fit evaluates one model many times)."""
    out = np.polynomial.polynomial.polyder(poly)
    out.setflags(write=False)
    return out


@lru_cache(maxsize=64)
def _monotone_lut(poly: tuple[float, ...], c: float, d: float, e: float, shape: tuple[int, int]):
    """:meth:`FisheyeModel._lut` of a model with these parameters."""
    model = FisheyeModel(poly, 0.0, 0.0, c, d, e, shape=shape)
    rho = np.linspace(0.0, model.rho_max(), _LUT_SAMPLES)
    theta = model.theta_of_rho(rho)
    dtheta = np.diff(theta)
    bad = np.nonzero(dtheta <= 0)[0]
    n = bad[0] + 1 if bad.size else rho.size
    theta, rho = theta[:n], rho[:n]
    theta.setflags(write=False)
    rho.setflags(write=False)
    return theta, rho


@dataclass(frozen=True)
class FisheyeModel:
    """Scaramuzza fisheye model of one lens (see module docstring for conventions).

    Attributes
    ----------
    poly : ascending coefficients (a0, a1, a2, ...) of f(rho), a1 = 0, pixels.
    xc, yc : principal point, pixels (u, v).
    c, d, e : stretch matrix ``[[c, d], [e, 1]]``.
    shape : image shape (rows, cols) the model belongs to (keyword only).
    half_fov_deg : theta at the edge of the image circle (field stop), or None.
    """

    poly: tuple[float, ...]
    xc: float
    yc: float
    c: float = 1.0
    d: float = 0.0
    e: float = 0.0
    shape: tuple[int, int] = field(kw_only=True)
    half_fov_deg: float | None = None
    meta: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "poly", tuple(float(a) for a in self.poly))
        object.__setattr__(self, "shape", tuple(int(n) for n in self.shape))

    # ------------------------------------------------------------------ basics
    @property
    def stretch(self) -> np.ndarray:
        return np.array([[self.c, self.d], [self.e, 1.0]])

    def f(self, rho):
        """f(rho) of the polynomial (pixels), Eq. (5) of Larouche et al. (2024).

        Parameters
        ----------
        rho : float or numpy.ndarray
            Radial distance on the sensor plane from the principal point, pixels.

        Returns
        -------
        numpy.ndarray
            ``f(rho) = a0 + a2 rho^2 + ...``, pixels, of the shape of ``rho``; negative where theta exceeds 90 degrees.
        """
        return np.polynomial.polynomial.polyval(rho, self.poly)

    def df(self, rho):
        """Derivative of f with respect to rho.

        Parameters
        ----------
        rho : float or numpy.ndarray
            Radial distance on the sensor plane from the principal point, pixels.

        Returns
        -------
        numpy.ndarray
            ``f'(rho)`` (dimensionless, pixels per pixel), of the shape of ``rho``.
        """
        return np.polynomial.polynomial.polyval(rho, _derivative(self.poly))

    def theta_of_rho(self, rho):
        """Angle from the optical axis (radians) at radial distance rho (pixels).

        tan(theta) = rho / f(rho), Eq. (7).

        Parameters
        ----------
        rho : float or numpy.ndarray
            Radial distance on the sensor plane from the principal point, pixels.

        Returns
        -------
        numpy.ndarray
            Field angle theta, radians (0 on the optical axis, beyond pi/2 where f < 0), of the shape of ``rho``.
        """
        rho = np.asarray(rho, dtype=float)
        return np.arctan2(rho, self.f(rho))

    def _sensor_xy(self, u, v):
        """Sensor-plane (x', y') of pixel coordinates (u, v): the affine map of Eq. (6) inverted (pixels)."""
        u = np.asarray(u, dtype=float)
        v = np.asarray(v, dtype=float)
        du, dv = u - self.xc, v - self.yc
        det = self.c - self.d * self.e
        x = (du - self.d * dv) / det
        y = (-self.e * du + self.c * dv) / det
        return x, y

    # ---------------------------------------------------------------- mappings
    def cam2world(self, u, v) -> np.ndarray:
        """Unit rays (..., 3) in the camera frame seen by pixel coordinates (u, v).

        Parameters
        ----------
        u, v : float or numpy.ndarray
            Pixel coordinates (column, row; pixel centres at integers), broadcastable to each other.

        Returns
        -------
        numpy.ndarray
            Unit ray directions, shape ``(..., 3)`` (x right, y down, z along the optical axis into the scene).
        """
        x, y = self._sensor_xy(u, v)
        z = self.f(np.hypot(x, y))
        ray = np.stack(np.broadcast_arrays(x, y, z), axis=-1)
        return ray / np.linalg.norm(ray, axis=-1, keepdims=True)

    def rho_max(self) -> float:
        """Upper end of the radial domain over which theta(rho) is inverted.

        Returns
        -------
        float
            The image diagonal, pixels, enlarged by ``1 / |det A|`` when the stretch matrix shrinks the sensor plane.
        """
        h, w = self.shape
        return float(np.hypot(h, w)) * max(1.0, 1.0 / abs(self.c - self.d * self.e))

    def _lut(self):
        """Monotone table (theta, rho) from rho = 0 to where theta stops rising (read-only arrays, kept per
        polynomial, stretch and shape: the fits' Jacobians evaluate one model at many poses)."""
        return _monotone_lut(self.poly, self.c, self.d, self.e, self.shape)

    def rho_of_theta(self, theta_rad) -> np.ndarray:
        """Invert theta(rho) (radians -> pixels); NaN beyond the model's domain.

        A lookup table on the monotone part of theta(rho) gives the start,
        five Newton steps on ``atan2(rho, f(rho)) - theta`` polish it to
        rounding error, which is robust for theta beyond 90 degrees where
        f(rho) changes sign.

        Parameters
        ----------
        theta_rad : float or numpy.ndarray
            Field angle from the optical axis, radians.

        Returns
        -------
        numpy.ndarray
            Radial distance rho on the sensor plane, pixels, of the shape of ``theta_rad``; NaN for negative,
            non-finite or out-of-domain angles.
        """
        theta = np.asarray(theta_rad, dtype=float)
        t_lut, r_lut = self._lut()
        rho = np.interp(theta, t_lut, r_lut)
        outside = (theta > t_lut[-1]) | (theta < 0) | ~np.isfinite(theta)
        for _ in range(5):
            f = self.f(rho)
            g = np.arctan2(rho, f) - theta
            dg = (f - rho * self.df(rho)) / (rho**2 + f**2)
            step = np.where(dg > 0, g / np.where(dg > 0, dg, 1.0), 0.0)
            rho = np.clip(rho - step, 0.0, r_lut[-1])
        return np.where(outside, np.nan, rho)

    def world2cam(self, rays) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (u, v) of camera-frame rays (..., 3) (any length).

        Rays outside the model's monotone domain give NaN.

        Parameters
        ----------
        rays : numpy.ndarray
            Ray directions in the camera frame, shape ``(..., 3)``, of any length.

        Returns
        -------
        u : numpy.ndarray
            Column coordinate of each ray's pixel, pixels, shape ``(...)``; NaN outside the domain.
        v : numpy.ndarray
            Row coordinate of each ray's pixel, pixels, shape ``(...)``; NaN outside the domain.
        """
        rays = np.asarray(rays, dtype=float)
        x, y = rays[..., 0], rays[..., 1]
        r_xy = np.hypot(x, y)
        rho = self.rho_of_theta(field_angle_rad(rays))
        safe = np.where(r_xy > 0, r_xy, 1.0)
        xs = np.where(r_xy > 0, x / safe, 0.0) * rho
        ys = np.where(r_xy > 0, y / safe, 0.0) * rho
        # the affine map of Eq. (6): [u - xc, v - yc] = A [x', y']
        u = self.c * xs + self.d * ys + self.xc
        v = self.e * xs + ys + self.yc
        return u, v

    def theta_phi(self, u, v, degrees: bool = True):
        """Angle from the optical axis and azimuth of pixel coordinates (u, v).

        Parameters
        ----------
        u, v : float or numpy.ndarray
            Pixel coordinates (column, row; pixel centres at integers).
        degrees : bool, default True
            Return degrees (True) or radians (False).

        Returns
        -------
        theta : numpy.ndarray
            Angle from the optical axis, degree (or radian).
        phi : numpy.ndarray
            Azimuth ``atan2(y, x)`` in the camera frame, from +u towards +v, in ``(-180, 180]`` degree (or radian).
        """
        x, y = self._sensor_xy(u, v)
        theta = self.theta_of_rho(np.hypot(x, y))
        phi = np.arctan2(y, x)
        if degrees:
            return np.degrees(theta), np.degrees(phi)
        return theta, phi

    def solid_angle_density(self, u, v) -> np.ndarray:
        """Solid angle per unit pixel area (sr / px^2) at (u, v).

        For the ray r = (x', y', f(rho)), d(Omega) = |f - rho f'| /
        (rho^2 + f^2)^(3/2) dx' dy', and dx' dy' = du dv / |det A|.

        Parameters
        ----------
        u, v : float or numpy.ndarray
            Pixel coordinates (column, row; pixel centres at integers).

        Returns
        -------
        numpy.ndarray
            Solid angle per unit pixel area, sr px-2, of the broadcast shape of ``u`` and ``v``.
        """
        x, y = self._sensor_xy(u, v)
        rho = np.hypot(x, y)
        f = self.f(rho)
        dens = np.abs(f - rho * self.df(rho)) / (rho**2 + f**2) ** 1.5
        return dens / abs(self.c - self.d * self.e)

    def image_circle_radius(self, half_fov_deg: float | None = None) -> float:
        """Radial distance rho (pixels, sensor plane) where theta = half FOV.

        Parameters
        ----------
        half_fov_deg : float, optional
            Half field of view, degree; the model's own ``half_fov_deg`` when None.

        Returns
        -------
        float
            Radius rho of the image circle on the sensor plane, pixels (NaN beyond the model's domain).

        Raises
        ------
        ValueError
            When neither the argument nor the model gives a half field of view.
        """
        hf = self.half_fov_deg if half_fov_deg is None else half_fov_deg
        if hf is None:
            raise ValueError("model has no half_fov_deg; pass one")
        return float(self.rho_of_theta(np.radians(hf)))

    # ----------------------------------------------------------------- scaling
    def scaled(self, s: float, shape: tuple[int, int] | None = None) -> "FisheyeModel":
        """The same lens imaged on a grid scaled by s (edges fixed, see module doc).

        Parameters
        ----------
        s : float
            Scale factor of the new pixel grid (e.g. 0.5 for the Bayer band images of a raw mosaic).
        shape : tuple of int, optional
            (rows, cols) of the scaled image; the model's shape times ``s``, rounded, when None.

        Returns
        -------
        FisheyeModel
            The model with coefficients ``a_k s^(1-k)`` and principal point ``s (xc + 0.5) - 0.5``.
        """
        poly = tuple(a * s ** (1 - k) for k, a in enumerate(self.poly))
        if shape is None:
            shape = tuple(int(round(n * s)) for n in self.shape)
        return replace(
            self,
            poly=poly,
            xc=s * (self.xc + 0.5) - 0.5,
            yc=s * (self.yc + 0.5) - 0.5,
            shape=shape,
        )

    # ------------------------------------------------------------ persistence
    def to_dict(self) -> dict:
        """The model's parameters as plain numbers and lists, as written to YAML (``meta`` is not kept).

        Returns
        -------
        dict
            Keys ``poly`` (pixels), ``xc``, ``yc`` (pixels), ``c``, ``d``, ``e`` (stretch), ``shape`` (rows, cols) and
            ``half_fov_deg`` (degree or None).
        """
        return {
            "poly": list(self.poly),
            "xc": self.xc,
            "yc": self.yc,
            "c": self.c,
            "d": self.d,
            "e": self.e,
            "shape": list(self.shape),
            "half_fov_deg": self.half_fov_deg,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "FisheyeModel":
        """The model written by :meth:`to_dict`.

        Parameters
        ----------
        d : dict
            Keys as :meth:`to_dict` writes them; ``c``, ``d``, ``e`` default to no stretch (1, 0, 0) and
            ``half_fov_deg`` to None when absent.

        Returns
        -------
        FisheyeModel
            The model.
        """
        return cls(
            poly=tuple(d["poly"]),
            xc=float(d["xc"]),
            yc=float(d["yc"]),
            c=float(d.get("c", 1.0)),
            d=float(d.get("d", 0.0)),
            e=float(d.get("e", 0.0)),
            shape=tuple(d["shape"]),
            half_fov_deg=None if d.get("half_fov_deg") is None else float(d["half_fov_deg"]),
        )


def field_angle_rad(rays) -> np.ndarray:
    """Angle from the optical axis (radians) of camera-frame rays (..., 3) of any length.

    tan(theta) = hypot(x, y) / z: Eq. (7) for the ray (x', y', f(rho)) a
    pixel sees; beyond 90 degrees where z < 0.

    Parameters
    ----------
    rays : numpy.ndarray
        Ray directions in the camera frame, shape ``(..., 3)``.

    Returns
    -------
    numpy.ndarray
        Field angle theta, radians, shape ``(...)``.
    """
    rays = np.asarray(rays, dtype=float)
    return np.arctan2(np.hypot(rays[..., 0], rays[..., 1]), rays[..., 2])


def fit_poly_to_theta(rho, theta_rad, degree: int = 4) -> tuple[float, ...]:
    """Least-squares f(rho) (a1 = 0) with atan2(rho, f(rho)) = theta at given samples.

    The condition rho cos(theta) = f(rho) sin(theta) is linear in the
    coefficients; rows are weighted so that residuals are ~ radians.

    Parameters
    ----------
    rho : numpy.ndarray
        Radial distances on the sensor plane, pixels, shape ``(n,)``.
    theta_rad : numpy.ndarray
        Field angles at those distances, radians, shape ``(n,)``.
    degree : int, default 4
        Polynomial degree N of f(rho).

    Returns
    -------
    tuple of float
        Ascending coefficients ``(a0, 0, a2, ..., aN)`` of f(rho), pixels.
    """
    rho = np.asarray(rho, float)
    theta = np.asarray(theta_rad, float)
    powers = [0] + list(range(2, degree + 1))
    M = np.stack([rho**k * np.sin(theta) for k in powers], axis=1)
    b = rho * np.cos(theta)
    w = 1.0 / np.sqrt(rho**2 + 1.0)
    sol, *_ = np.linalg.lstsq(M * w[:, None], b * w, rcond=None)
    poly = [sol[0], 0.0] + list(sol[1:])
    return tuple(float(a) for a in poly)
