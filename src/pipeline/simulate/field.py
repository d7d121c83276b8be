"""Field experiment: an hour of sky beside a reference radiometer (Larouche et al. 2024, Sections 2.9 and 3.8).

18 March 2021, 16:00 to 17:00 local time (UTC-4), 46.7800 N 71.2754 W: the
zenith lens (``close``) takes a frame every 2 minutes (31 frames) at ISO 100
and one exposure for the hour; the other lens looks at a dim uniform ground.
The sky is :mod:`pipeline.simulate.sky` (CIE clear sky times the SPECTRL2
diffuse spectrum, drifting clouds, the sun disc), rendered through the same
camera physics as the lab experiments (geometry, roll-off, responsivity, the
effects' optics, stray light and noise, :class:`pipeline.simulate.render.Renderer`).

Directions. A zenith-lens pixel at field angle theta and camera azimuth phi
looks at sky zenith angle Z = theta and compass azimuth
alpha = phi + ``CAMERA_HEADING_DEG`` (east of north): the convention of
:func:`pipeline.bundle.apply.sphere_coordinates` for the lens that looks up, turned
by the camera's heading (recorded in the truth).

Band radiance. Each scene gives every raw pixel the effective band radiance
of Eq. (3) computed with the TRUE spectral response
of the zenith lens (:func:`pipeline.simulate.spectral.default_spectral_response`) on a 0.1 nm
grid: the sky's components are spectra times angular patterns, so the band
average of each spectrum is taken once per frame and the pixels only weigh
the patterns.

Exposure. A user points the camera up and picks, from the exposure times of
the dark experiment (so that the dark model is calibrated there), the longest
one that keeps the brightest sky pixel outside the sun below 70 % of
saturation over the hour (the sun disc saturates at any of them).

Reference radiometer (``reference_radiometer.csv``): 19 C-OPS-like channels
(Gaussian, 10 nm FWHM) reading the solid-angle mean of the true spectral
radiance over a 9 degree half-angle cone at the zenith, 6 Hz in UTC from a
minute before the first frame to a minute after the last, with 0.3 % noise
per sample, a dark noise of the C-OPS's noise-equivalent radiance
(1.8e-8 W sr-1 m-2 nm-1, Larouche et al. 2024, Section 3.8) and a calibration
scale error drawn once per dataset (common N(0, 0.025) plus N(0, 0.005) per
channel). In air, no other factor.

Times. Frames carry the camera clock in local time (``FrameSpec.time``),
shifted by the ``clock_offset`` effect's ``camera_clock_offset_s()`` when that
effect is on; the ``spectral_mismatch`` effect's ``sky_spectral_exponent``
tilts the sky spectrum over the hour.

Sun glare. With an effect whose ``sun_glare_wings()`` gives parameters
(``stray_light``), the zenith lens's scene gains the glare of
:mod:`pipeline.simulate.glare`: the band average of SPECTRL2's direct-normal
spectrum, through the cloud in front of the sun, times the image-plane wing
kernel at each pixel; the truth records its mask mean per frame and band
(``mask_sun_glare_W_sr_m2_nm``, also inside ``mask_band_radiance``). Without
it the frames are byte for byte those of a dataset without the effect.
"""

from __future__ import annotations

from datetime import datetime, timedelta

import numpy as np
import pandas as pd
import yaml

from pipeline.io.bands import BANDS
from pipeline.radiometry.rolloff import evaluate_rolloff
from pipeline.simulate import sky as skymod
from pipeline.simulate.glare import SunGlare
from pipeline.simulate.camera import DarkPlan
from pipeline.simulate.lens import HALF_FOV_DEG, default_model, default_rolloff
from pipeline.simulate.plan import ExperimentPlan, FrameSpec, SimContext, planner
from pipeline.simulate.render import band_index_map, lens_geometry
from pipeline.simulate.sensor import true_exposure_and_gain
from pipeline.simulate.spectral import default_spectral_response

#: the lens that points at the zenith (frames.csv ``lens``)
ZENITH_LENS = "close"
START_LOCAL = datetime(2021, 3, 18, 16, 0, 0)
N_FRAMES = 31
FRAME_STEP_S = 120.0
ISO = 100.0
#: compass azimuth (deg east of north) of the zenith lens's phi = 0 direction
CAMERA_HEADING_DEG = 35.0
#: the brightest sky pixel outside the sun stays below this fraction of saturation
EXPOSURE_PEAK_FRACTION = 0.7

#: C-OPS radiance channels (nm), FWHM (nm), field of view and rate
REFERENCE_CHANNELS_NM = (380, 395, 412, 443, 465, 490, 510, 532, 555, 560, 589, 625, 665, 683, 694, 710,
                         765, 780, 875)
REFERENCE_FWHM_NM = 10.0
REFERENCE_HALF_FOV_DEG = 9.0
REFERENCE_RATE_HZ = 6
#: reference samples before the first and after the last frame (s)
REFERENCE_MARGIN_S = 60.0
REFERENCE_RELATIVE_NOISE = 0.003
#: noise-equivalent radiance of the C-OPS (Larouche et al. 2024, Section 3.8: 1.8e-8 at 5 Hz, 490 nm)
REFERENCE_DARK_NOISE_W_SR_M2_NM = 1.8e-8
REFERENCE_SCALE_SIGMA = 0.025
REFERENCE_CHANNEL_SCALE_SIGMA = 0.005
REFERENCE_NAME = "C-OPS radiance sensor (simulated)"

#: the draw of the cloud field is repeated until the zenith cone has structure during the hour:
#: between these fractions of the 31 frames see a cloud (cone-mean optical depth above 1)
CLOUDY_FRAME_FRACTION = (0.15, 0.6)
MAX_CLOUD_DRAWS = 100

_CAMERA_FINE_NM = np.arange(380.0, 720.0 + 1e-9, 0.1)
_REFERENCE_FINE_NM = np.arange(340.0, 920.0 + 1e-9, 0.1)


def reference_responses(fine_nm=_REFERENCE_FINE_NM) -> np.ndarray:
    """Gaussian channel responses (19, n) of the reference on ``fine_nm``."""
    sigma = REFERENCE_FWHM_NM / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    ch = np.asarray(REFERENCE_CHANNELS_NM, float)
    return np.exp(-0.5 * ((fine_nm[None, :] - ch[:, None]) / sigma) ** 2)


def camera_band_weights(native_nm: np.ndarray, lens: str = ZENITH_LENS) -> np.ndarray:
    """(3, n_native): band averages (Eq. 3) of a spectrum given on ``native_nm``, TRUE response, 0.1 nm grid.

    Parameters
    ----------
    native_nm : ndarray
        The spectrum's wavelengths (nm).
    lens : str
        The lens whose true response weighs the spectrum (default: the zenith lens).

    Returns
    -------
    ndarray
        (3, n_native) weights, rows R, G, B.
    """
    s = default_spectral_response(_CAMERA_FINE_NM, lens)
    return skymod.band_weights(native_nm, _CAMERA_FINE_NM, np.stack([s[b] for b in BANDS]))


def reference_weights(native_nm: np.ndarray) -> np.ndarray:
    return skymod.band_weights(native_nm, _REFERENCE_FINE_NM, reference_responses())


def sky_direction(theta_deg, phi_deg, heading_deg: float = CAMERA_HEADING_DEG):
    """Sky zenith angle and compass azimuth (deg) seen by a zenith-lens pixel at (theta, phi)."""
    return np.asarray(theta_deg, float), np.mod(np.asarray(phi_deg, float) + heading_deg, 360.0)


class FieldScene:
    """scene(lens, LensGeometry, band_index): band radiance of every raw pixel at one frame time."""

    def __init__(self, sky: skymod.Sky, band_spectra: dict, index: int, heading_deg: float,
                 glare: SunGlare | None = None, sun_band_irradiance=None):
        self.sky = sky
        self.spectra = band_spectra
        self.index = index
        self.heading_deg = heading_deg
        #: the stray_light effect's sun glare and the band direct-normal irradiance (3, n_frames), W m-2 nm-1
        self.glare = glare
        self.sun_band_irradiance = sun_band_irradiance

    def glare_radiance(self, geometry, band_index):
        """The sun glare's excess (radiance units) at every raw pixel of the zenith lens (0 without it)."""
        if self.glare is None:
            return np.zeros(geometry.theta_deg.shape)
        pattern = self.glare.pattern(geometry.theta_deg, geometry.phi_deg, self.index)
        return self.sun_band_irradiance[:, self.index][band_index] * pattern

    def __call__(self, lens, geometry, band_index):
        i = self.index
        if lens == ZENITH_LENS:
            z, a = sky_direction(geometry.theta_deg, geometry.phi_deg, self.heading_deg)
            patterns = self.sky.patterns(z, a, i)
        else:                                   # the lens that looks down sees the ground only
            patterns = {"ground": np.ones(geometry.theta_deg.shape)}
        out = np.zeros(geometry.theta_deg.shape)
        for k, pattern in patterns.items():
            out += self.spectra[k][:, i][band_index] * pattern
        if lens == ZENITH_LENS:
            out += self.glare_radiance(geometry, band_index)
        return out


def _ring_around(zenith_deg: float, azimuth_deg: float, radius_deg: float, n: int = 90):
    """Directions (Z, alpha) at angular distance ``radius_deg`` from a direction."""
    z, a = np.radians(zenith_deg), np.radians(azimuth_deg)
    centre = np.array([np.sin(z) * np.sin(a), np.sin(z) * np.cos(a), np.cos(z)])      # east, north, up
    u = np.cross(centre, [0.0, 0.0, 1.0]) if abs(centre[2]) < 0.999 else np.array([1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(centre, u)
    psi = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    r = np.radians(radius_deg)
    d = np.cos(r) * centre[:, None] + np.sin(r) * (np.cos(psi) * u[:, None] + np.sin(psi) * v[:, None])
    return np.degrees(np.arccos(np.clip(d[2], -1, 1))), np.mod(np.degrees(np.arctan2(d[0], d[1])), 360.0)


def brightest_sky_rate_dn_per_s(sky: skymod.Sky, band_spectra: dict, camera, exclusion_deg: float,
                                step_deg: float = 1.0) -> float:
    """Largest DN/s of any band over the hour's frames in sky directions farther than ``exclusion_deg`` from the sun.

    Nominal camera (band responsivity and roll-off, no effects): what a user
    sees on the preview. A grid over the sky plus a ring at the exclusion
    radius, where the circumsolar brightness peaks.
    """
    zg, ag = np.meshgrid(np.arange(step_deg / 2, 90.0, step_deg), np.arange(0.0, 360.0, 2 * step_deg),
                         indexing="ij")
    zg, ag = zg.ravel(), ag.ravel()
    resp = camera.radiometry.responsivity_dn_s_per_radiance
    grid_rolloff = {band: evaluate_rolloff(default_rolloff(band, "air", ZENITH_LENS), zg) for band in BANDS}
    best = 0.0
    for i in range(len(sky.times_utc)):
        zs, azs = float(sky.sun["zenith_deg"].iloc[i]), float(sky.sun["azimuth_deg"].iloc[i])
        rz, ra = _ring_around(zs, azs, exclusion_deg)
        z, a = np.concatenate([zg, rz]), np.concatenate([ag, ra])
        keep = (skymod.angle_from_sun_deg(z, a, zs, azs) >= exclusion_deg - 1e-9) & (z < 90.0)
        patterns = sky.patterns(z[keep], a[keep], i)
        for b, band in enumerate(BANDS):
            radiance = sum(band_spectra[k][b, i] * p for k, p in patterns.items())
            g = np.concatenate([grid_rolloff[band], evaluate_rolloff(default_rolloff(band, "air", ZENITH_LENS), rz)])[keep]
            rate = resp[band] * g * radiance
            best = max(best, float(rate.max()))
    return best


def recorded_dn(rate_dn_per_s: float, exposure_s: float, effects=()) -> float:
    """DN above dark that a rate (DN/s at ISO 100, nominal exposure) gives in the frame the camera records:
    the true exposure and gain (shutter offset, per-ISO gain factor when ``effects`` have them)."""
    t_true, factor = true_exposure_and_gain(effects, exposure_s, ISO)
    return rate_dn_per_s * t_true * ISO / 100.0 * factor


def choose_exposure_s(peak_rate_dn_per_s: float, saturation_dn: float, effects=()) -> tuple[float, bool]:
    """The longest dark-plan exposure with the peak below 70 % of saturation (else the shortest, False).

    The user judges the exposure on what the camera records, so the peak is
    taken with the camera's true exposure and gain (:func:`recorded_dn`), not
    the nominal ones.
    """
    ok = [t for t in sorted(DarkPlan().exposures_s)
          if recorded_dn(peak_rate_dn_per_s, t, effects) <= EXPOSURE_PEAK_FRACTION * saturation_dn]
    if ok:
        return float(ok[-1]), True
    return float(min(DarkPlan().exposures_s)), False


def _draw_clouds(rng: np.random.Generator, frame_t_s: np.ndarray) -> tuple[skymod.CloudField, int]:
    """A cloud field whose clouds cross the radiometer cone in some frames but not most (and the draws used)."""
    cz, ca = skymod.cone_directions(REFERENCE_HALF_FOV_DEG)
    for draw in range(1, MAX_CLOUD_DRAWS + 1):
        clouds = skymod.CloudField(skymod.CloudParams(), rng)
        tau = clouds.tau_towards(np.broadcast_to(cz, (frame_t_s.size, cz.size)), ca, frame_t_s[:, None])
        cloudy = float(np.mean(tau.mean(axis=1) > 1.0))
        if CLOUDY_FRAME_FRACTION[0] <= cloudy <= CLOUDY_FRAME_FRACTION[1]:
            return clouds, draw
    raise RuntimeError(f"no cloud field with {CLOUDY_FRAME_FRACTION} cloudy frames in {MAX_CLOUD_DRAWS} draws")


def _saturation_dn(camera) -> float:
    s = camera.sensor
    well = s.conversion_gain(ISO) * s.full_well_e if s.full_well_e else np.inf
    return float(min(s.adc_max_dn - s.bias_dn, well))


def _reference_csv(times_utc: pd.DatetimeIndex, values: np.ndarray) -> str:
    """reference_radiometer.csv text: ISO 8601 UTC with milliseconds and Z, then L_<nm> columns.

    Radiances with 7 significant digits (far below the 0.3 % noise); one
    C-level format per row, not per cell.
    """
    stamps = np.datetime_as_string(times_utc.tz_convert(None).to_numpy().astype("datetime64[ms]"), unit="ms")
    row = "%sZ," + ",".join(["%.6e"] * len(REFERENCE_CHANNELS_NM))
    header = ",".join(["time"] + [f"L_{c}" for c in REFERENCE_CHANNELS_NM])
    lines = [row % ((s,) + tuple(v)) for s, v in zip(stamps.tolist(), values.T.tolist())]
    return header + "\n" + "\n".join(lines) + "\n"


def _site_yaml(clock_offset_h: float) -> str:
    site = {
        "latitude_deg": skymod.LATITUDE_DEG,
        "longitude_deg": skymod.LONGITUDE_DEG,
        "camera_clock_utc_offset_h": clock_offset_h,
        "reference": {"name": REFERENCE_NAME, "channels_nm": [float(c) for c in REFERENCE_CHANNELS_NM],
                      "fwhm_nm": REFERENCE_FWHM_NM, "half_fov_deg": REFERENCE_HALF_FOV_DEG},
    }
    return yaml.safe_dump(site, sort_keys=False)


@planner("field")
def plan_field(ctx: SimContext) -> ExperimentPlan:
    camera = ctx.camera
    lens_px = ctx.scale.lens_px
    # the field's own draws: the same sky whichever other experiments are simulated
    rng = np.random.default_rng([ctx.seed, 20210318])
    clock_offset_s = float(sum(e.camera_clock_offset_s() for e in ctx.effects))

    def exponent(t_s):
        return np.array([sum(e.sky_spectral_exponent(float(t) / 3600.0) for e in ctx.effects) for t in t_s])

    utc = timedelta(hours=-skymod.UTC_OFFSET_H)
    t0_utc = pd.Timestamp(START_LOCAL + utc, tz="UTC")
    frame_t_s = np.arange(N_FRAMES) * FRAME_STEP_S
    frame_utc = pd.DatetimeIndex([t0_utc + pd.Timedelta(seconds=float(t)) for t in frame_t_s])
    clouds, draws = _draw_clouds(rng, frame_t_s)

    # the sun disc, drawn at least 1.5 raw pixels wide in radius where the pixels are coarser than it
    deg_per_px = HALF_FOV_DEG["air"] / default_model(ZENITH_LENS, "air", (lens_px, lens_px)).image_circle_radius()
    sun_radius = max(skymod.SUN_DIAMETER_DEG / 2, 1.5 * deg_per_px)
    sky = skymod.Sky(frame_utc, t0_utc, clouds, spectral_exponent=exponent(frame_t_s),
                     sun_render_radius_deg=sun_radius)
    band_w = camera_band_weights(sky.wavelength_nm)
    ref_w = reference_weights(sky.wavelength_nm)
    band_spectra = sky.band_spectra(band_w)

    saturation = _saturation_dn(camera)
    exclusion = sun_radius + deg_per_px
    peak_rate = brightest_sky_rate_dn_per_s(sky, band_spectra, camera, exclusion)
    exposure_s, rule_met = choose_exposure_s(peak_rate, saturation, ctx.effects)

    # the stray_light effect's glare from the sun (simulate/glare.py): the direct beam through the clouds
    tau_sun = np.array([float(clouds.tau_towards(z, a, t)) for z, a, t in
                        zip(sky.sun["zenith_deg"], sky.sun["azimuth_deg"], frame_t_s)])
    wings = [w for w in (e.sun_glare_wings() for e in ctx.effects) if w is not None]
    glare, sun_band = None, None
    if wings:
        transmission = np.exp(-tau_sun / np.cos(np.radians(sky.sun["zenith_deg"].to_numpy())))
        glare = SunGlare(wings[0], sky.sun["zenith_deg"].to_numpy(),
                         np.mod(sky.sun["azimuth_deg"].to_numpy() - CAMERA_HEADING_DEG, 360.0), transmission)
        sun_band = band_w @ sky.spectra.direct_normal                                      # (3, n_frames)

    lit = tuple(camera.lens_names)
    frames = []
    for i in range(N_FRAMES):
        clock = START_LOCAL + timedelta(seconds=float(frame_t_s[i]) + clock_offset_s)
        frames.append(FrameSpec(ZENITH_LENS, "signal", ISO, exposure_s, {},
                                FieldScene(sky, band_spectra, i, CAMERA_HEADING_DEG, glare, sun_band),
                                time=clock, lit=lit))

    # truth at the frames: pixel mean of the band radiance in the 9-degree mask, and the cone mean
    geo = lens_geometry(ZENITH_LENS, "air", lens_px)
    band_index = band_index_map(lens_px)
    mask = (geo.theta_deg <= REFERENCE_HALF_FOV_DEG) & geo.lit
    cz, ca = skymod.cone_directions(REFERENCE_HALF_FOV_DEG)
    cone = sky.cone_mean_patterns(*sky_direction(cz, ca))
    cone_band = sum(band_spectra[k] * cone[k][None, :] for k in skymod.COMPONENTS)       # (3, n_frames)
    ref_spectra = sky.band_spectra(ref_w)
    ref_at_frames = sum(ref_spectra[k] * cone[k][None, :] for k in skymod.COMPONENTS)    # (19, n_frames)
    mask_band = np.empty((len(BANDS), N_FRAMES))
    mask_glare = np.zeros((len(BANDS), N_FRAMES))
    for i, spec in enumerate(frames):
        radiance = spec.radiance(ZENITH_LENS, geo, band_index)
        excess = spec.radiance.glare_radiance(geo, band_index)
        for b in range(len(BANDS)):
            mask_band[b, i] = radiance[mask & (band_index == b)].mean()
            mask_glare[b, i] = excess[mask & (band_index == b)].mean()
    tau_zenith = clouds.tau_towards(np.broadcast_to(cz, (N_FRAMES, cz.size)), sky_direction(cz, ca)[1],
                                    frame_t_s[:, None]).mean(axis=1)

    # the reference series: 6 Hz in UTC, on exact milliseconds
    n_ref = int(round((frame_t_s[-1] + 2 * REFERENCE_MARGIN_S) * REFERENCE_RATE_HZ)) + 1
    ref_t_s = np.round(np.arange(n_ref) * 1000.0 / REFERENCE_RATE_HZ) / 1000.0 - REFERENCE_MARGIN_S
    ref_utc = t0_utc + pd.to_timedelta(np.round(ref_t_s * 1000.0).astype(np.int64), unit="ms")
    ref_sky = skymod.Sky(ref_utc, t0_utc, clouds, spectral_exponent=exponent(ref_t_s),
                         sun_render_radius_deg=sun_radius)
    ref_cone = ref_sky.cone_mean_patterns(*sky_direction(cz, ca))
    ref_spec = ref_sky.band_spectra(ref_w)
    ref_true = sum(ref_spec[k] * ref_cone[k][None, :] for k in skymod.COMPONENTS)         # (19, n_ref)
    scale_common = float(REFERENCE_SCALE_SIGMA * rng.standard_normal())
    scale_channel = REFERENCE_CHANNEL_SCALE_SIGMA * rng.standard_normal(len(REFERENCE_CHANNELS_NM))
    scale = 1.0 + scale_common + scale_channel
    measured = (ref_true * scale[:, None] * (1.0 + REFERENCE_RELATIVE_NOISE * rng.standard_normal(ref_true.shape))
                + REFERENCE_DARK_NOISE_W_SR_M2_NM * rng.standard_normal(ref_true.shape))

    st = sky.sky_type
    truth = {
        "zenith_lens": ZENITH_LENS,
        "iso": ISO,
        "exposure_s": exposure_s,
        "exposure_rule": {"peak_fraction_of_saturation": EXPOSURE_PEAK_FRACTION, "met": rule_met,
                          "brightest_sky_fraction_of_saturation":
                              recorded_dn(peak_rate, exposure_s, ctx.effects) / saturation,
                          "sun_exclusion_deg": exclusion},
        "clock_offset_s": clock_offset_s,
        "camera_heading_deg": CAMERA_HEADING_DEG,
        "direction_convention": "sky zenith = theta, compass azimuth (east of north) = phi + camera_heading_deg",
        "frames": {
            "true_utc": [t.isoformat() for t in frame_utc],
            "camera_clock_local": [spec.time.isoformat() for spec in frames],
            "sun_zenith_deg": sky.sun["zenith_deg"].to_numpy(),
            "sun_azimuth_deg": sky.sun["azimuth_deg"].to_numpy(),
            "sun_elevation_deg": sky.sun["elevation_deg"].to_numpy(),
            "spectral_exponent": exponent(frame_t_s),
            "zenith_cloud_optical_depth": tau_zenith,
            "sun_cloud_optical_depth": tau_sun,
            "mask_band_radiance_W_sr_m2_nm": {b: mask_band[j] for j, b in enumerate(BANDS)},
            "mask_sun_glare_W_sr_m2_nm": {b: mask_glare[j] for j, b in enumerate(BANDS)},
            "sun_direct_band_irradiance_W_m2_nm": ({b: sun_band[j] for j, b in enumerate(BANDS)}
                                                   if sun_band is not None else None),
            "cone_band_radiance_W_sr_m2_nm": {b: cone_band[j] for j, b in enumerate(BANDS)},
            "reference_true_W_sr_m2_nm": {f"L_{c}": ref_at_frames[j] for j, c in enumerate(REFERENCE_CHANNELS_NM)},
        },
        "sun_glare": ({**wings[0], "form": "image-plane Moffat wings f (p-2)/(2 pi d0^2) (1 + (d/d0)^2)^(-p/2), "
                       "d in the equidistant image plane, times the band direct-normal irradiance through the "
                       "clouds (simulate/glare.py); included in mask_band_radiance"} if wings else None),
        "mask": {"half_angle_deg": REFERENCE_HALF_FOV_DEG,
                 "pixels_per_band": [int(np.sum(mask & (band_index == b))) for b in range(len(BANDS))],
                 "mask_band_radiance": "mean over the raw pixels of each band within the half angle (true optics)",
                 "cone_band_radiance": "solid-angle mean over the cone (the reference's field of view)"},
        "reference": {
            "channels_nm": list(REFERENCE_CHANNELS_NM), "fwhm_nm": REFERENCE_FWHM_NM,
            "half_fov_deg": REFERENCE_HALF_FOV_DEG, "rate_hz": REFERENCE_RATE_HZ,
            "scale_error_common_rel": scale_common, "scale_error_channel_rel": scale_channel,
            "scale_factor": scale, "relative_noise": REFERENCE_RELATIVE_NOISE,
            "dark_noise_W_sr_m2_nm": REFERENCE_DARK_NOISE_W_SR_M2_NM,
        },
        "sky_model": {
            "description": ("CIE standard general sky (ISO 15469:2004) angular pattern times the SPECTRL2 "
                            "diffuse spectrum scaled to its horizontal diffuse irradiance; a drifting "
                            "layer of cumulus (two-stream diffuse transmission of the global irradiance, "
                            "direct attenuation of the clear sky); the sun disc of SPECTRL2's direct beam"),
            "cie_type": {"number": st.number, "a": st.a, "b": st.b, "c": st.c, "d": st.d, "e": st.e,
                         "description": st.description},
            "atmosphere": vars(sky.atmosphere).copy(),
            "clouds": vars(clouds.params).copy(),
            "cloud_draws": draws,
            "sun_render_radius_deg": sun_radius,
            "ground_fraction_of_clear_zenith": sky.ground_fraction,
            "solar_position": "pvlib.solarposition.get_solarposition, method nrel_numpy (SPA), apparent",
        },
    }
    sidecars = {"reference_radiometer.csv": _reference_csv(ref_utc, measured),
                "site.yaml": _site_yaml(skymod.UTC_OFFSET_H)}
    return ExperimentPlan(frames, sidecars=sidecars, truth=truth)
