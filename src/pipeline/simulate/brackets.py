"""Exposure brackets of one sky with the sun: the frames a user merges into one high-dynamic-range map.

The scene (a stated form, defined here; directions as the camera's sphere
convention: the close lens looks at the zenith, a raw site of the close lens
at field angle theta sees zenith angle Z = theta, one of the far lens
Z = 180 - theta, and azimuth phi, -phi respectively):

* sky (Z <= 90 degrees): the CIE standard general sky of type 12 relative
  to its zenith radiance (:func:`pipeline.simulate.sky.cie_relative_radiance`),
  L = L_z,b * f(chi) phi(Z) / (f(Z_s) phi(0)), with L_z,b the band's zenith
  radiance; the sun-adjacent sky is about ten times the zenith's;
* the sun: a disc of ``sun_radius_deg`` about (Z_s, alpha_s) of radiance
  ``sun_factor`` times L_z,b, far above saturation at the shortest exposure;
* the lower hemisphere (Z > 90 degrees): a ground that dims from the
  horizon to the nadir, L = L_z,b h (g / h)^((Z - 90) / 90) with
  h = ``horizon_ratio`` and g = ``ground_ratio``: every level from the sky's
  to the nadir's, five decades below the sun-adjacent sky.

A bracket is one frame per exposure of the same scene (the camera still),
rendered through the camera's true physics (:class:`pipeline.simulate.render.Renderer`,
shot, read and quantisation noise, saturation at the ADC's white level), and
written as DNG files with a frames table ``frames.csv`` (columns ``file`` and
``bracket``). The truth, never read by the pipeline, is each lens's band
images of the effective band radiance every band pixel sees: the scene at
each raw site's true direction, split into bands as the pipeline splits the
mosaic (R and B their site, G the mean of its two sites).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import xarray as xr
import pandas as pd
import yaml
from scipy.spatial.transform import Rotation

from pipeline.io.bands import BANDS
from pipeline.io.rawio import write_dng
from pipeline.simulate.camera import Camera
from pipeline.simulate.dataset import SCALES
from pipeline.simulate.plan import FrameSpec
from pipeline.simulate.render import Renderer
from pipeline.simulate.sky import CIE_SKY_TYPES, angle_from_sun_deg, cie_relative_radiance

__all__ = ["BracketScene", "BRACKET_EXPOSURES_S", "render_bracket", "truth_band_images", "sun_at_site",
           "write_attitude_log", "ATTITUDE_LOG_SIGMA_DEG"]

#: the simulated attitude log's noise (roll, pitch, heading; degree): each sample is the true attitude plus
#: independent normal noise of these standard deviations, which the log states as its sigmas
ATTITUDE_LOG_SIGMA_DEG = (0.2, 0.2, 1.0)

#: the default bracket: 1/4000 s to 1 s in steps of about four (seven exposures, 3.6 decades of exposure)
BRACKET_EXPOSURES_S = (1 / 4000, 1 / 1000, 1 / 250, 1 / 60, 1 / 15, 1 / 4, 1.0)


@dataclass(frozen=True)
class BracketScene:
    """A clear sky with the sun over a dim ground (module docstring); radiances in W m-2 sr-1 nm-1."""

    zenith_radiance: tuple = (0.035, 0.04, 0.045)     # R, G, B
    sun_zenith_deg: float = 40.0
    sun_azimuth_deg: float = 120.0
    sun_radius_deg: float = 4.0
    sun_factor: float = 3000.0
    horizon_ratio: float = 0.1
    ground_ratio: float = 2e-5
    cie_type: int = 12
    #: the camera's true attitude (roll, pitch, heading; degree): camera directions are rotated into the
    #: earth frame (north, east, down) by Rz(heading) Ry(pitch) Rx(roll) before the scene is looked up
    attitude_deg: tuple = (0.0, 0.0, 0.0)

    def radiance(self, zenith_deg, azimuth_deg, band_index) -> np.ndarray:
        """Effective band radiance of the directions (arrays of one shape; ``band_index`` 0 R, 1 G, 2 B).

        Parameters
        ----------
        zenith_deg : array_like
            Earth-frame zenith angle Z of the directions, degree (above 90: the ground).
        azimuth_deg : array_like
            Azimuth, degree from north towards east.
        band_index : array_like
            Band index of each direction (0 R, 1 G, 2 B), same shape.

        Returns
        -------
        numpy.ndarray
            The scene's band radiance, W m-2 sr-1 nm-1: sky, sun disc or ground (module docstring).
        """
        z = np.asarray(zenith_deg, float)
        a = np.asarray(azimuth_deg, float)
        lz = np.asarray(self.zenith_radiance, float)[np.asarray(band_index)]
        sky = CIE_SKY_TYPES[self.cie_type]
        chi = angle_from_sun_deg(z, a, self.sun_zenith_deg, self.sun_azimuth_deg)
        upper = lz * cie_relative_radiance(np.minimum(z, 90.0), a, self.sun_zenith_deg, self.sun_azimuth_deg, sky,
                                           chi_deg=chi)
        upper = np.where(chi <= self.sun_radius_deg, lz * self.sun_factor, upper)
        lower = lz * self.horizon_ratio * (self.ground_ratio / self.horizon_ratio) ** ((np.clip(z, 90.0, 180.0)
                                                                                        - 90.0) / 90.0)
        return np.where(z <= 90.0, upper, lower)

    def camera_radiance(self, lens: str, geometry, band_index) -> np.ndarray:
        """The renderer's scene callback: per raw site of ``lens``.

        A site of the close lens at field angle theta and azimuth phi looks at Z = theta, alpha = phi; one of the
        far lens at Z = 180 - theta, alpha = -phi; then rotated into the earth frame by the camera's attitude
        (:meth:`earth_direction`).

        Parameters
        ----------
        lens : str
            ``close`` (looking at the zenith) or ``far``.
        geometry : LensGeometry
            The true viewing directions of the lens's raw sites (theta, phi, degree).
        band_index : numpy.ndarray
            Band index of each raw site (0 R, 1 G, 2 B).

        Returns
        -------
        numpy.ndarray
            Band radiance at each raw site, W m-2 sr-1 nm-1.
        """
        theta, phi = geometry.theta_deg, geometry.phi_deg
        if lens == "close":
            z, a = theta, phi % 360.0
        else:
            z, a = 180.0 - theta, (-phi) % 360.0
        return self.radiance(*self.earth_direction(z, a), band_index)

    def earth_direction(self, zenith_deg, azimuth_deg):
        """Earth-frame zenith angle and azimuth (deg, from north towards east) of camera directions.

        Camera directions are rotated into the earth frame (north, east, down) by Rz(heading) Ry(pitch) Rx(roll) of
        ``attitude_deg``; unchanged when the attitude is zero.

        Parameters
        ----------
        zenith_deg : array_like
            Zenith angle in the camera's frame, degree.
        azimuth_deg : array_like
            Azimuth in the camera's frame, degree.

        Returns
        -------
        zenith_deg : numpy.ndarray
            Earth-frame zenith angle, degree.
        azimuth_deg : numpy.ndarray
            Earth-frame azimuth in [0, 360), degree from north towards east.
        """
        if not any(self.attitude_deg):
            return zenith_deg, azimuth_deg
        z, a = np.radians(np.asarray(zenith_deg, float)), np.radians(np.asarray(azimuth_deg, float))
        ned = np.stack([np.sin(z) * np.cos(a), np.sin(z) * np.sin(a), -np.cos(z)], axis=-1)
        roll, pitch, heading = self.attitude_deg
        e = Rotation.from_euler("ZYX", [heading, pitch, roll], degrees=True).apply(ned.reshape(-1, 3))
        e = e.reshape(ned.shape)
        return (np.degrees(np.arccos(np.clip(-e[..., 2], -1.0, 1.0))),
                np.degrees(np.arctan2(e[..., 1], e[..., 0])) % 360.0)


def truth_band_images(renderer: Renderer, scene: BracketScene, lens: str, medium: str = "air") -> np.ndarray:
    """(band, y, x) effective band radiance each band pixel of ``lens`` sees (G: the mean of its two sites).

    Parameters
    ----------
    renderer : Renderer
        The renderer of the bracket (its camera's true geometry and band sites).
    scene : BracketScene
        The scene.
    lens : str
        The lens.
    medium : str, optional
        ``air`` or ``water``; default ``air``.

    Returns
    -------
    numpy.ndarray
        Shape (3, lens_px / 2, lens_px / 2), bands R, G, B: W m-2 sr-1 nm-1; NaN outside the image circle.
    """
    geo = renderer.geometry(lens, medium)
    sites = scene.camera_radiance(lens, geo, renderer.band_index)
    sites = np.where(geo.lit, sites, np.nan)
    return np.stack([sites[0::2, 0::2], 0.5 * (sites[0::2, 1::2] + sites[1::2, 0::2]), sites[1::2, 1::2]])


def sun_at_site(site, when: datetime) -> tuple[float, float]:
    """The sun's apparent zenith angle and azimuth (deg, from north towards east) at ``site`` and time ``when``.

    pvlib's solar position, as the scene's truth.

    Parameters
    ----------
    site : sequence of float
        (latitude, longitude[, altitude]): degree north, degree east, m (altitude default 0).
    when : datetime.datetime
        The time, UTC (naive).

    Returns
    -------
    zenith_deg : float
        Apparent (refracted) zenith angle, degree.
    azimuth_deg : float
        Azimuth, degree from north towards east.
    """
    from pvlib.solarposition import get_solarposition

    pos = get_solarposition(pd.DatetimeIndex([pd.Timestamp(when, tz="UTC")]), site[0], site[1],
                            altitude=site[2] if len(site) > 2 else 0.0)
    return float(pos["apparent_zenith"].iloc[0]), float(pos["azimuth"].iloc[0])


def write_attitude_log(path, attitude_deg, start: datetime, seconds: float, *, seed: int,
                       sigma_deg=ATTITUDE_LOG_SIGMA_DEG, heading_bias_deg: float = 0.0) -> Path:
    """An attitude log (the pipeline's CSV format) of a still camera.

    One sample a second from two seconds before ``start`` to two after ``start + seconds`` (a sample at ``start``
    itself), each the true attitude plus normal noise of ``sigma_deg``, stated as the sigmas.

    Parameters
    ----------
    path : str or pathlib.Path
        The CSV file to write.
    attitude_deg : sequence of float
        The true (roll, pitch, heading), degree.
    start : datetime.datetime
        The first frame's time, UTC (naive).
    seconds : float
        The duration the log must cover, s.
    seed : int
        Seed of the noise (with the stream 33).
    sigma_deg : sequence of float, optional
        Standard deviations of the noise of (roll, pitch, heading), degree; default
        :data:`ATTITUDE_LOG_SIGMA_DEG` (0.2, 0.2, 1.0).
    heading_bias_deg : float, optional
        A wrong heading added to every sample (a compass off by that much), degree, not stated; default 0.

    Returns
    -------
    pathlib.Path
        ``path``: columns ``time_utc``, ``roll_deg``, ``pitch_deg``, ``heading_deg`` and their ``*_sigma_deg``.
    """
    rng = np.random.default_rng([seed, 33])
    n = int(np.ceil(seconds)) + 5
    times = [pd.Timestamp(start, tz="UTC") + pd.Timedelta(seconds=k - 2) for k in range(n)]
    noise = rng.normal(0.0, 1.0, (n, 3)) * np.asarray(sigma_deg, float)
    values = np.asarray(attitude_deg, float) + noise
    values[:, 2] = (values[:, 2] + heading_bias_deg) % 360.0
    table = pd.DataFrame({"time_utc": [t.isoformat() for t in times], "roll_deg": values[:, 0],
                          "pitch_deg": values[:, 1], "heading_deg": values[:, 2],
                          "roll_sigma_deg": sigma_deg[0], "pitch_sigma_deg": sigma_deg[1],
                          "heading_sigma_deg": sigma_deg[2]})
    path = Path(path)
    table.to_csv(path, index=False)
    return path


def render_bracket(folder, scene: BracketScene = BracketScene(), exposures_s=BRACKET_EXPOSURES_S, *, seed: int = 1,
                   scale: str = "tiny", iso: float = 100.0, start: datetime = datetime(2021, 3, 18, 16, 0, 0),
                   bracket: str = "B001", raw_transform=None, first_index: int = 0, site=None,
                   attitude_log_sigma_deg=None, heading_bias_deg: float = 0.0, medium: str = "air",
                   light_factor=1.0) -> dict:
    """Render one bracket into ``folder``: DNG frames, the frames table and the truth.

    ``<bracket>_<k>.dng`` per exposure, ``frames.csv`` (appended to when it exists) and the truth in
    ``truth/<bracket>.nc`` and ``truth/<bracket>.yaml``. The frames follow each other by their exposure and a
    quarter second.

    Parameters
    ----------
    folder : str or pathlib.Path
        The folder to write into (created when missing).
    scene : BracketScene, optional
        The scene; default ``BracketScene()``.
    exposures_s : sequence of float, optional
        The exposure times, s; default :data:`BRACKET_EXPOSURES_S` (1/4000 s to 1 s).
    seed : int, optional
        The camera's and the noise's seed; default 1.
    scale : str, optional
        The simulator's scale (the lens region size); default ``tiny``.
    iso : float, optional
        The ISO setting; default 100.
    start : datetime.datetime, optional
        The first frame's time (UTC, which the DNG carries); default 2021-03-18 16:00.
    bracket : str, optional
        The bracket's name (file names, ``bracket`` column); default ``B001``.
    raw_transform : callable, optional
        ``raw_transform(cfa, black_level_dn, white_level_dn) -> cfa``: applied to each raw mosaic before it is
        written (a test's own bent response, for example); the truth is the scene's, untouched by it. Default none.
    first_index : int, optional
        Index of the first frame in the noise's stream (brackets of one scene with different noise); default 0.
    site : sequence of float, optional
        (lat, lon[, alt_m]): the sun is put where pvlib puts it at the site and ``start``, replacing the scene's
        sun position; default None.
    attitude_log_sigma_deg : sequence of float, optional
        (roll, pitch, heading), degree: also write ``<bracket>_attitude.csv``, a log of the scene's
        ``attitude_deg`` with that noise (:func:`write_attitude_log`); default None (no log).
    heading_bias_deg : float, optional
        A wrong heading in the attitude log, degree; default 0.
    medium : str, optional
        ``air`` or ``water``: the lenses' true geometry in that medium; default ``air``.
    light_factor : float or callable, optional
        The renderer's light factor (in water: the response over the in-air one,
        :func:`pipeline.simulate.underwater.in_water_light_factor`); default 1.

    Returns
    -------
    dict
        ``files`` (list of pathlib.Path, the DNGs), ``frames_csv`` and ``truth`` (paths), ``scene`` (the
        BracketScene rendered, the sun placed), and ``attitude_log`` (path) when one was written.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if site is not None:
        sz, sa = sun_at_site(site, start)
        scene = replace(scene, sun_zenith_deg=sz, sun_azimuth_deg=sa)
    camera = Camera()
    renderer = Renderer(camera, SCALES[scale].lens_px, seed, [])
    black = round(camera.sensor.bias_dn)
    white = camera.sensor.adc_max_dn
    files = []
    when = start
    for k, t in enumerate(exposures_s):
        spec = FrameSpec("both", "signal", iso, float(t), radiance=scene.camera_radiance, medium=medium,
                         light_factor=light_factor)
        cfa = renderer.render(first_index + k, 97, spec)
        if raw_transform is not None:
            cfa = np.asarray(raw_transform(cfa, float(black), float(white)), np.uint16)
        path = folder / f"{bracket}_{k}.dng"
        write_dng(path, cfa, exposure_s=float(t), iso=iso, time=when, black_level=black, white_level=white,
                  cfa_pattern="RGGB", make=camera.make, model=camera.model, serial=camera.serial)
        files.append(path)
        when += timedelta(seconds=float(t) + 0.25)     # a burst: each exposure and a quarter second
    table = folder / "frames.csv"
    rows = "".join(f"{p.name},{bracket}\n" for p in files)
    table.write_text((table.read_text() if table.exists() else "file,bracket\n") + rows)
    truth_dir = folder / "truth"
    truth_dir.mkdir(exist_ok=True)
    lenses = list(camera.lens_names)
    truth = np.stack([truth_band_images(renderer, scene, lens, medium) for lens in lenses])
    ds = xr.Dataset({"radiance": (("lens", "band", "y", "x"), truth,
                                  {"long_name": "true effective band radiance of each band pixel",
                                   "units": "W m-2 sr-1 nm-1"})},
                    coords={"lens": lenses, "band": list(BANDS)})
    ds.to_netcdf(truth_dir / f"{bracket}.nc")
    (truth_dir / f"{bracket}.yaml").write_text(yaml.safe_dump(
        {"scene": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(scene).items()},
         "exposures_s": [float(t) for t in exposures_s], "iso": iso, "seed": seed, "scale": scale, "medium": medium,
         "files": [p.name for p in files]}, sort_keys=False))
    out = {"files": files, "frames_csv": table, "truth": truth_dir / f"{bracket}.nc", "scene": scene}
    meta = yaml.safe_load((truth_dir / f"{bracket}.yaml").read_text())
    meta["site"] = list(site) if site is not None else None
    meta["start_utc"] = start.isoformat()
    if attitude_log_sigma_deg is not None:
        out["attitude_log"] = write_attitude_log(folder / f"{bracket}_attitude.csv", scene.attitude_deg, start,
                                                 (when - start).total_seconds(), seed=seed,
                                                 sigma_deg=attitude_log_sigma_deg, heading_bias_deg=heading_bias_deg)
        meta["attitude_log"] = {"file": out["attitude_log"].name, "sigma_deg": list(attitude_log_sigma_deg),
                                "heading_bias_deg": float(heading_bias_deg)}
    (truth_dir / f"{bracket}.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    return out
