"""Optical effects of the roll-off and immersion experiments (docs/design.md catalogue).

* ``rolloff_azimuth``: decentred or tilted optics. The relative illumination
  gains a term odd in the field direction,
  ``g(theta, phi) = g(theta) * (1 + A (theta / 90 deg) cos(phi - phi0))``.
  Roll-off stage term (level ``setting``): two columns
  ``pred * (theta/90) cos(phi)`` and ``pred * (theta/90) sin(phi)`` with
  coefficients ``A cos(phi0)`` and ``A sin(phi0)``: the even polynomial fitted
  over both azimuth planes mispredicts each plane's two sides as cos(phi - phi0).
* ``immersion_angle``: the immersion factor grows with field angle,
  ``I(theta) = I(0) / (1 - kappa (theta / 60 deg)^4)`` (Wei et al. 2012,
  Section 3.5 and Fig. 5(d): the immersion factor measured against viewing
  direction). Closure that shows it (level ``water`` of the roll-off stage):
  each in-water point against its prediction from the in-air fit and the
  immersion physics, ``g_w(theta_w) = c g_air(theta_a) F(theta_a, theta_w)``
  (the same pixels' field angle in air from the geometry artefact, F the
  outer surface's Fresnel transmissions, radiometry/immersion_rolloff.py),
  with only the scale c fitted. A free even polynomial fitted to the
  in-water points alone absorbs any smooth even factor, so that fit cannot
  show it; the prediction from air has no shape to adjust, and the residuals
  grow with theta. Term: ``-pred * (theta/60)^4``, coefficient kappa. The
  simulator's ``optics_factor`` is the same form; the hidden-effect test
  injects another (tests/effects/test_effects_optics.py).
* ``stray_light``: a fraction ``f`` of the flux is spread by a wide Gaussian
  point-spread function (width a fraction of the image-circle radius; Wei et
  al. 2012, Section 3.4). Roll-off stage term (rows of level ``setting`` with
  ``kind == "halo"``: the mean excess in an annulus just outside the port
  spot): the port pixels' flux (in each band, all pixels above the port
  threshold in any band) convolved with the model kernel, ``halo_column_dn``;
  coefficient f / (1 - f), about f: the measured port pixels have already
  lost the spread fraction.
  Field (level ``frame`` of the match-up table): the far wings of the same
  spread carry the sun's direct beam into the zenith mask. The simulator
  draws them as image-plane power-law wings (``sun_wing_fraction``,
  ``sun_wing_core_deg``, ``sun_wing_index``; :mod:`pipeline.simulate.glare`);
  the pipeline's term is the field stage's covariate, the band's clear-sky
  direct irradiance times whether the sun is seen times an inverse power of
  the solar zenith angle (:mod:`pipeline.radiometry.sun_glare`), one
  coefficient common to the bands: the spread in sr-1 at the reference angle
  (``stray_light_glare_sr``).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.effects.base import Effect, register

#: field angle that scales the azimuthal term (deg)
AZIMUTH_THETA_REF_DEG = 90.0
#: field angle that scales the immersion-angle term (deg)
IMMERSION_THETA_REF_DEG = 60.0
#: power of theta in the immersion-angle term
IMMERSION_POWER = 4


def _pred(table: pd.DataFrame) -> np.ndarray:
    return table["pred_dn"].to_numpy(float) if "pred_dn" in table else table["value_dn"].to_numpy(float)


@register
class RolloffAzimuth(Effect):
    name = "rolloff_azimuth"
    experiments = ("rolloff",)
    truth_defaults = {"amplitude": 0.03, "phi0_deg": 30.0}
    amplitude_name = "rolloff_azimuth_amplitude"
    amplitude_units = "1"

    def optics_factor(self, lens, medium, theta_deg, phi_deg, band_index):
        t = np.minimum(np.asarray(theta_deg, float), 100.0) / AZIMUTH_THETA_REF_DEG
        return 1.0 + self.params["amplitude"] * t * np.cos(np.radians(phi_deg - self.params["phi0_deg"]))

    def columns(self, experiment, level, table):
        if experiment != "rolloff" or level not in ("setting", "water") or "theta_deg" not in table:
            return None
        t = table["theta_deg"].to_numpy(float) / AZIMUTH_THETA_REF_DEG
        phi = np.radians(table["phi_deg"].to_numpy(float))
        p = _pred(table)
        if "kind" in table:
            p = p * (table["kind"].to_numpy() == "spot")
        return np.column_stack([p * t * np.cos(phi), p * t * np.sin(phi)])

    def amplitude(self, experiment, level, table, coef, cov):
        amp = float(np.hypot(coef[0], coef[1]))
        if amp == 0:
            return 0.0, 0.0, 0.0
        j = np.array([coef[0], coef[1]]) / amp
        se = float(np.sqrt(max(j @ cov[:2, :2] @ j, 0.0)))
        return amp, max(amp - 1.96 * se, 0.0), amp + 1.96 * se


def azimuth_from_coefficients(coef, cov) -> tuple[float, float, float, float]:
    """(A, sigma_A, phi0_deg, sigma_phi0_deg) from (A cos phi0, A sin phi0) and their covariance.

    Parameters
    ----------
    coef : array_like
        The two fitted coefficients of :class:`RolloffAzimuth`'s columns, (A cos phi0, A sin phi0)
        (dimensionless); further entries are ignored.
    cov : array_like
        Their covariance; its leading 2 x 2 block is used.

    Returns
    -------
    amplitude : float
        A, the relative amplitude of the azimuthal term at theta = 90 degree (dimensionless).
    sigma_amplitude : float
        Its standard error, by linear propagation (dimensionless).
    phi0_deg : float
        Azimuth phi0 of the brightest side (degree, in (-180, 180]).
    sigma_phi0_deg : float
        Its standard error (degree).
    """
    c, s = float(coef[0]), float(coef[1])
    amp = float(np.hypot(c, s))
    ja = np.array([c, s]) / amp
    jp = np.array([-s, c]) / amp**2
    cov = np.asarray(cov)[:2, :2]
    return (amp, float(np.sqrt(ja @ cov @ ja)), float(np.degrees(np.arctan2(s, c))),
            float(np.degrees(np.sqrt(jp @ cov @ jp))))


@register
class ImmersionAngle(Effect):
    name = "immersion_angle"
    experiments = ("rolloff",)
    truth_defaults = {"kappa": 0.06}
    amplitude_name = "immersion_angle_kappa"
    amplitude_units = "1"

    def optics_factor(self, lens, medium, theta_deg, phi_deg, band_index):
        if medium != "water":
            return 1.0
        u = np.minimum(np.asarray(theta_deg, float), 90.0) / IMMERSION_THETA_REF_DEG
        return 1.0 - self.params["kappa"] * u**IMMERSION_POWER

    def columns(self, experiment, level, table):
        if experiment != "rolloff" or level != "water" or "theta_deg" not in table:
            return None
        u = table["theta_deg"].to_numpy(float) / IMMERSION_THETA_REF_DEG
        return (-_pred(table) * u**IMMERSION_POWER)[:, None]


@register
class StrayLight(Effect):
    name = "stray_light"
    experiments = ("rolloff", "field")
    #: lab: fraction spread; Gaussian PSF width as a fraction of the image-circle radius.
    #: field (the simulator's sun glare, simulate/glare.py): fraction of the sun's flux in power-law
    #: wings, their core (deg) and index p (K ~ d^-p far from the sun); 0 fraction: no glare
    truth_defaults = {"fraction": 0.02, "psf_sigma_fraction": 0.1,
                      "sun_wing_fraction": 0.06, "sun_wing_core_deg": 0.5, "sun_wing_index": 2.5}
    amplitude_name = "stray_light_fraction"
    amplitude_units = "1"

    def sun_glare_wings(self):
        if not self.params.get("sun_wing_fraction"):
            return None
        return {"fraction": float(self.params["sun_wing_fraction"]), "core_deg": float(self.params["sun_wing_core_deg"]),
                "index": float(self.params["sun_wing_index"])}

    def prepare(self, rng, context):
        # the simulator's context gives the image-circle radius of its optics in band pixels
        self.sigma_band_px = self.params["psf_sigma_fraction"] * context["image_circle_radius_band_px"]

    def spread_light(self, photo_rate, lens):
        from scipy.ndimage import gaussian_filter

        rate = np.asarray(photo_rate, dtype=float)
        if rate.ndim != 2:
            return photo_rate
        out = (1.0 - self.params["fraction"]) * rate
        for dy in (0, 1):
            for dx in (0, 1):
                sub = rate[dy::2, dx::2]
                out[dy::2, dx::2] += self.params["fraction"] * gaussian_filter(
                    sub, self.sigma_band_px, mode="constant", truncate=4.0)
        return out

    def columns(self, experiment, level, table):
        """Lab: the halo column (coefficient about f). Field (level ``frame``): the field stage's
        ``sun_glare_covariate`` (the band's clear-sky direct irradiance, the sun seen or not, an
        inverse-square law in the angle from the sun: radiometry/sun_glare.py); one coefficient common to
        the bands, the spread in sr-1 at the reference angle.

        Parameters
        ----------
        experiment : str
            Stage whose observation table this is (``"rolloff"`` or ``"field"``).
        level : str
            Level of the observations (``"setting"`` of the roll-off stage, ``"frame"`` of
            the field stage).
        table : pandas.DataFrame
            The observation table, with ``halo_column_dn`` (lab, DN) or ``sun_glare_covariate``
            (field, camera units sr).

        Returns
        -------
        numpy.ndarray or None
            One column, shape (n_rows, 1); None where silent or where the table lacks the covariate.
        """
        if experiment == "field":
            if level != "frame" or "sun_glare_covariate" not in table:
                return None
            return table["sun_glare_covariate"].to_numpy(float)[:, None]
        if experiment != "rolloff" or level != "setting" or "halo_column_dn" not in table:
            return None
        return table["halo_column_dn"].to_numpy(float)[:, None]

    predicted_from = ("field", "frame")

    def predicted_shift(self, experiment, level, table, coef, anchor):
        """Field scale: the glare the match-up table's coefficient c (sr-1) puts into the mask, as a share of the
        camera radiance, ln(1 + c G) with G the mean glare covariate over the mean camera radiance (sr).

        Parameters
        ----------
        experiment : str
            Stage of the table whose rows are predicted (``"field"``: silent elsewhere).
        level : str
            Level of that table (``"scale"``: silent elsewhere).
        table : pandas.DataFrame
            The field scale closure's table, one row per band and lens, with ``glare_share_sr`` (G, sr).
        coef : numpy.ndarray
            The effect's coefficients fitted on ``anchor``: one, c (sr-1).
        anchor : pandas.DataFrame
            The observation table of :attr:`predicted_from` on which ``coef`` was fitted.

        Returns
        -------
        numpy.ndarray or None
            Shift of ln(camera / reference scale) of each row of ``table`` (dimensionless), shape (n_rows,); None
            when the table lacks the covariates.
        """
        if experiment != "field" or level != "scale" or "glare_share_sr" not in table:
            return None
        return np.log(np.maximum(1.0 + float(coef[0]) * table["glare_share_sr"].to_numpy(float), 1e-6))

    def amplitude_label(self, experiment):
        if experiment == "field":
            return "stray_light_glare_sr", "sr-1"
        return super().amplitude_label(experiment)
