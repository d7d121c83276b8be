"""The light field under a flat water surface: what a submerged camera's two lenses see at depth z.

The scene (a stated form, defined here from textbook optics; directions in the
earth frame, Z_w the zenith angle in water of the direction looked at, the
azimuth alpha from north towards east):

* above the surface, a sky with the sun (:class:`~pipeline.simulate.brackets.BracketScene`'s
  CIE sky of type ``cie_type`` relative to the band zenith radiance L_z,b) and
  a soft sun: L_sun = ``sun_factor`` L_z,b exp(-chi^2 / (2 s^2)) with chi the
  angle from the sun's centre and s = ``sun_radius_deg`` (a sun seen through
  thin haze; a smooth peak that a camera's pixels sample fairly);
* inside Snell's window (Z_w <= asin(1 / n_w)), the refracted sky and sun: a
  direction in water at Z_w sees the air direction at Z_a = asin(n_w sin Z_w)
  and the same azimuth, with radiance
  L_r = t_F(Z_a) n_w^2 L_a(Z_a, alpha) exp(-K_b z / cos Z_w)
  (Fresnel transmission of unpolarised light from air into water,
  :func:`fresnel_transmission`, written here; the n-squared law; the beam's
  attenuation along its slant path of z / cos Z_w with ``beam_attenuation_per_m``
  K_b per band). The surface is flat: no wind roughening, no internal
  reflection of the upwelling light outside the window;
* everywhere (both hemispheres), a diffuse in-water radiance of the form
  L_s = ``diffuse_factor`` L_z,b exp(-K_d z) exp(k (cos Z_w - 1)), with K_d =
  ``diffuse_attenuation_per_m`` per band and k = ln(1 / r) / 2 for the stated
  ``nadir_ratio`` r = L_s(nadir) / L_s(zenith): smooth over the sphere, its
  upwelling part (Z_w > 90 degrees) the only light of the lower hemisphere,
  five decades and more below the refracted sun.

The camera is in water (the lenses' water geometry; its response the in-air
one over the immersion factor, :func:`in_water_light_factor`) and may be tilted
(``attitude_deg``, as :class:`~pipeline.simulate.brackets.BracketScene`).

The truth (:func:`light_field_truth`) integrates the scene's true band
radiance over the earth-frame sphere by a fine midpoint quadrature (exact cell
solid angles and cosine integrals), independently of the pipeline's own
quadrature: it never calls the light-field package.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path

import numpy as np
import yaml

from pipeline.io.bands import BANDS
from pipeline.simulate.brackets import BracketScene, render_bracket
from pipeline.simulate.immersion import true_immersion_factors
from pipeline.simulate.sky import CIE_SKY_TYPES, angle_from_sun_deg, cie_relative_radiance

__all__ = ["UnderwaterScene", "render_underwater_bracket", "fresnel_transmission", "in_water_light_factor", "light_field_truth",
           "TRUTH_QUANTITIES", "UNDERWATER_EXPOSURES_S", "WATER_INDEX"]

#: the water's refractive index per band (R, G, B), a stated constant of the scene
WATER_INDEX = (1.332, 1.334, 1.337)

#: five exposures a factor eight apart, 1/4000 s to 1 s: with the default scene the refracted sun is below
#: saturation at the shortest and the nadir radiance above the noise at the longest
UNDERWATER_EXPOSURES_S = (1 / 4000, 1 / 500, 1 / 64, 1 / 8, 1.0)

#: the quantities of :func:`light_field_truth`
TRUTH_QUANTITIES = ("E_d", "E_u", "E_0d", "E_0u", "E_0", "mu_d", "mu_u", "mu", "L_d", "L_u", "Q")


def fresnel_transmission(incidence_deg, n: float) -> np.ndarray:
    """Fresnel transmittance of unpolarised light from air (index 1) into a medium of index ``n``.

    t = 1 - (r_s + r_p) / 2 with r_s = ((cos i - n cos t) / (cos i + n cos t))^2 and
    r_p = ((n cos i - cos t) / (n cos i + cos t))^2, sin t = sin i / n.

    Parameters
    ----------
    incidence_deg : array_like
        Angle of incidence in air, degree (0 to 90).
    n : float or array_like
        Refractive index of the medium (broadcast with ``incidence_deg``).

    Returns
    -------
    numpy.ndarray
        The transmittance (0 at grazing incidence, 1 - ((n - 1) / (n + 1))^2 at normal incidence).
    """
    ci = np.cos(np.radians(np.clip(np.asarray(incidence_deg, float), 0.0, 90.0)))
    si = np.sqrt(np.clip(1.0 - ci ** 2, 0.0, 1.0))
    ct = np.sqrt(1.0 - (si / n) ** 2)
    rs = ((ci - n * ct) / (ci + n * ct)) ** 2
    rp = ((n * ci - ct) / (n * ci + ct)) ** 2
    return 1.0 - 0.5 * (rs + rp)


class InWaterLightFactor:
    """The camera's in-water response over its in-air one per band: 1 / the true immersion factor."""

    def __init__(self):
        factors = true_immersion_factors()["immersion_factor"]
        self.values = np.array([1.0 / factors[b] for b in BANDS])

    def __call__(self, band_index):
        """Per raw site: the factor of its band (``band_index`` 0 R, 1 G, 2 B)."""
        return self.values[np.asarray(band_index)]


def in_water_light_factor() -> InWaterLightFactor:
    """The renderer's light factor of a camera in water (the simulator's true immersion factors).

    Returns
    -------
    InWaterLightFactor
        Callable of the band index: 1 / immersion factor of the band.
    """
    return InWaterLightFactor()


@dataclass(frozen=True)
class UnderwaterScene(BracketScene):
    """The light field at ``depth_m`` below a flat surface (module docstring); radiances in W m-2 sr-1 nm-1."""

    zenith_radiance: tuple = (0.0007, 0.0008, 0.0009)      # of the sky above the water, R, G, B
    sun_zenith_deg: float = 40.0
    sun_azimuth_deg: float = 120.0
    sun_radius_deg: float = 3.0                             # the soft sun's standard deviation in air
    sun_factor: float = 300.0
    depth_m: float = 3.0
    beam_attenuation_per_m: tuple = (0.40, 0.08, 0.05)
    diffuse_attenuation_per_m: tuple = (0.42, 0.09, 0.06)
    diffuse_factor: float = 0.5
    nadir_ratio: float = 0.002

    def air_radiance(self, zenith_deg, azimuth_deg, band_index) -> np.ndarray:
        """The sky and the soft sun above the water (Z <= 90 degrees), per band.

        Parameters
        ----------
        zenith_deg, azimuth_deg : array_like
            Air direction, degree (azimuth from north towards east).
        band_index : array_like
            Band index (0 R, 1 G, 2 B), same shape.

        Returns
        -------
        numpy.ndarray
            Band radiance in air, W m-2 sr-1 nm-1.
        """
        z = np.minimum(np.asarray(zenith_deg, float), 90.0)
        lz = np.asarray(self.zenith_radiance, float)[np.asarray(band_index)]
        chi = angle_from_sun_deg(z, azimuth_deg, self.sun_zenith_deg, self.sun_azimuth_deg)
        sky = lz * cie_relative_radiance(z, azimuth_deg, self.sun_zenith_deg, self.sun_azimuth_deg,
                                         CIE_SKY_TYPES[self.cie_type], chi_deg=chi)
        return sky + self.sun_factor * lz * np.exp(-0.5 * (chi / self.sun_radius_deg) ** 2)

    def radiance(self, zenith_deg, azimuth_deg, band_index) -> np.ndarray:
        """In-water band radiance of earth-frame directions: refracted sky and sun plus the diffuse light.

        Parameters
        ----------
        zenith_deg : array_like
            Earth-frame zenith angle Z_w in water, degree (above 90: upwelling light).
        azimuth_deg : array_like
            Azimuth, degree from north towards east.
        band_index : array_like
            Band index of each direction (0 R, 1 G, 2 B), same shape.

        Returns
        -------
        numpy.ndarray
            The band radiance, W m-2 sr-1 nm-1 (module docstring).
        """
        zw = np.asarray(zenith_deg, float)
        bi = np.asarray(band_index)
        n = np.asarray(WATER_INDEX, float)[bi]
        lz = np.asarray(self.zenith_radiance, float)[bi]
        kb = np.asarray(self.beam_attenuation_per_m, float)[bi]
        kd = np.asarray(self.diffuse_attenuation_per_m, float)[bi]
        k = 0.5 * np.log(1.0 / self.nadir_ratio)
        cz = np.cos(np.radians(zw))
        diffuse = self.diffuse_factor * lz * np.exp(-kd * self.depth_m) * np.exp(k * (cz - 1.0))
        s = n * np.sin(np.radians(np.clip(zw, 0.0, 90.0)))
        inside = (zw < 90.0) & (s < 1.0)
        za = np.degrees(np.arcsin(np.clip(s, 0.0, 1.0)))
        refracted = fresnel_transmission(za, n) * n ** 2 \
            * self.air_radiance(za, azimuth_deg, bi) * np.exp(-kb * self.depth_m / np.maximum(cz, 1e-6))
        return diffuse + np.where(inside, refracted, 0.0)



def _zenith_edges(cone_deg: float) -> np.ndarray:
    """Quadrature rows: 0.05 degree over Snell's window and the cones, 0.25 degree elsewhere."""
    fine = np.arange(0.0, 50.0, 0.05)
    return np.unique(np.round(np.concatenate([fine, np.arange(50.0, 180.0 - cone_deg, 0.25),
                                              np.arange(180.0 - cone_deg, 180.0, 0.05), [180.0, cone_deg]]), 9))


def light_field_truth(scene: UnderwaterScene, cone_half_angle_deg: float = 5.0, azimuth_step_deg: float = 0.2) -> dict:
    """The light-field quantities of the scene's true band radiance, by a fine midpoint quadrature.

    Over earth-frame cells (zenith rows of 0.05 degree over Snell's window and the zenith and nadir cones, 0.25
    degree elsewhere; azimuth columns of ``azimuth_step_deg``), the radiance at each cell's centre times the cell's
    exact solid angle (cos Z_1 - cos Z_2) dalpha or its exact cosine integral (sin^2 Z_2 - sin^2 Z_1) dalpha / 2.
    The camera's attitude plays no part: the light field is the earth frame's.

    Parameters
    ----------
    scene : UnderwaterScene
        The scene.
    cone_half_angle_deg : float, optional
        Half-angle of the cones about the zenith and the nadir over which L_d and L_u are the mean radiance
        (solid-angle weighted), degree; default 5.
    azimuth_step_deg : float, optional
        Azimuth step, degree; default 0.2.

    Returns
    -------
    dict
        Per name of :data:`TRUTH_QUANTITIES`: numpy.ndarray of the bands R, G, B. Irradiances W m-2 nm-1,
        radiances W m-2 sr-1 nm-1, Q sr, average cosines 1.
    """
    edges = _zenith_edges(cone_half_angle_deg)
    z1, z2 = np.radians(edges[:-1]), np.radians(edges[1:])
    zc = np.degrees(0.5 * (z1 + z2))
    n_a = int(round(360.0 / azimuth_step_deg))
    da = 2.0 * np.pi / n_a
    ac = (np.arange(n_a) + 0.5) * 360.0 / n_a
    solid = (np.cos(z1) - np.cos(z2)) * da                       # per row
    cosine = 0.5 * (np.sin(z2) ** 2 - np.sin(z1) ** 2) * da      # signed: negative below the horizon
    upper = zc < 90.0
    out = {q: np.zeros(len(BANDS)) for q in TRUTH_QUANTITIES}
    Z, A = np.meshgrid(zc, ac, indexing="ij")
    for b in range(len(BANDS)):
        row = scene.radiance(Z, A, np.full(Z.shape, b)).sum(axis=1)       # per row: sum over azimuth
        e_d, e_u = np.sum((row * cosine)[upper]), -np.sum((row * cosine)[~upper])
        e_0d, e_0u = np.sum((row * solid)[upper]), np.sum((row * solid)[~upper])
        cone_d, cone_u = edges[1:] <= cone_half_angle_deg + 1e-9, edges[:-1] >= 180.0 - cone_half_angle_deg - 1e-9
        l_d = np.sum((row * solid)[cone_d]) / (n_a * np.sum(solid[cone_d]))
        l_u = np.sum((row * solid)[cone_u]) / (n_a * np.sum(solid[cone_u]))
        with np.errstate(invalid="ignore", divide="ignore"):     # no upwelling light: NaN ratios
            values = {"E_d": e_d, "E_u": e_u, "E_0d": e_0d, "E_0u": e_0u, "E_0": e_0d + e_0u, "mu_d": e_d / e_0d,
                      "mu_u": np.float64(e_u) / e_0u, "mu": (e_d - e_u) / (e_0d + e_0u), "L_d": l_d, "L_u": l_u,
                      "Q": np.float64(e_u) / l_u}
        for q, v in values.items():
            out[q][b] = v
    return out


@lru_cache(maxsize=8)
def _cached_truth(scene: UnderwaterScene, cone_half_angle_deg: float) -> dict:
    return light_field_truth(scene, cone_half_angle_deg)


def render_underwater_bracket(folder, scene: UnderwaterScene = UnderwaterScene(),
                              exposures_s=UNDERWATER_EXPOSURES_S, *, cone_half_angle_deg: float = 5.0,
                              **kwargs) -> dict:
    """One bracket of the camera in water (:func:`~pipeline.simulate.brackets.render_bracket` with the lenses'
    water geometry and the in-water response) and the light field's truth beside the bracket's.

    Parameters
    ----------
    folder : str or pathlib.Path
        The folder to write into.
    scene : UnderwaterScene, optional
        The scene; default ``UnderwaterScene()``.
    exposures_s : sequence of float, optional
        Exposure times, s; default :data:`UNDERWATER_EXPOSURES_S`.
    cone_half_angle_deg : float, optional
        Cone half-angle of the truth's L_d and L_u, degree; default 5.
    **kwargs
        Passed to :func:`~pipeline.simulate.brackets.render_bracket` (seed, bracket, start,
        attitude_log_sigma_deg, ...); not ``site``, ``medium`` or ``light_factor``.

    Returns
    -------
    dict
        :func:`~pipeline.simulate.brackets.render_bracket`'s, plus ``light_field_truth`` (the dict of
        :func:`light_field_truth`) and ``light_field_truth_file`` (``truth/<bracket>_lightfield.yaml``).
    """
    out = render_bracket(folder, scene, exposures_s, medium="water", light_factor=in_water_light_factor(), **kwargs)
    truth = _cached_truth(replace(scene, attitude_deg=(0.0, 0.0, 0.0)), float(cone_half_angle_deg))
    path = Path(folder) / "truth" / f"{kwargs.get('bracket', 'B001')}_lightfield.yaml"
    path.write_text(yaml.safe_dump({
        "method": "midpoint quadrature of the true band radiance over the earth-frame sphere "
                  "(pipeline.simulate.underwater.light_field_truth)",
        "cone_half_angle_deg": float(cone_half_angle_deg), "bands": list(BANDS),
        "quantities": {q: [float(x) for x in v] for q, v in truth.items()}}, sort_keys=False))
    out["light_field_truth"] = truth
    out["light_field_truth_file"] = path
    return out
