"""Turn a FrameSpec into a raw dual-fisheye frame through the camera's true physics.

Light: per raw pixel, photo-electrons per second =
    responsivity(band) / K100 * L_band(pixel) * g_band(theta) [* effects' optics factors]
    * light factor (e.g. 1/I in water),

then any stray-light spreading (in the optics, before the light reaches the sensor), then the
pixel's sensitivity (flat field: it multiplies all the light that lands on the pixel, the spread
part too), then :func:`pipeline.simulate.sensor.expose` (Larouche et al. 2024, Eqs. 1 and 4).
"""

from __future__ import annotations

import numpy as np

from pipeline.io.bands import BANDS
from pipeline.geometry.maps import theta_phi_maps
from pipeline.radiometry.rolloff import evaluate_rolloff
from pipeline.simulate.camera import Camera
from pipeline.simulate.geometry import true_raw_models
from pipeline.simulate.lens import HALF_FOV_DEG, default_model, default_rolloff
from pipeline.simulate.plan import FrameSpec, LensGeometry
from pipeline.simulate.sensor import draw_static_pattern, expose


def lens_geometry(lens: str, medium: str, lens_px: int) -> LensGeometry:
    """True viewing directions of the raw pixels of one lens region.

    Each raw site is seen through the optics of its band (:func:`pipeline.simulate.geometry.true_raw_models`: the
    lens's lateral chromatic aberration, a centre offset and magnification of R and B), the same optics the
    chessboards of the geometry experiment are rendered through, so that every experiment sees one camera.

    Parameters
    ----------
    lens : str
        The lens (``close`` or ``far``).
    medium : str
        ``air`` or ``water``.
    lens_px : int
        Side of the square lens region, raw pixels (even).

    Returns
    -------
    LensGeometry
        Per raw pixel, shape (lens_px, lens_px): zenith angle theta and azimuth phi, degree (theta 180 where the
        model gives no direction), and whether it lies inside the image circle (theta <= the half field of view
        in that medium).
    """
    shape = (lens_px, lens_px)
    band_index = band_index_map(lens_px)
    theta = np.empty(shape)
    phi = np.empty(shape)
    for b, model in enumerate(true_raw_models(lens, medium, lens_px)[band] for band in BANDS):
        t, f = theta_phi_maps(model, shape)
        sites = band_index == b
        theta[sites], phi[sites] = t[sites], f[sites]
    theta = np.where(np.isfinite(theta), theta, 180.0)
    return LensGeometry(theta, phi, theta <= HALF_FOV_DEG[medium])


def band_index_map(lens_px: int) -> np.ndarray:
    """Band index (0 R, 1 G, 2 B) of every raw pixel of an RGGB lens region.

    Parameters
    ----------
    lens_px : int
        Side of the square lens region, raw pixels (even).

    Returns
    -------
    numpy.ndarray
        int8, shape (lens_px, lens_px).
    """
    site = np.array([[0, 1], [1, 2]], dtype=np.int8)
    return np.tile(site, (lens_px // 2, lens_px // 2))


class Renderer:
    """Holds the static per-lens maps of one simulated camera."""

    def __init__(self, camera: Camera, lens_px: int, seed: int, effects):
        self.camera = camera
        self.n = lens_px
        self.shape = (lens_px, lens_px)
        self.seed = seed
        self.effects = effects
        static = np.random.default_rng([seed, 7919])
        context = {"lens_names": camera.lens_names, "lens_shape": self.shape,
                   # image-circle radius of the default optics (close lens, air) in band pixels
                   "image_circle_radius_band_px": default_model(
                       "close", "air", (lens_px // 2, lens_px // 2)).image_circle_radius()}
        for effect in effects:
            effect.prepare(static, context)
        self.patterns = {lens: draw_static_pattern(static, self.shape, camera.sensor)
                         for lens in camera.lens_names}
        self.band_index = band_index_map(lens_px)
        k100 = camera.sensor.conversion_gain_dn_per_e_iso100
        self.resp_e = np.array([camera.radiometry.responsivity_dn_s_per_radiance[b] / k100 for b in BANDS])
        self._geometry = {}
        self._unit_rate = {}

    def geometry(self, lens: str, medium: str) -> LensGeometry:
        """True viewing directions of the raw pixels (default model at raw resolution), computed once per lens and medium.

        Parameters
        ----------
        lens : str
            The lens.
        medium : str
            ``air`` or ``water``.

        Returns
        -------
        LensGeometry
            As :func:`lens_geometry`.
        """
        key = (lens, medium)
        if key not in self._geometry:
            self._geometry[key] = lens_geometry(lens, medium, self.n)
        return self._geometry[key]

    def unit_rate(self, lens: str, medium: str) -> np.ndarray:
        """Photo-electrons per second per unit band radiance, roll-off and optics effects included.

        The pixels' sensitivity is not: :meth:`photo_rate` applies it after any stray-light spreading. Computed once
        per lens and medium.

        Parameters
        ----------
        lens : str
            The lens.
        medium : str
            ``air`` or ``water``.

        Returns
        -------
        numpy.ndarray
            Shape (lens_px, lens_px): e- s-1 per W m-2 sr-1 nm-1 of the site's band radiance (responsivity / K at
            ISO 100 times the roll-off at the pixel's theta and the effects' optics factors); zero outside the image
            circle.
        """
        key = (lens, medium)
        if key not in self._unit_rate:
            geo = self.geometry(lens, medium)
            theta = np.minimum(geo.theta_deg, HALF_FOV_DEG[medium])
            rate = np.zeros(self.shape)
            for b, band in enumerate(BANDS):
                sel = self.band_index == b
                rate[sel] = self.resp_e[b] * evaluate_rolloff(default_rolloff(band, medium, lens), theta[sel])
            for effect in self.effects:
                rate = rate * effect.optics_factor(lens, medium, geo.theta_deg, geo.phi_deg, self.band_index)
            self._unit_rate[key] = rate * geo.lit
        return self._unit_rate[key]

    def photo_rate(self, lens: str, spec: FrameSpec, light_scale: float = 1.0):
        """Photo-electrons per second of every raw pixel of one lens in the frame ``spec`` describes.

        The unit rate times the band radiance the scene sends to each site, the frame's light factor and
        ``light_scale``; then the effects' stray-light spreading, then the pixels' sensitivity (flat field).

        Parameters
        ----------
        lens : str
            The lens.
        spec : FrameSpec
            The frame: its radiance (none, one per band, or a scene of the pixels' directions), medium, light factor
            and the lenses it lights.
        light_scale : float, optional
            Factor on the source's light (the lab's flicker and drift); default 1.

        Returns
        -------
        numpy.ndarray or float
            Shape (lens_px, lens_px), e- s-1; the scalar 0.0 when no light reaches this lens.
        """
        lit = spec.lit if spec.lit is not None else (self.camera.lens_names if spec.lens == "both" else (spec.lens,))
        if spec.radiance is None or lens not in lit:
            return 0.0
        if callable(spec.radiance):
            lbar = spec.radiance(lens, self.geometry(lens, spec.medium), self.band_index)
        else:
            lbar = np.array([spec.radiance[b] for b in BANDS])[self.band_index]
        factor = spec.light_factor(self.band_index) if callable(spec.light_factor) else spec.light_factor
        rate = self.unit_rate(lens, spec.medium) * lbar * factor
        if light_scale != 1.0:
            rate = rate * light_scale
        for effect in self.effects:
            rate = effect.spread_light(rate, lens)
        for effect in self.effects:
            rate = rate * effect.sensitivity_map(lens, self.shape)
        return rate

    def render(self, index: int, experiment_id: int, spec: FrameSpec, light_scale: float = 1.0,
               bias_offset_dn: float = 0.0) -> np.ndarray:
        """One raw frame of the two lenses stacked (the dual-fisheye layout), through :func:`~pipeline.simulate.sensor.expose`.

        The noise is drawn from ``numpy.random.default_rng([seed, experiment_id, index])``, so a frame is the same
        whatever the order it is rendered in.

        Parameters
        ----------
        index : int
            The frame's index in its experiment.
        experiment_id : int
            The experiment's number (1-based, acquisition order).
        spec : FrameSpec
            The frame: exposure (s), ISO, light, medium, temperature (deg C).
        light_scale : float, optional
            Multiplies the source's light; default 1.
        bias_offset_dn : float, optional
            Shifts the black level of the whole frame, DN (the lab's frame-to-frame noise,
            :mod:`pipeline.simulate.lab_noise`); default 0.

        Returns
        -------
        numpy.ndarray
            uint16, shape (2 lens_px, lens_px): the raw CFA frame, DN.
        """
        rng = np.random.default_rng([self.seed, experiment_id, index])
        offset = sum(e.frame_offset_dn(rng) for e in self.effects) + bias_offset_dn
        frame = np.empty((2 * self.n, self.n), dtype=np.uint16)
        for row, lens in enumerate(self.camera.lens_names):
            frame[row * self.n:(row + 1) * self.n] = expose(
                rng, lens=lens, photo_rate_e_per_s=self.photo_rate(lens, spec, light_scale), exposure_s=spec.exposure_s,
                iso=spec.iso, sensor=self.camera.sensor, pattern=self.patterns[lens], effects=self.effects,
                frame_offset_dn=offset, shape=self.shape, temperature_c=spec.temperature_c)
        return frame
