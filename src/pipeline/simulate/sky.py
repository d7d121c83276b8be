"""Sky radiance of the field hour: clear sky, drifting clouds, the sun disc (Larouche et al. 2024, Section 2.9).

The spectral radiance of the sky in direction (zenith Z, azimuth alpha) at
time t is a sum of components, each a spectrum times an angular pattern,

    L(lambda, Z, alpha, t) = sum_k S_k(lambda, t) A_k(Z, alpha, t),

so that the effective band radiance of any pixel (Eq. 3 of Larouche et al.
2024) is sum_k Sbar_k,b(t) A_k(pixel, t), with Sbar_k,b the band average of
S_k computed once per time on a fine wavelength grid: a few array operations
per frame, no spectral integral per pixel. The components:

* ``clear``: the clear sky. Angular pattern from the CIE standard general sky
  (ISO 15469:2004 / CIE S 011/E:2003), relative to the zenith,

      L(Z, alpha) / L_z = f(chi) phi(Z) / (f(Z_s) phi(0)),
      phi(Z) = 1 + a exp(b / cos Z)                     (gradation; phi = 1 at the horizon),
      f(chi) = 1 + c [exp(d chi) - exp(d pi / 2)] + e cos^2 chi   (scattering indicatrix),
      cos chi = cos Z_s cos Z + sin Z_s sin Z cos(alpha - alpha_s),

  chi the angular distance from the sun (radians in f), with the standard's
  a..e for the chosen type (default type 12, "CIE standard clear sky, low
  luminance turbidity"). Spectrum: the zenith radiance L_z(lambda, t) =
  E_d(lambda, t) / int (L / L_z) cos Z dOmega, with E_d pvlib's SPECTRL2
  (Bird and Riordan 1986) diffuse horizontal irradiance for the sun position,
  so that the modelled sky's horizontal diffuse irradiance equals SPECTRL2's
  at every wavelength. Under a cloud the clear sky is attenuated by the
  cloud's direct transmission along the line of sight, exp(-tau / cos Z).
* ``cloud``: light scattered by the clouds. A smooth random field of vertical
  optical depth tau(x, y) >= 0 on a horizontal layer at ``cloud_height_m``,
  advected by a constant wind; a direction sees the layer at horizontal
  offset h tan Z (capped near the horizon). The cloud base radiates
  isotropically the diffusely transmitted part of the global irradiance,
  L = T_d(tau) E_g(lambda) / pi with the two-stream transmission of a
  conservative layer, T_d = 1 / (1 + 3/4 (1 - g) tau) - exp(-tau / cos Z_s)
  (asymmetry g = 0.85): thin edges and moderate clouds are brighter than the
  clear sky, thick cores darker, and the light is whiter (the global
  spectrum, dominated by the direct beam, is flatter than the blue diffuse
  sky's).
* ``sun``: the solar disc (0.53 degree across) of SPECTRL2's direct normal
  irradiance, dimmed by the cloud in front of it, exp(-tau / cos Z_s). On a
  camera whose pixels are wider than the disc it is drawn as a larger disc
  of the same flux (``sun_render_radius_deg``): the pixels it covers get the
  mean radiance the disc gives them, far above saturation at any exposure.
* ``ground``: the dim uniform ground below the horizon (the far lens, and the
  zenith lens past 90 degrees): a fixed fraction of the clear zenith radiance.

The ``spectral_mismatch`` effect's hook multiplies the sky components (clear,
cloud, ground; not the sun) by (lambda / 550 nm)^(-a(t)).

Limits (what the model does not do): the CIE pattern is one wavelength-
independent shape, so the sky's colour does not change with direction (no
reddening towards the horizon or whitening around the sun beyond the cloud
mixing); SPECTRL2 is a single-layer clear-sky model (no multiple-scattering
angular detail, no polarisation); the clouds are a flat layer with no
thickness, sides or shadows on the clear sky, their base radiance does not
depend on the viewing direction (no forward-scattering silver lining), and
they do not change the clear-sky diffuse irradiance elsewhere; the ground is
uniform and grey relative to the sky.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
import pandas as pd

#: 46.7800 N, 71.2754 W, Universite Laval campus (Larouche et al. 2024, Section 2.9)
LATITUDE_DEG = 46.78
LONGITUDE_DEG = -71.2754
#: the camera clock's (and the site's) offset from UTC (h): 18 March 2021 is EDT, UTC-4
UTC_OFFSET_H = -4.0
#: angular diameter of the sun (deg)
SUN_DIAMETER_DEG = 0.53
#: zenith angle (deg) beyond which the cloud layer's offset h tan Z stops growing
CLOUD_MAX_ZENITH_DEG = 88.0
#: asymmetry parameter of cloud droplets' scattering in the two-stream transmission
CLOUD_ASYMMETRY = 0.85


@dataclass(frozen=True)
class CieSkyType:
    """Parameters of one CIE standard general sky (ISO 15469:2004, Table 1)."""

    number: int
    a: float
    b: float
    c: float
    d: float
    e: float
    description: str


#: The clear types of ISO 15469:2004 / CIE S 011/E:2003 (gradation group IV or V, indicatrix group 4 or 5).
CIE_SKY_TYPES = {
    11: CieSkyType(11, -1.0, -0.55, 10.0, -3.0, 0.45, "white-blue sky with distinct solar corona"),
    12: CieSkyType(12, -1.0, -0.32, 10.0, -3.0, 0.45, "CIE standard clear sky, low luminance turbidity"),
    13: CieSkyType(13, -1.0, -0.32, 16.0, -3.0, 0.30, "CIE standard clear sky, polluted atmosphere"),
}


def gradation(zenith_deg, sky: CieSkyType):
    """phi(Z) = 1 + a exp(b / cos Z); 1 at and below the horizon.

    Parameters
    ----------
    zenith_deg : array_like
        Zenith angle Z of the sky directions, degree.
    sky : CieSkyType
        The CIE sky type (its ``a`` and ``b``).

    Returns
    -------
    numpy.ndarray
        The gradation, dimensionless, shaped like ``zenith_deg``.
    """
    cos_z = np.cos(np.radians(np.asarray(zenith_deg, float)))
    with np.errstate(divide="ignore", over="ignore"):
        return np.where(cos_z > 0, 1.0 + sky.a * np.exp(sky.b / np.where(cos_z > 0, cos_z, 1.0)), 1.0)


def indicatrix(chi_deg, sky: CieSkyType):
    """f(chi) = 1 + c [exp(d chi) - exp(d pi/2)] + e cos^2 chi, chi the angle from the sun.

    Parameters
    ----------
    chi_deg : array_like
        Angular distance from the sun, degree (radians inside the formula).
    sky : CieSkyType
        The CIE sky type (its ``c``, ``d`` and ``e``).

    Returns
    -------
    numpy.ndarray
        The scattering indicatrix, dimensionless, shaped like ``chi_deg``.
    """
    chi = np.radians(np.asarray(chi_deg, float))
    return 1.0 + sky.c * (np.exp(sky.d * chi) - np.exp(sky.d * np.pi / 2)) + sky.e * np.cos(chi) ** 2


def angle_from_sun_deg(zenith_deg, azimuth_deg, sun_zenith_deg, sun_azimuth_deg):
    """Great-circle angle (deg) between a sky direction and the sun.

    Parameters
    ----------
    zenith_deg : array_like
        Zenith angle of the directions, degree.
    azimuth_deg : array_like
        Azimuth of the directions, degree east of north.
    sun_zenith_deg : float or array_like
        The sun's zenith angle, degree.
    sun_azimuth_deg : float or array_like
        The sun's azimuth, degree east of north.

    Returns
    -------
    numpy.ndarray
        chi in [0, 180], degree, the arguments' broadcast shape.
    """
    z, zs = np.radians(zenith_deg), np.radians(sun_zenith_deg)
    cos_chi = (np.cos(zs) * np.cos(z)
               + np.sin(zs) * np.sin(z) * np.cos(np.radians(np.asarray(azimuth_deg) - sun_azimuth_deg)))
    return np.degrees(np.arccos(np.clip(cos_chi, -1.0, 1.0)))


def cie_relative_radiance(zenith_deg, azimuth_deg, sun_zenith_deg, sun_azimuth_deg, sky: CieSkyType,
                          chi_deg=None):
    """L(Z, alpha) / L_z of the CIE standard general sky (1 at the zenith by construction).

    Parameters
    ----------
    zenith_deg : array_like
        Zenith angle Z of the sky directions, degree.
    azimuth_deg : array_like
        Azimuth alpha of the directions, degree east of north.
    sun_zenith_deg : float or array_like
        The sun's zenith angle, degree.
    sun_azimuth_deg : float or array_like
        The sun's azimuth, degree east of north.
    sky : CieSkyType
        The CIE sky type.
    chi_deg : array_like, optional
        The angle from the sun, degree, when the caller has it already; default None (computed).

    Returns
    -------
    numpy.ndarray
        The radiance relative to the zenith's, dimensionless.
    """
    chi = angle_from_sun_deg(zenith_deg, azimuth_deg, sun_zenith_deg, sun_azimuth_deg) if chi_deg is None else chi_deg
    return (indicatrix(chi, sky) * gradation(zenith_deg, sky)
            / (indicatrix(sun_zenith_deg, sky) * gradation(0.0, sky)))


@lru_cache(maxsize=256)
def horizontal_integral_sr(sun_zenith_deg: float, sky: CieSkyType, step_deg: float = 0.5) -> float:
    """int over the sky hemisphere of (L / L_z) cos Z dOmega (sr), midpoint rule on a Z x alpha grid.

    The integrand is smooth (the steepest term, exp(-3 chi), varies on a
    scale of 19 degrees) and the midpoint rule's error falls as step^2:
    against a 0.1 degree grid, 1 degree cells are off by 6e-5 relative and
    0.5 degree cells by 1.5e-5 (sun at 65 degrees, type 12). The sun azimuth
    is taken as 0 (the integral does not depend on it).

    Parameters
    ----------
    sun_zenith_deg : float
        The sun's zenith angle, degree.
    sky : CieSkyType
        The CIE sky type.
    step_deg : float, optional
        The grid's cell size in Z and alpha, degree; default 0.5.

    Returns
    -------
    float
        The integral, sr: the horizontal diffuse irradiance per unit zenith radiance.
    """
    z = np.arange(step_deg / 2, 90.0, step_deg)
    a = np.arange(step_deg / 2, 360.0, step_deg)
    zz, aa = np.meshgrid(z, a, indexing="ij")
    rel = cie_relative_radiance(zz, aa, sun_zenith_deg, 0.0, sky)
    d = np.radians(step_deg)
    return float(np.sum(rel * np.cos(np.radians(zz)) * np.sin(np.radians(zz))) * d * d)


def solar_position(times_utc: pd.DatetimeIndex) -> pd.DataFrame:
    """Apparent (refracted) sun zenith and azimuth (deg, azimuth east of north) by the NREL SPA in pvlib.

    At the site of :data:`LATITUDE_DEG`, :data:`LONGITUDE_DEG`.

    Parameters
    ----------
    times_utc : pandas.DatetimeIndex
        The instants, tz-aware UTC.

    Returns
    -------
    pandas.DataFrame
        Indexed by ``times_utc``: ``zenith_deg``, ``azimuth_deg`` and ``elevation_deg``, degree.
    """
    from pvlib.solarposition import get_solarposition

    sp = get_solarposition(times_utc, LATITUDE_DEG, LONGITUDE_DEG, method="nrel_numpy")
    return pd.DataFrame({"zenith_deg": sp["apparent_zenith"].to_numpy(float),
                         "azimuth_deg": sp["azimuth"].to_numpy(float),
                         "elevation_deg": sp["apparent_elevation"].to_numpy(float)}, index=times_utc)


@dataclass(frozen=True)
class Atmosphere:
    """SPECTRL2 inputs: a clean, dry late-winter atmosphere at sea level."""

    surface_pressure_pa: float = 101325.0
    #: precipitable water (cm): late-winter continental air is dry
    precipitable_water_cm: float = 0.8
    #: total ozone (atm-cm): spring values at mid-high latitude
    ozone_atm_cm: float = 0.35
    #: aerosol optical depth at 500 nm: clean continental air
    aerosol_turbidity_500nm: float = 0.08
    ground_albedo: float = 0.2


@dataclass
class SkySpectra:
    """SPECTRL2 irradiance spectra (W m-2 nm-1) on its own wavelength grid, shape (n_wavelength, n_time)."""

    wavelength_nm: np.ndarray
    diffuse_horizontal: np.ndarray
    direct_normal: np.ndarray
    global_horizontal: np.ndarray


def clear_sky_spectra(sun_zenith_deg, day_of_year: int, atmosphere: Atmosphere = Atmosphere()) -> SkySpectra:
    """SPECTRL2 spectra (pvlib.spectrum.spectrl2) for a horizontal surface at each sun zenith angle.

    Parameters
    ----------
    sun_zenith_deg : float or array_like
        The sun's apparent zenith angle at each time, degree.
    day_of_year : int
        The day of the year (the sun-earth distance).
    atmosphere : Atmosphere, optional
        Pressure, water vapour, ozone, aerosol and ground albedo; default a clean, dry late-winter atmosphere.

    Returns
    -------
    SkySpectra
        Wavelength (nm) and the diffuse horizontal, direct normal and global horizontal irradiance,
        W m-2 nm-1, each of shape (n_wavelength, n_time).
    """
    from pvlib.atmosphere import get_relative_airmass
    from pvlib.spectrum import spectrl2

    zen = np.atleast_1d(np.asarray(sun_zenith_deg, float))
    airmass = np.asarray(get_relative_airmass(zen), float)
    out = spectrl2(apparent_zenith=zen, aoi=zen, surface_tilt=0.0, ground_albedo=atmosphere.ground_albedo,
                   surface_pressure=atmosphere.surface_pressure_pa, relative_airmass=airmass,
                   precipitable_water=atmosphere.precipitable_water_cm, ozone=atmosphere.ozone_atm_cm,
                   aerosol_turbidity_500nm=atmosphere.aerosol_turbidity_500nm, dayofyear=day_of_year)
    dhi = np.asarray(out["dhi"], float).reshape(-1, zen.size)
    dni = np.asarray(out["dni"], float).reshape(-1, zen.size)
    ghi = dhi + dni * np.cos(np.radians(zen))[None, :]
    return SkySpectra(np.asarray(out["wavelength"], float), dhi, dni, ghi)


def band_weights(native_nm: np.ndarray, fine_nm: np.ndarray, responses: np.ndarray) -> np.ndarray:
    """Matrix W (n_response, n_native): W @ S_native = int S R dlambda / int R dlambda.

    S is linearly interpolated from its native grid to ``fine_nm`` (uniform)
    and integrated with the trapezoidal rule against each response.

    Parameters
    ----------
    native_nm : numpy.ndarray
        Shape (n_native,): the spectra's own wavelength grid, nm, increasing.
    fine_nm : numpy.ndarray
        Shape (n_fine,): a uniform wavelength grid, nm, the responses are sampled on.
    responses : numpy.ndarray
        Shape (n_response, n_fine) (or (n_fine,) for one): relative spectral responses.

    Returns
    -------
    numpy.ndarray
        Shape (n_response, n_native): the response-weighted averaging matrix (each row sums to 1).
    """
    native_nm = np.asarray(native_nm, float)
    fine_nm = np.asarray(fine_nm, float)
    j = np.clip(np.searchsorted(native_nm, fine_nm, side="right") - 1, 0, native_nm.size - 2)
    frac = np.clip((fine_nm - native_nm[j]) / (native_nm[j + 1] - native_nm[j]), 0.0, 1.0)
    w = np.full(fine_nm.size, fine_nm[1] - fine_nm[0])
    w[[0, -1]] *= 0.5
    weighted = np.atleast_2d(responses) * w[None, :]
    n = native_nm.size
    out = np.stack([np.bincount(j, r * (1.0 - frac), n) + np.bincount(j + 1, r * frac, n) for r in weighted])
    return out / weighted.sum(axis=1, keepdims=True)


# ----------------------------------------------------------------------------------------- clouds
@dataclass(frozen=True)
class CloudParams:
    """A layer of fair-weather cumulus ("few clouds") drifting over the site."""

    cloud_height_m: float = 1800.0
    #: wind at cloud height: speed (m/s) and the direction it blows towards (deg east of north)
    wind_speed_m_s: float = 11.0
    wind_towards_deg: float = 70.0
    #: fraction of the layer covered (tau > 0): 1 to 2 oktas
    cover_fraction: float = 0.2
    #: correlation length of the random field (m): cumulus a few hundred metres across
    correlation_length_m: float = 600.0
    #: optical depth at a cloud's edge and its growth per standard deviation of the field above the
    #: cover threshold: fair-weather cumulus, optical depth 8 at the edges to 50-100 in the cores
    tau_edge: float = 8.0
    tau_per_sigma: float = 40.0
    #: periodic domain (m) and grid cells per side
    domain_m: float = 64000.0
    grid_n: int = 1024


class CloudField:
    """Vertical optical depth of the cloud layer: a thresholded Gaussian random field, periodic, advected."""

    def __init__(self, params: CloudParams, rng: np.random.Generator):
        self.params = params
        n = params.grid_n
        cell = params.domain_m / n
        k = 2 * np.pi * np.fft.fftfreq(n, d=cell)
        k2 = k[:, None] ** 2 + k[None, :] ** 2
        noise = np.fft.fft2(rng.standard_normal((n, n)))
        length = params.correlation_length_m
        # two scales: cloud bodies and their ragged edges
        spectrum = np.exp(-0.5 * k2 * length**2) + 0.35 * np.exp(-0.5 * k2 * (length / 3.0) ** 2)
        g = np.real(np.fft.ifft2(noise * spectrum))
        g = (g - g.mean()) / g.std()
        threshold = np.quantile(g, 1.0 - params.cover_fraction)
        self.tau_grid = np.where(g > threshold, params.tau_edge + params.tau_per_sigma * (g - threshold), 0.0)
        self.cell_m = cell
        self.origin_m = params.domain_m / 2.0 * rng.uniform(-1.0, 1.0, 2)
        w = np.radians(params.wind_towards_deg)
        self.wind_east_north_m_s = params.wind_speed_m_s * np.array([np.sin(w), np.cos(w)])

    def tau(self, east_m, north_m, t_s):
        """Optical depth of the layer above horizontal offset (east, north) at time ``t_s`` (bilinear, periodic).

        Parameters
        ----------
        east_m : array_like
            Offset east of the site, m.
        north_m : array_like
            Offset north of the site, m.
        t_s : float or array_like
            Time since the start of the hour, s (the wind advects the field).

        Returns
        -------
        numpy.ndarray
            Vertical optical depth tau >= 0, dimensionless, the broadcast shape of ``east_m`` and ``north_m``.
        """
        from scipy.ndimage import map_coordinates

        east = np.asarray(east_m, float) - self.wind_east_north_m_s[0] * t_s + self.origin_m[0]
        north = np.asarray(north_m, float) - self.wind_east_north_m_s[1] * t_s + self.origin_m[1]
        coords = np.stack([np.ravel(north / self.cell_m), np.ravel(east / self.cell_m)])
        out = map_coordinates(self.tau_grid, coords, order=1, mode="grid-wrap")
        return out.reshape(np.broadcast(east, north).shape)

    def tau_towards(self, zenith_deg, azimuth_deg, t_s):
        """Optical depth of the layer seen in direction (Z, alpha); 0 below the horizon.

        Parameters
        ----------
        zenith_deg : array_like
            Zenith angle, degree (the offset h tan Z stops growing beyond ``CLOUD_MAX_ZENITH_DEG``).
        azimuth_deg : array_like
            Azimuth, degree east of north.
        t_s : float or array_like
            Time since the start of the hour, s.

        Returns
        -------
        numpy.ndarray
            Vertical optical depth, dimensionless.
        """
        z = np.asarray(zenith_deg, float)
        a = np.radians(np.asarray(azimuth_deg, float))
        r = self.params.cloud_height_m * np.tan(np.radians(np.minimum(z, CLOUD_MAX_ZENITH_DEG)))
        tau = self.tau(r * np.sin(a), r * np.cos(a), t_s)
        return np.where(z < 90.0, tau, 0.0)


def cloud_diffuse_transmission(tau, sun_zenith_deg):
    """Two-stream diffuse transmission of a conservative cloud layer of optical depth ``tau``.

    T_d = 1 / (1 + 3/4 (1 - g) tau) - exp(-tau / cos Z_s), g = ``CLOUD_ASYMMETRY``, not below 0.

    Parameters
    ----------
    tau : array_like
        Vertical optical depth, dimensionless.
    sun_zenith_deg : float or array_like
        The sun's zenith angle Z_s, degree.

    Returns
    -------
    numpy.ndarray
        The fraction of the global irradiance transmitted diffusely, dimensionless.
    """
    tau = np.asarray(tau, float)
    mu_s = np.cos(np.radians(sun_zenith_deg))
    return np.maximum(1.0 / (1.0 + 0.75 * (1.0 - CLOUD_ASYMMETRY) * tau) - np.exp(-tau / mu_s), 0.0)


# -------------------------------------------------------------------------------------------- sky
COMPONENTS = ("clear", "cloud", "sun", "ground")
#: time step (s) of the solar position and SPECTRL2 spectra of a long series (interpolated linearly
#: between steps): the sun moves 0.04 degree in 10 s, and its path is straight to 1e-6 degree over it
SPECTRUM_STEP_S = 10.0


@dataclass
class Sky:
    """The sky over the site at a set of times: component spectra and angular patterns.

    ``times_utc``: the instants (tz-aware UTC). ``t0_utc``: the start of the
    hour (t = 0 of the clouds' drift and of the spectral-exponent hook).
    ``spectral_exponent``: a(t) per time (the effects' hook), 0 without it.
    """

    times_utc: pd.DatetimeIndex
    t0_utc: pd.Timestamp
    clouds: CloudField
    sky_type: CieSkyType = CIE_SKY_TYPES[12]
    atmosphere: Atmosphere = Atmosphere()
    spectral_exponent: np.ndarray | None = None
    sun_render_radius_deg: float = SUN_DIAMETER_DEG / 2
    #: ground radiance as a fraction of the clear zenith radiance
    ground_fraction: float = 0.2
    sun: pd.DataFrame = field(init=False)
    spectra: SkySpectra = field(init=False)

    def __post_init__(self):
        self.t_s = (self.times_utc - self.t0_utc).total_seconds().to_numpy(float)
        self.sun = self._solar_position()
        zen = self.sun["zenith_deg"].to_numpy()
        self.spectra = self._spectra(zen)
        # the hemispheric integral depends only on the sun zenith: tabulate it and interpolate
        table_z = np.arange(np.floor(zen.min()) - 1.0, np.ceil(zen.max()) + 1.01, 0.5)
        table = np.array([horizontal_integral_sr(float(z), self.sky_type, step_deg=1.0) for z in table_z])
        self.horizontal_integral_sr = np.interp(zen, table_z, table)
        wl = self.spectra.wavelength_nm
        a = np.zeros(len(self.times_utc)) if self.spectral_exponent is None else np.asarray(self.spectral_exponent)
        zenith = self.spectra.diffuse_horizontal / self.horizontal_integral_sr[None, :]
        omega_sun = 2 * np.pi * (1.0 - np.cos(np.radians(self.sun_render_radius_deg)))
        clear, cloud = zenith, self.spectra.global_horizontal / np.pi
        ground = self.ground_fraction * zenith
        if np.any(a != 0):
            # without the hook's exponent the tilt is x ** -0 = 1 exactly, and a product with it changes no bit:
            # skipped (the reference's hour at 6 Hz is 22,000 spectra)
            tilt = (wl[:, None] / 550.0) ** (-a[None, :])
            clear, cloud, ground = clear * tilt, cloud * tilt, ground * tilt
        #: component -> spectrum (n_wavelength, n_time), W sr-1 m-2 nm-1 per unit pattern
        self.component_spectra = {
            "clear": clear,
            "cloud": cloud,
            "sun": self.spectra.direct_normal / omega_sun,
            "ground": ground,
        }

    def _long_series(self) -> bool:
        span = float(self.t_s.max() - self.t_s.min())
        return self.t_s.size > 2 * (span / SPECTRUM_STEP_S + 1)

    def _solar_position(self) -> pd.DataFrame:
        """SPA at every time, or on the ``SPECTRUM_STEP_S`` grid interpolated linearly for long series."""
        if not self._long_series():
            return solar_position(self.times_utc)
        grid_t = np.arange(self.t_s.min(), self.t_s.max() + SPECTRUM_STEP_S, SPECTRUM_STEP_S)
        coarse = solar_position(self.t0_utc + pd.to_timedelta(grid_t, unit="s"))
        out = {k: np.interp(self.t_s, grid_t, np.unwrap(coarse[k].to_numpy(), period=360.0))
               for k in ("zenith_deg", "azimuth_deg", "elevation_deg")}
        out["azimuth_deg"] = np.mod(out["azimuth_deg"], 360.0)
        return pd.DataFrame(out, index=self.times_utc)

    def _spectra(self, zen: np.ndarray) -> SkySpectra:
        """SPECTRL2 at every time, or on a ``SPECTRUM_STEP_S`` grid interpolated linearly in time for long series."""
        day = int(self.times_utc[0].day_of_year)
        if not self._long_series():
            return clear_sky_spectra(zen, day, self.atmosphere)
        grid_t = np.arange(self.t_s.min(), self.t_s.max() + SPECTRUM_STEP_S, SPECTRUM_STEP_S)
        grid_z = np.interp(grid_t, self.t_s, zen)
        coarse = clear_sky_spectra(grid_z, day, self.atmosphere)
        j = np.clip(np.searchsorted(grid_t, self.t_s, side="right") - 1, 0, grid_t.size - 2)
        f = ((self.t_s - grid_t[j]) / SPECTRUM_STEP_S)[None, :]

        def at(x):
            return np.take(x, j, axis=1) * (1.0 - f) + np.take(x, j + 1, axis=1) * f   # take: half the time of x[:, j]

        return SkySpectra(coarse.wavelength_nm, at(coarse.diffuse_horizontal), at(coarse.direct_normal),
                          at(coarse.global_horizontal))

    @property
    def wavelength_nm(self) -> np.ndarray:
        return self.spectra.wavelength_nm

    def clear_zenith_radiance(self) -> np.ndarray:
        """Clear-sky zenith spectral radiance (n_wavelength, n_time), W sr-1 m-2 nm-1.

        Returns
        -------
        numpy.ndarray
            The ``clear`` component's spectrum (with the spectral-exponent hook's tilt).
        """
        return self.component_spectra["clear"]

    def patterns(self, zenith_deg, azimuth_deg, i: int) -> dict[str, np.ndarray]:
        """Angular pattern of each component at time index ``i`` for sky directions (deg).

        Parameters
        ----------
        zenith_deg : array_like
            Zenith angle of the directions, degree.
        azimuth_deg : array_like
            Azimuth of the directions, degree east of north.
        i : int
            Index into ``times_utc``.

        Returns
        -------
        dict[str, numpy.ndarray]
            Component (``clear``, ``cloud``, ``sun``, ``ground``) -> its pattern at each direction, dimensionless
            (the factor on the component's spectrum).
        """
        z = np.asarray(zenith_deg, float)
        a = np.asarray(azimuth_deg, float)
        zs, az_s = float(self.sun["zenith_deg"].iloc[i]), float(self.sun["azimuth_deg"].iloc[i])
        above = z < 90.0
        tau = self.clouds.tau_towards(z, a, self.t_s[i])
        cos_z = np.cos(np.radians(np.minimum(z, CLOUD_MAX_ZENITH_DEG)))
        chi = angle_from_sun_deg(z, a, zs, az_s)
        clear = np.where(above, cie_relative_radiance(z, a, zs, az_s, self.sky_type, chi) * np.exp(-tau / cos_z),
                         0.0)
        cloud = np.where(above, cloud_diffuse_transmission(tau, zs), 0.0)
        tau_sun = float(self.clouds.tau_towards(zs, az_s, self.t_s[i]))
        disc = chi <= self.sun_render_radius_deg
        sun = np.where(disc & above, np.exp(-tau_sun / np.cos(np.radians(zs))), 0.0)
        return {"clear": clear, "cloud": cloud, "sun": sun, "ground": (~above).astype(float)}

    def cone_mean_patterns(self, zenith_deg, azimuth_deg, chunk: int = 2048) -> dict[str, np.ndarray]:
        """Mean of each component's pattern over directions of equal solid angle, at every time: (n_time,) each.

        Vectorised over times and directions (in chunks of ``chunk`` times); for the narrow radiometer cone around
        the zenith (see :func:`cone_directions`).

        Parameters
        ----------
        zenith_deg : array_like
            Shape (n_directions,): zenith angle of the directions, degree.
        azimuth_deg : array_like
            Shape (n_directions,): azimuth, degree east of north.
        chunk : int, optional
            Times computed at once; default 2048.

        Returns
        -------
        dict[str, numpy.ndarray]
            Component -> the mean pattern over the directions at each time, dimensionless, shape (n_time,).
        """
        z = np.asarray(zenith_deg, float)[None, :]
        a = np.asarray(azimuth_deg, float)[None, :]
        n = len(self.times_utc)
        out = {k: np.empty(n) for k in COMPONENTS}
        zs_all = self.sun["zenith_deg"].to_numpy()
        azs_all = self.sun["azimuth_deg"].to_numpy()
        cos_z = np.cos(np.radians(np.minimum(z, CLOUD_MAX_ZENITH_DEG)))
        for start in range(0, n, chunk):
            sl = slice(start, min(start + chunk, n))
            zs, azs, t = zs_all[sl, None], azs_all[sl, None], self.t_s[sl, None]
            tau = self.clouds.tau_towards(np.broadcast_to(z, (t.shape[0], z.shape[1])), a, t)
            above = z < 90.0
            chi = angle_from_sun_deg(z, a, zs, azs)
            clear = np.where(above, cie_relative_radiance(z, a, zs, azs, self.sky_type, chi) * np.exp(-tau / cos_z),
                             0.0)
            cloud = np.where(above, cloud_diffuse_transmission(tau, zs), 0.0)
            tau_sun = self.clouds.tau_towards(zs, azs, t)
            disc = (chi <= self.sun_render_radius_deg) & above
            sun = disc * np.exp(-tau_sun / np.cos(np.radians(zs)))
            out["clear"][sl] = clear.mean(axis=1)
            out["cloud"][sl] = cloud.mean(axis=1)
            out["sun"][sl] = sun.mean(axis=1)
            out["ground"][sl] = np.broadcast_to(~above, clear.shape).mean(axis=1)
        return out

    def band_spectra(self, weights: np.ndarray) -> dict[str, np.ndarray]:
        """Component spectra averaged by ``weights`` (n_response, n_wavelength): (n_response, n_time) each.

        Parameters
        ----------
        weights : numpy.ndarray
            Shape (n_response, n_wavelength): response-weighted averaging on the spectra's grid
            (:func:`band_weights`).

        Returns
        -------
        dict[str, numpy.ndarray]
            Component -> its band-averaged spectrum, W sr-1 m-2 nm-1 per unit pattern, shape (n_response, n_time).
        """
        return {k: weights @ s for k, s in self.component_spectra.items()}

    def radiance(self, weights: np.ndarray, zenith_deg, azimuth_deg, i: int) -> np.ndarray:
        """Response-averaged radiance ``(n_response, *directions)`` at time index ``i``.

        Parameters
        ----------
        weights : numpy.ndarray
            Shape (n_response, n_wavelength): response-weighted averaging (:func:`band_weights`).
        zenith_deg : array_like
            Zenith angle of the directions, degree.
        azimuth_deg : array_like
            Azimuth of the directions, degree east of north.
        i : int
            Index into ``times_utc``.

        Returns
        -------
        numpy.ndarray
            Band radiance, W sr-1 m-2 nm-1, shape (n_response,) followed by the directions' shape.
        """
        spectra = self.band_spectra(weights)
        pats = self.patterns(zenith_deg, azimuth_deg, i)
        return sum(spectra[k][:, i].reshape((-1,) + (1,) * np.ndim(pats[k])) * pats[k][None] for k in COMPONENTS)


def cone_directions(half_angle_deg: float, n_rings: int = 8, n_azimuth: int = 24):
    """Directions (zenith, azimuth in deg) of equal solid angle filling a cone around the zenith.

    Rings at the midpoints of equal steps in cos Z, so every point carries the
    same solid angle: a plain mean over the points is the solid-angle mean
    over the cone (the mean a uniform-response radiometer field of view gives).

    Parameters
    ----------
    half_angle_deg : float
        The cone's half angle, degree.
    n_rings : int, optional
        Rings in cos Z; default 8.
    n_azimuth : int, optional
        Points per ring (successive rings staggered by half a step); default 24.

    Returns
    -------
    zenith_deg : numpy.ndarray
        Shape (n_rings n_azimuth,): zenith angle, degree.
    azimuth_deg : numpy.ndarray
        Shape (n_rings n_azimuth,): azimuth in [0, 360), degree.
    """
    c = 1.0 - (np.arange(n_rings) + 0.5) / n_rings * (1.0 - np.cos(np.radians(half_angle_deg)))
    z = np.degrees(np.arccos(c))
    a = (np.arange(n_azimuth) + 0.5) * 360.0 / n_azimuth
    zz, aa = np.meshgrid(z, a, indexing="ij")
    aa = aa + (np.arange(n_rings)[:, None] * 360.0 / n_azimuth / 2.0)   # stagger the rings
    return zz.ravel(), np.mod(aa.ravel(), 360.0)
