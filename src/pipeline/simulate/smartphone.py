"""A rectilinear smartphone-like RAW camera and its lab experiments (any RAW camera, issue 14).

The camera, after the smartphone RAW radiometry of Burggraaff et al. (2022):
one lens region covering the whole active area (docs/dataset-format.md ``projection:
rectilinear``: no image circle, no unlit corners), a 12-bit ADC, a GRBG colour
filter array, optically black margins outside the DNG ActiveArea, and a gain
table that is not proportional to ISO (Section 2.3 of the paper: the ISO
speed maps to an analogue gain through a camera-specific table; digital gain
above the analogue range). Its optics are a pinhole camera with Brown-Conrady
radial and tangential distortion, written here in its forward form (the
pipeline fits the same physics with OpenCV), and a vignetting that is the
natural cos^4 law times a mechanical term, stronger in red (lens colour
shading). Truth, as for the default camera, goes to the truth folder beside
the dataset.

Experiments: dark (ISO and exposure sweeps), linearity (uniform integrating
sphere, exposure and gain sweeps), geometry (a lit chessboard in several
poses, rendered by intersecting every raw pixel's true ray with the board),
roll-off (vignetting: the sphere port, a disc of 2 degrees, at field angles
every 5 degrees in the horizontal and vertical planes, as far as the frame
reaches, two frames each, and dark frames). The sensor physics (Poisson electrons,
read noise, offset pattern, the effects' dark current, hot pixels, PRNU and
frame offsets) is :func:`pipeline.simulate.sensor.expose`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from pipeline import __version__
from pipeline.io.bands import BANDS
from pipeline.io.dataset import write_md5sums
from pipeline.effects import get as get_effect
from pipeline.errors import InputError
from pipeline.geometry.chessboard import Board
from pipeline.io.rawio import write_dng
from pipeline.simulate.camera import SensorParams
from pipeline.simulate.chessboard import render_chessboard
from pipeline.simulate.dataset import partial_folders, yaml_plain
from pipeline.simulate.plan import PLANNERS, FrameSpec, LensGeometry, SimContext
from pipeline.simulate.sensor import draw_static_pattern, expose, true_exposure_and_gain

#: experiments the smartphone simulator writes, in acquisition order
PHONE_EXPERIMENTS = ("dark", "linearity", "geometry", "rolloff", "spectral", "absolute")
LENS = "main"
START_TIME = datetime(2022, 6, 1, 10, 0, 0)
FRAME_INTERVAL_S = 0.5


@dataclass(frozen=True)
class PhoneSensor(SensorParams):
    """A 12-bit smartphone sensor whose conversion gain follows a table, not ISO / 100."""

    bias_dn: float = 256.0
    read_noise_e: float = 1.6
    offset_fpn_e: float = 0.5
    offset_fpn_dn: float = 0.6
    adc_max_dn: int = 2**12 - 1
    #: (ISO, conversion gain in DN per electron): analogue gain up to ISO 400, then less than
    #: proportional (digital gain at a smaller step); ISO 100 is the reference
    gain_table: tuple = ((100.0, 0.42), (200.0, 0.81), (400.0, 1.55), (800.0, 2.70), (1600.0, 4.40))
    conversion_gain_dn_per_e_iso100: float = 0.42

    def conversion_gain(self, iso: float) -> float:
        """Conversion gain at ``iso`` from the phone's gain table (not ISO / 100).

        Parameters
        ----------
        iso : float
            The ISO setting; one of the table's.

        Returns
        -------
        float
            DN per electron.

        Raises
        ------
        ValueError
            When ``iso`` is not in the gain table.
        """
        table = dict(self.gain_table)
        if float(iso) not in table:
            raise ValueError(f"ISO {iso} is not in the phone's gain table {sorted(table)}")
        return table[float(iso)]


@dataclass(frozen=True)
class PinholeOptics:
    """True pinhole camera with Brown-Conrady distortion, in raw pixels of the active area.

    Forward model (normalised coordinates x, y of a ray; r^2 = x^2 + y^2):
    x_d = x (1 + k1 r^2 + k2 r^4) + 2 p1 x y + p2 (r^2 + 2 x^2),
    y_d = y (1 + k1 r^2 + k2 r^4) + p1 (r^2 + 2 y^2) + 2 p2 x y,
    u = fx x_d + cx, v = fy y_d + cy (pixel centres at integers).
    Focal length and centre are fractions of the active width and height.
    """

    focal_fraction_of_width: float = 0.78     # half diagonal FOV about 38 degrees (26 mm equivalent)
    centre_offset_fraction: tuple = (0.012, -0.008)
    k1: float = -0.08
    k2: float = 0.02
    p1: float = 0.0015
    p2: float = -0.001
    #: mechanical vignetting at the half diagonal, per band (lens colour shading: red strongest)
    mechanical_at_corner: dict = field(default_factory=lambda: {"R": 0.22, "G": 0.12, "B": 0.15})

    def intrinsics(self, shape: tuple[int, int]) -> tuple[float, float, float, float]:
        """Focal lengths and principal point of the active area.

        Parameters
        ----------
        shape : tuple of (int, int)
            (rows, cols) of the active area, raw pixels.

        Returns
        -------
        fx : float
            Focal length along the columns, raw pixels.
        fy : float
            Focal length along the rows, raw pixels (equal to ``fx``).
        cx : float
            Principal point's column, raw pixels (pixel centres at integers).
        cy : float
            Principal point's row, raw pixels.
        """
        h, w = shape
        f = self.focal_fraction_of_width * w
        return f, f, (w - 1) / 2 + self.centre_offset_fraction[0] * w, (h - 1) / 2 + self.centre_offset_fraction[1] * h

    def distort(self, x, y):
        """Brown-Conrady distortion of normalised ray coordinates (the forward model of the class docstring).

        Parameters
        ----------
        x : numpy.ndarray
            Normalised undistorted coordinate x (tangent of the ray's angle along the columns).
        y : numpy.ndarray
            Normalised undistorted coordinate y, same shape.

        Returns
        -------
        xd : numpy.ndarray
            Distorted normalised x.
        yd : numpy.ndarray
            Distorted normalised y.
        """
        r2 = x * x + y * y
        radial = 1 + self.k1 * r2 + self.k2 * r2 * r2
        xd = x * radial + 2 * self.p1 * x * y + self.p2 * (r2 + 2 * x * x)
        yd = y * radial + self.p1 * (r2 + 2 * y * y) + 2 * self.p2 * x * y
        return xd, yd

    def project(self, x, y, shape):
        """Pixel coordinates of normalised ray coordinates through the true distortion.

        Parameters
        ----------
        x : array_like
            Normalised undistorted coordinate x.
        y : array_like
            Normalised undistorted coordinate y, same shape.
        shape : tuple of (int, int)
            (rows, cols) of the active area, raw pixels.

        Returns
        -------
        u : numpy.ndarray
            Column, raw pixels (pixel centres at integers).
        v : numpy.ndarray
            Row, raw pixels.
        """
        fx, fy, cx, cy = self.intrinsics(shape)
        xd, yd = self.distort(np.asarray(x, float), np.asarray(y, float))
        return fx * xd + cx, fy * yd + cy

    def ray(self, u, v, shape, iterations: int = 30):
        """Normalised undistorted (x, y) of the ray that lands on pixel (u, v): Newton-free fixed point.

        Parameters
        ----------
        u : array_like
            Column, raw pixels.
        v : array_like
            Row, raw pixels, same shape.
        shape : tuple of (int, int)
            (rows, cols) of the active area.
        iterations : int, optional
            Fixed-point iterations; default 30.

        Returns
        -------
        x : numpy.ndarray
            Normalised undistorted x.
        y : numpy.ndarray
            Normalised undistorted y.
        """
        fx, fy, cx, cy = self.intrinsics(shape)
        xd, yd = (np.asarray(u, float) - cx) / fx, (np.asarray(v, float) - cy) / fy
        x, y = xd.copy(), yd.copy()
        for _ in range(iterations):
            ex, ey = self.distort(x, y)
            x, y = x - (ex - xd), y - (ey - yd)
        return x, y

    def theta_phi_deg(self, u, v, shape):
        """Field angle and azimuth of the rays that land on pixels (u, v).

        Parameters
        ----------
        u : array_like
            Column, raw pixels.
        v : array_like
            Row, raw pixels, same shape.
        shape : tuple of (int, int)
            (rows, cols) of the active area.

        Returns
        -------
        theta_deg : numpy.ndarray
            Angle from the optical axis, degree.
        phi_deg : numpy.ndarray
            Azimuth about the axis, degree in (-180, 180], 0 along the columns.
        """
        x, y = self.ray(u, v, shape)
        return np.degrees(np.arctan(np.hypot(x, y))), np.degrees(np.arctan2(y, x))

    def corner_theta_deg(self, shape) -> float:
        """The largest field angle of the four corner pixels of the active area.

        Parameters
        ----------
        shape : tuple of (int, int)
            (rows, cols) of the active area.

        Returns
        -------
        float
            The field angle, degree.
        """
        h, w = shape
        theta, _ = self.theta_phi_deg(np.array([0.0, w - 1.0, 0.0, w - 1.0]), np.array([0.0, 0.0, h - 1.0, h - 1.0]),
                                      shape)
        return float(theta.max())

    def vignetting(self, theta_deg, band: str, corner_theta_deg: float):
        """Relative illumination: cos^4 (natural) times 1 - m (theta / theta_corner)^4 (mechanical).

        Parameters
        ----------
        theta_deg : array_like
            Field angle, degree.
        band : str
            R, G or B (the mechanical term m at the corner, :attr:`mechanical_at_corner`).
        corner_theta_deg : float
            The field angle of the frame's corner, degree (:meth:`corner_theta_deg`).

        Returns
        -------
        numpy.ndarray
            The relative illumination, dimensionless (1 on the axis).
        """
        t = np.radians(theta_deg)
        return np.cos(t) ** 4 * (1.0 - self.mechanical_at_corner[band] * (np.asarray(theta_deg) / corner_theta_deg) ** 4)


class PinholeRays:
    """The optics' rays in the interface the chessboard renderer uses (``cam2world``, ``shape``)."""

    half_fov_deg = None

    def __init__(self, optics: PinholeOptics, shape: tuple[int, int]):
        self.optics = optics
        self.shape = tuple(shape)
        self._rays = {}     # the renderer asks for the same sub-pixel grid in every pose

    def world2cam(self, points):
        """Pixels (u, v) of camera-frame points (..., 3) through the true distortion.

        Parameters
        ----------
        points : array_like
            Shape (..., 3): points in the camera frame (z along the optical axis, positive in front).

        Returns
        -------
        u : numpy.ndarray
            Column, raw pixels, shape (...).
        v : numpy.ndarray
            Row, raw pixels, shape (...).
        """
        p = np.asarray(points, float)
        return self.optics.project(p[..., 0] / p[..., 2], p[..., 1] / p[..., 2], self.shape)

    def cam2world(self, u, v):
        """Unit ray directions of pixels (u, v) in the camera frame (kept for a pixel grid asked for again).

        Parameters
        ----------
        u : array_like
            Column, raw pixels.
        v : array_like
            Row, raw pixels, same shape.

        Returns
        -------
        numpy.ndarray
            Shape (..., 3): unit vectors, z along the optical axis.
        """
        u, v = np.asarray(u, float), np.asarray(v, float)
        key = (u.shape, float(u.flat[0]), float(v.flat[0]), float(u.flat[-1]), float(v.flat[-1]))
        if key not in self._rays:
            x, y = self.optics.ray(u, v, self.shape)
            d = np.stack([x, y, np.ones_like(x)], axis=-1)
            self._rays[key] = d / np.linalg.norm(d, axis=-1, keepdims=True)
        return self._rays[key]


@dataclass(frozen=True)
class PhoneScale:
    name: str
    active_shape: tuple      # raw rows, cols of the active area (the lens region)
    dark_frames: int
    linearity_frames: int
    geometry_frames: int = 12
    #: the lab's chessboard: inner corners and square size (mm); squares of about 6 band pixels at the
    #: tiny scale, the sampling limit being 2
    board_inner_corners: tuple = (5, 4)
    board_square_mm: float = 30.0


PHONE_SCALES = {
    # tests: 64 x 96 band pixels
    "tiny": PhoneScale("tiny", (128, 192), dark_frames=5, linearity_frames=4),
    "small": PhoneScale("small", (384, 576), dark_frames=10, linearity_frames=4, board_inner_corners=(9, 6),
                        board_square_mm=25.0),
    "medium": PhoneScale("medium", (768, 1152), dark_frames=10, linearity_frames=4, board_inner_corners=(9, 6),
                         board_square_mm=25.0),
}


@dataclass(frozen=True)
class Smartphone:
    sensor: PhoneSensor = field(default_factory=PhoneSensor)
    optics: PinholeOptics = field(default_factory=PinholeOptics)
    #: DN/s at ISO 100 per W sr-1 m-2 nm-1 of effective band radiance, on the optical axis
    #: (the sweeps' sphere gives about 53e3, 54e3 and 33e3 DN/s in R, G and B: G reaches the 12-bit
    #: top between 1/15 and 1/10 s)
    responsivity_dn_s_per_radiance: dict = field(default_factory=lambda: {"R": 0.9e8, "G": 1.4e8, "B": 1.6e8})
    #: the lab's integrating sphere at full power (W sr-1 m-2 nm-1, effective band radiance)
    sphere_band_radiance: dict = field(default_factory=lambda: {"R": 0.74e-3, "G": 0.48e-3, "B": 0.26e-3})
    cfa_pattern: str = "GRBG"
    #: optically black margins outside the ActiveArea (raw rows on top, raw columns on the left)
    black_margin_px: tuple = (8, 16)
    make: str = "SimPhone"
    model: str = "RAW-12"
    serial: str = "SIM-PHONE-01"
    dark_exposures_s: tuple = (1 / 2000, 1 / 250, 1 / 30, 1 / 4, 1.0)
    dark_isos: tuple = (100.0, 200.0, 400.0, 800.0, 1600.0)
    dark_gain_sweep_exposure_s: float = 1 / 30
    linearity_exposures_s: tuple = (1 / 1000, 1 / 500, 1 / 250, 1 / 125, 1 / 60, 1 / 30, 1 / 15, 1 / 10)
    linearity_isos: tuple = (100.0, 200.0, 400.0, 800.0, 1600.0)
    linearity_gain_sweep_exposure_s: float = 1 / 1000
    #: sphere power of the sweeps as fractions of full power
    exposure_source_fraction: float = 0.8
    gain_source_fraction: float = 0.8


def band_index_map(shape: tuple[int, int], pattern: str) -> np.ndarray:
    """Band index (0 R, 1 G, 2 B) of every raw pixel of a mosaic with the 2 x 2 ``pattern`` (e.g. GRBG).

    Parameters
    ----------
    shape : tuple of (int, int)
        (rows, cols) of the mosaic, raw pixels (even).
    pattern : str
        The CFA pattern, four letters of R, G, B in row order.

    Returns
    -------
    numpy.ndarray
        int8, shape ``shape``.
    """
    site = np.array([BANDS.index(ch) for ch in pattern], dtype=np.int8).reshape(2, 2)
    return np.tile(site, (shape[0] // 2, shape[1] // 2))


class PhoneRenderer:
    """Static maps of one simulated phone: pattern, per-pixel light rate per unit radiance."""

    def __init__(self, phone: Smartphone, scale: PhoneScale, seed: int, effects):
        self.phone = phone
        self.shape = tuple(scale.active_shape)
        self.seed = seed
        self.effects = effects
        static = np.random.default_rng([seed, 7919])
        context = {"lens_names": (LENS,), "lens_shape": self.shape,
                   "image_circle_radius_band_px": float(np.hypot(*self.shape) / 4)}
        for effect in effects:
            effect.prepare(static, context)
        self.pattern = draw_static_pattern(static, self.shape, phone.sensor)
        self.band_index = band_index_map(self.shape, phone.cfa_pattern)
        v, u = np.indices(self.shape, dtype=float)
        self.theta_deg, self.phi_deg = phone.optics.theta_phi_deg(u, v, self.shape)
        corner = phone.optics.corner_theta_deg(self.shape)
        k100 = phone.sensor.conversion_gain_dn_per_e_iso100
        rate = np.zeros(self.shape)
        for b, band in enumerate(BANDS):
            sel = self.band_index == b
            rate[sel] = (phone.responsivity_dn_s_per_radiance[band] / k100
                         * phone.optics.vignetting(self.theta_deg[sel], band, corner))
        for effect in effects:
            rate = rate * effect.optics_factor(LENS, "air", self.theta_deg, self.phi_deg, self.band_index)
        self.unit_rate = rate
        # where every raw pixel looks, in the form the default camera's scenes read
        self.geometry = LensGeometry(self.theta_deg, self.phi_deg, np.ones(self.shape, dtype=bool))

    def photo_rate(self, spec: FrameSpec):
        """Photo-electrons per second of every pixel of the active area in the frame ``spec`` describes.

        Parameters
        ----------
        spec : FrameSpec
            The frame: its radiance (none, one per band, or a scene of the pixels' directions).

        Returns
        -------
        numpy.ndarray or float
            e- s-1, the active area's shape: responsivity / K at ISO 100 times the vignetting and the effects'
            optics and sensitivity factors, times the band radiance; the scalar 0.0 for a frame without light.
        """
        if spec.radiance is None:
            return 0.0
        if callable(spec.radiance):     # a scene: per raw pixel effective band radiance
            lbar = spec.radiance(LENS, self.geometry, self.band_index)
        else:
            lbar = np.array([spec.radiance[b] for b in BANDS])[self.band_index]
        rate = self.unit_rate * lbar
        for effect in self.effects:
            rate = rate * effect.sensitivity_map(LENS, self.shape)
        return rate

    def render(self, index: int, experiment_id: int, spec: FrameSpec) -> tuple[np.ndarray, tuple]:
        """The full raw frame (optically black margins and the active area) and its ActiveArea.

        The masked pixels have the same amplifier and black level, their own read noise, no light and no hot
        pixels; they collect the sensor's median dark current.

        Parameters
        ----------
        index : int
            The frame's index in its experiment.
        experiment_id : int
            The experiment's number (1-based, acquisition order).
        spec : FrameSpec
            The frame: exposure (s), ISO, light, temperature.

        Returns
        -------
        frame : numpy.ndarray
            uint16, shape (rows + top margin, cols + left margin): the raw values, DN.
        active_area : tuple of int
            (top, left, bottom, right) of the active area in the frame, raw pixels (the DNG ActiveArea tag).
        """
        rng = np.random.default_rng([self.seed, experiment_id, index])
        sensor = self.phone.sensor
        offset = sum(e.frame_offset_dn(rng) for e in self.effects)
        active = expose(rng, lens=LENS, photo_rate_e_per_s=self.photo_rate(spec), exposure_s=spec.exposure_s,
                        iso=spec.iso, sensor=sensor, pattern=self.pattern, effects=self.effects,
                        frame_offset_dn=offset, shape=self.shape, temperature_c=spec.temperature_c)
        top, left = self.phone.black_margin_px
        full_shape = (self.shape[0] + top, self.shape[1] + left)
        # masked pixels: the same amplifier and black level, their own read noise, no light and no
        # hot pixels; they collect the mean dark current of the sensor
        t_true, gain_factor = true_exposure_and_gain(self.effects, spec.exposure_s, spec.iso)
        k = sensor.conversion_gain(spec.iso) * gain_factor
        dark_e = sum(float(np.median(np.broadcast_to(e.dark_rate_e_per_s(LENS, self.shape), self.shape)))
                     for e in self.effects) * spec.exposure_s
        ob = (sensor.bias_dn + offset + k * rng.poisson(dark_e, full_shape)
              + k * sensor.read_noise_e * rng.standard_normal(full_shape))
        frame = np.clip(np.rint(ob), 0, sensor.adc_max_dn).astype(np.uint16)
        frame[top:, left:] = active
        return frame, (top, left, full_shape[0], full_shape[1])


def _dark_plan(phone: Smartphone, n: int) -> list[FrameSpec]:
    settings = [(phone.dark_isos[0], t) for t in phone.dark_exposures_s]
    settings += [(iso, phone.dark_gain_sweep_exposure_s) for iso in phone.dark_isos
                 if (iso, phone.dark_gain_sweep_exposure_s) not in settings]
    return [FrameSpec("both", "dark", iso, t) for iso, t in settings for _ in range(n)]


def _linearity_plan(phone: Smartphone, n: int) -> tuple[list[FrameSpec], dict]:
    sphere = phone.sphere_band_radiance
    exposure_source = {b: phone.exposure_source_fraction * sphere[b] for b in BANDS}
    gain_source = {b: phone.gain_source_fraction * sphere[b] for b in BANDS}
    frames = [FrameSpec(LENS, "signal", phone.linearity_isos[0], t, {"sweep": "exposure"}, exposure_source)
              for t in phone.linearity_exposures_s for _ in range(n)]
    frames += [FrameSpec(LENS, "signal", iso, phone.linearity_gain_sweep_exposure_s, {"sweep": "gain"}, gain_source)
               for iso in phone.linearity_isos for _ in range(n)]
    return frames, {"exposure_source_band_radiance": exposure_source, "gain_source_band_radiance": gain_source}


class BoardScene:
    """A lit chessboard in one pose: per raw pixel the reflectance times the white board's band radiance."""

    def __init__(self, rays: PinholeRays, board: Board, rvec, tvec, white_radiance: dict):
        self.reflectance, _ = render_chessboard(rays, board, rvec, tvec, supersample=3, background=0.3)
        self.white = np.array([white_radiance[b] for b in BANDS])

    def __call__(self, lens, geometry, band_index):
        return self.white[band_index] * self.reflectance


def _geometry_plan(phone: Smartphone, scale: PhoneScale, rng: np.random.Generator) -> tuple[list[FrameSpec], dict]:
    """Board poses a lab would take: facing the camera within 35 degrees, its centre anywhere in the
    central 60 % of the frame, at the distance that makes it about half the frame wide."""
    shape = tuple(scale.active_shape)
    board = Board(*scale.board_inner_corners, scale.board_square_mm)
    fx = phone.optics.intrinsics(shape)[0]
    width_mm = (board.nx + 1) * board.square_mm
    # the white board at the linearity sweep's sphere power; 1/30 s puts white G near 1600 DN
    white = {b: phone.exposure_source_fraction * phone.sphere_band_radiance[b] for b in BANDS}
    frames, poses = [], []
    rays = PinholeRays(phone.optics, shape)
    for _ in range(scale.geometry_frames):
        z = width_mm * fx / (rng.uniform(0.4, 0.6) * shape[1])
        x, y = phone.optics.ray(rng.uniform(0.2, 0.8) * shape[1], rng.uniform(0.2, 0.8) * shape[0], shape)
        axis = rng.normal(size=3)
        axis[2] *= 0.3                   # mostly tilt, a little roll
        rvec = axis / np.linalg.norm(axis) * np.radians(rng.uniform(0, 35))
        tvec = np.array([float(x) * z, float(y) * z, z])
        frames.append(FrameSpec(LENS, "signal", 100.0, 1 / 30, {"medium": "air"},
                                BoardScene(rays, board, rvec, tvec, white)))
        poses.append({"rvec": rvec.tolist(), "tvec_mm": tvec.tolist()})
    return frames, {"poses": poses, "board": {"inner_corners": list(scale.board_inner_corners),
                                              "square_mm": scale.board_square_mm}}


#: port angles of the roll-off experiment per azimuth plane: as far as the tiny frame's half width
#: (about 32 degrees) and half height (about 23 degrees) reach with the port inside
ROLLOFF_ANGLES_DEG = {0.0: np.arange(-30.0, 30.0 + 1e-9, 5.0), 90.0: np.arange(-20.0, 20.0 + 1e-9, 5.0)}
ROLLOFF_PORT_RADIUS_DEG = 2.0
ROLLOFF_EXPOSURE_S = 1 / 60
ROLLOFF_FRAMES_PER_SETTING = 2
ROLLOFF_DARK_FRAMES = 6


class PortMask:
    """The sphere port, a uniform disc of band radiance around a direction, per raw pixel."""

    def __init__(self, renderer: PhoneRenderer, radiance: dict, theta_deg: float, phi_deg: float, radius_deg: float):
        t, p = np.radians(renderer.theta_deg), np.radians(renderer.phi_deg)
        t0, p0 = np.radians(theta_deg), np.radians(phi_deg)
        cos_d = np.sin(t) * np.sin(t0) * np.cos(p - p0) + np.cos(t) * np.cos(t0)
        self.inside = cos_d >= np.cos(np.radians(radius_deg))
        self.radiance = np.array([radiance[b] for b in BANDS])

    def __call__(self, lens, geometry, band_index):
        return np.where(self.inside, self.radiance[band_index], 0.0)


def _rolloff_plan(phone: Smartphone, renderer: PhoneRenderer) -> tuple[list[FrameSpec], dict]:
    """The camera turned in front of the port: angle_deg >= 0 puts it at phi = azimuth, < 0 at azimuth + 180."""
    frames = [FrameSpec("both", "dark", 100.0, ROLLOFF_EXPOSURE_S, {"medium": "air", "azimuth_deg": "",
                                                                     "angle_deg": ""}) for _ in range(ROLLOFF_DARK_FRAMES)]
    for az, angles in ROLLOFF_ANGLES_DEG.items():
        for angle in angles:
            phi = az if angle >= 0 else az + 180.0
            scene = PortMask(renderer, phone.sphere_band_radiance, abs(float(angle)), phi, ROLLOFF_PORT_RADIUS_DEG)
            frames += [FrameSpec(LENS, "signal", 100.0, ROLLOFF_EXPOSURE_S,
                                 {"medium": "air", "azimuth_deg": az, "angle_deg": float(angle)}, scene)
                       for _ in range(ROLLOFF_FRAMES_PER_SETTING)]
    truth = {"vignetting": "cos(theta)^4 * (1 - mechanical_at_corner[band] * (theta / corner_theta_deg)^4)",
             "mechanical_at_corner": dict(phone.optics.mechanical_at_corner),
             "corner_theta_deg": phone.optics.corner_theta_deg(renderer.shape),
             "port_radius_deg": ROLLOFF_PORT_RADIUS_DEG}
    return frames, truth


#: the phone's absolute-calibration exposure: the default camera's 0.1 s would clip the 12-bit range
PHONE_ABSOLUTE_EXPOSURE_S = 1 / 60


def _default_lab_plan(name: str, phone: Smartphone, seed: int, index: int):
    """The default camera's planner of experiment ``name`` run for this camera (one lens, its radiometry)."""
    from types import SimpleNamespace

    from pipeline.simulate import absolute, spectral  # noqa: F401  (register the planners)
    from pipeline.simulate.lab_errors import no_lab_errors

    # the phone keeps its own smooth response, not the default camera's measured one
    camera = SimpleNamespace(lens_names=(LENS,), sensor=phone.sensor, spectral_response=spectral.two_gaussian_response,
                             radiometry=SimpleNamespace(
        responsivity_dn_s_per_radiance=dict(phone.responsivity_dn_s_per_radiance),
        sphere_band_radiance=dict(phone.sphere_band_radiance)))
    ctx = SimContext(camera=camera, scale=None, seed=seed, rng=np.random.default_rng([seed, 104729, index]),
                     lab_errors=no_lab_errors())
    plan = PLANNERS[name](ctx)
    if name == "absolute":
        for spec in plan.frames:
            spec.exposure_s = PHONE_ABSOLUTE_EXPOSURE_S
        plan.truth["exposure_s"] = PHONE_ABSOLUTE_EXPOSURE_S
    return plan.frames, plan.truth, plan.sidecars


def band_intrinsics(phone: Smartphone, shape: tuple[int, int]) -> dict:
    """True intrinsics of each band image (band pixel (i, j) of a site at raw (2i + a, 2j + b)).

    Parameters
    ----------
    phone : Smartphone
        The phone (its optics and CFA pattern).
    shape : tuple of (int, int)
        (rows, cols) of the active area, raw pixels.

    Returns
    -------
    dict[str, dict[str, float]]
        Band -> ``fx``, ``fy``, ``cx``, ``cy`` in band pixels (G: the mean of its two sites).
    """
    fx, fy, cx, cy = phone.optics.intrinsics(shape)
    out = {}
    for band in BANDS:
        sites = [(k // 2, k % 2) for k, ch in enumerate(phone.cfa_pattern) if ch == band]
        a = float(np.mean([r for r, _ in sites]))
        b = float(np.mean([c for _, c in sites]))
        out[band] = {"fx": fx / 2, "fy": fy / 2, "cx": (cx - b) / 2, "cy": (cy - a) / 2}
    return out


def simulate_smartphone_dataset(out: str | Path, scale: str = "tiny", seed: int = 0,
                                effects: list[tuple[str, dict]] = (), experiments=PHONE_EXPERIMENTS,
                                phone: Smartphone | None = None) -> Path:
    """Simulate the smartphone's calibration experiments into ``out`` (which must not exist yet).

    The truth goes beside it (:func:`pipeline.simulate.dataset.truth_dir_for`); both are written to hidden
    partial folders and renamed at the end.

    Parameters
    ----------
    out : str or pathlib.Path
        The dataset folder to write.
    scale : str, optional
        A name of :data:`PHONE_SCALES` (tiny, small, medium); default ``tiny``.
    seed : int, optional
        Seed of every random draw; default 0.
    effects : list of tuple of (str, dict), optional
        Effects injected into the frames: (name in the effect catalogue, its parameters); default none.
    experiments : sequence of str, optional
        The experiments to write, in acquisition order; default :data:`PHONE_EXPERIMENTS`.
    phone : Smartphone, optional
        The camera; default ``Smartphone()``.

    Returns
    -------
    pathlib.Path
        ``out``: dataset.yaml (one rectilinear lens region), each experiment's frames.csv and DNG frames,
        sidecars, and MD5SUMS.

    Raises
    ------
    InputError
        For an unknown scale or experiment, or when ``out`` or its truth folder exists.
    """
    from pipeline.simulate.dataset import truth_dir_for  # noqa: PLC0415 (dataset imports the planners)

    out = Path(out)
    truth_dir = truth_dir_for(out)
    if scale not in PHONE_SCALES:
        raise InputError(None, f"unknown smartphone scale '{scale}'; choose one of {', '.join(PHONE_SCALES)}")
    unknown = [e for e in experiments if e not in PHONE_EXPERIMENTS]
    if unknown:
        raise InputError(None, f"the smartphone simulator does not write {', '.join(unknown)} yet; "
                               f"it writes {', '.join(PHONE_EXPERIMENTS)}")
    for path in (out, truth_dir):
        if path.exists():
            raise InputError(path, "already exists; the simulator never overwrites a folder (remove it or choose --out)")
    sc = PHONE_SCALES[scale]
    phone = phone or Smartphone()
    effect_objs = [get_effect(name, **params) for name, params in effects]
    renderer = PhoneRenderer(phone, sc, seed, effect_objs)
    tmp, tmp_truth = partial_folders(out, truth_dir)
    plans = {}
    if "dark" in experiments:
        plans["dark"] = (_dark_plan(phone, sc.dark_frames), {})
    if "linearity" in experiments:
        plans["linearity"] = _linearity_plan(phone, sc.linearity_frames)
    if "geometry" in experiments:
        plans["geometry"] = _geometry_plan(phone, sc, np.random.default_rng([seed, 104729]))
    if "rolloff" in experiments:
        plans["rolloff"] = _rolloff_plan(phone, renderer)
    for k, name in enumerate(("spectral", "absolute")):
        if name in experiments:
            plans[name] = _default_lab_plan(name, phone, seed, k)
    clock = START_TIME
    for exp_id, exp in enumerate(experiments):
        frames = plans[exp][0]
        (tmp / exp / "raw").mkdir(parents=True)
        rows = []
        for i, spec in enumerate(frames):
            spec.file = f"raw/PXL_{clock:%Y%m%d_%H%M%S}_{i:05d}.dng"
            raw, active_area = renderer.render(i, exp_id + 1, spec)
            write_dng(tmp / exp / spec.file, raw, exposure_s=spec.exposure_s, iso=spec.iso, time=clock,
                      black_level=round(phone.sensor.bias_dn), white_level=phone.sensor.adc_max_dn,
                      cfa_pattern=phone.cfa_pattern, make=phone.make, model=phone.model, serial=phone.serial,
                      active_area=active_area)
            rows.append({"file": spec.file, "lens": spec.lens, "kind": spec.kind, **spec.extra})
            clock += timedelta(seconds=spec.exposure_s + FRAME_INTERVAL_S)
        pd.DataFrame(rows).to_csv(tmp / exp / "frames.csv", index=False)
        for rel, text in (plans[exp][2] if len(plans[exp]) > 2 else {}).items():
            (tmp / exp / rel).write_text(text)
    h, w = sc.active_shape
    meta = {
        "layout": 1,
        "camera": {"make": phone.make, "model": phone.model, "serial": phone.serial},
        "lenses": {LENS: {"rows": [0, h], "cols": [0, w], "projection": "rectilinear"}},
        "chessboard": {"inner_corners": list(sc.board_inner_corners), "square_mm": {"air": sc.board_square_mm}},
        "description": f"simulated smartphone dataset, scale {sc.name}, seed {seed}",
    }
    (tmp / "dataset.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    write_md5sums(tmp)
    _write_truth(tmp_truth, phone, sc, seed, effect_objs, experiments, {e: p[1] for e, p in plans.items() if p[1]})
    tmp.rename(out)
    tmp_truth.rename(truth_dir)
    return out


def _write_truth(folder: Path, phone: Smartphone, scale: PhoneScale, seed: int, effects, experiments,
                 experiment_truth: dict) -> None:
    s = phone.sensor
    k100 = s.conversion_gain_dn_per_e_iso100
    fx, fy, cx, cy = phone.optics.intrinsics(scale.active_shape)
    truth = {
        "pipeline_version": __version__,
        "camera_kind": "smartphone",
        "scale": asdict(scale),
        "seed": seed,
        "experiments": list(experiments),
        "camera": {"sensor": asdict(s), "optics": asdict(phone.optics), "cfa_pattern": phone.cfa_pattern,
                   "make": phone.make, "model": phone.model, "serial": phone.serial,
                   "responsivity_dn_s_per_radiance": phone.responsivity_dn_s_per_radiance,
                   "sphere_band_radiance": phone.sphere_band_radiance},
        "effects": {e.name: e.truth() for e in effects},
        "experiments_truth": experiment_truth,
        "derived": {
            "bias_dn": s.bias_dn,
            "conversion_gain_dn_per_e_iso100": k100,
            "gain_e_per_dn_iso100": 1.0 / k100,
            "read_noise_e": s.read_noise_e,
            "read_noise_dn_iso100": float(np.sqrt((k100 * s.read_noise_e) ** 2 + 1 / 12)),
            # the gain table against ISO / 100: the factors the iso_gain effect fits
            "iso_gain_factors": {str(int(iso)): float(k / (k100 * iso / 100.0)) for iso, k in s.gain_table},
            "saturation_dn": float(s.adc_max_dn - s.bias_dn),
            # raw-pixel intrinsics of the active area (pixel centres at integers)
            "intrinsics_raw_px": {"fx": fx, "fy": fy, "cx": cx, "cy": cy},
            "distortion": {"k1": phone.optics.k1, "k2": phone.optics.k2, "p1": phone.optics.p1, "p2": phone.optics.p2},
            "band_intrinsics_px": band_intrinsics(phone, scale.active_shape),
        },
    }
    if any(e.name == "dark_current" for e in effects):
        dc = next(e for e in effects if e.name == "dark_current")
        truth["derived"]["dark_current_dn_per_s_iso100"] = dc.params["rate_e_per_s"] * k100
    (folder / "truth.yaml").write_text(yaml.safe_dump(yaml_plain(truth), sort_keys=False))

