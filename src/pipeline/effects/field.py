"""Effects that only the field match-up reveals (Larouche et al. 2024, Sections 2.9 and 3.8).

* ``clock_offset``: the camera clock runs ahead of UTC (after the declared
  time-zone offset) by ``offset_s`` seconds. The simulator writes the frames'
  DateTimeOriginal with that offset; the field stage fits it by shifting the
  reference series.
* ``spectral_mismatch``: broad camera bands against narrow reference
  channels. The simulator's switch makes the sky spectrum's slope change over
  the hour (a power law in wavelength whose exponent drifts by
  ``exponent_change_per_h``), so that a comparison with the nearest channel
  leaves residuals that follow the scene's in-band slope; the pipeline's model
  term is the comparison with the reference spectrum convolved with the
  band's measured response (no power law).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.effects.base import Effect, register


def band_scale(table: pd.DataFrame) -> np.ndarray:
    """The fitted camera/reference scale of each row's band, pred_dn / x_scale (1 where unknown).

    The base model of the field table is camera = k_b x reference; the
    effects' columns are in the camera's units, so they carry k_b.

    Parameters
    ----------
    table : pandas.DataFrame
        The field match-up table, with ``pred_dn`` (the model's camera prediction, camera units) and
        ``x_scale`` (the reference radiance the scale multiplies).

    Returns
    -------
    numpy.ndarray
        k_b of each row, shape (n_rows,), in camera units per reference unit; 1 where either column is missing,
        x_scale is 0 or the ratio is not finite.
    """
    if "pred_dn" not in table or "x_scale" not in table:
        return np.ones(len(table))
    pred = table["pred_dn"].to_numpy(float)
    x = table["x_scale"].to_numpy(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        k = pred / x
    return np.where(np.isfinite(k) & (x != 0), k, 1.0)


def _profile_excludes_zero(table: pd.DataFrame) -> float | None:
    """The clock profile's offset (s) when the table carries it and its interval excludes 0, else None."""
    cols = ("clock_profile_offset_s", "clock_profile_offset_low_s", "clock_profile_offset_high_s")
    if not all(c in table for c in cols) or not len(table):
        return None
    c, low, high = (float(table[col].iloc[0]) for col in cols)
    if not (np.isfinite(c) and c != 0.0 and ((np.isfinite(low) and low > 0) or (np.isfinite(high) and high < 0))):
        return None
    return c


def _field_frame(experiment: str, level: str, table: pd.DataFrame, needed: tuple[str, ...]) -> bool:
    return experiment == "field" and level == "frame" and all(c in table for c in needed)


@register
class ClockOffset(Effect):
    name = "clock_offset"
    experiments = ("field",)
    #: camera clock minus true time (s), after the time-zone offset of site.yaml
    truth_defaults = {"offset_s": 30.0}
    amplitude_name = "clock_offset_s"
    amplitude_units = "s"
    #: with the effect in the model the field stage fits the offset by shifting the reference series
    corrects_data = True

    def camera_clock_offset_s(self) -> float:
        return float(self.params["offset_s"])

    def columns(self, experiment, level, table):
        """-k_b dref/dt. A camera clock ahead of UTC by c seconds takes the reference at t + c:
        x = ref(t + c) = ref(t) + c dref/dt, while the camera saw k_b ref(t); so
        value = pred + c (-k_b dref/dt) and the coefficient is the offset c in seconds.

        The tangent holds for shifts short against the sky's time scale only. Where the match-up table carries
        the stage's clock profile and its interval excludes 0 (an offset the profile itself finds), the column
        is the secant to the profile's offset c*, k_b (ref(t - c*) - ref(t)) / c* (``ref_at_clock_profile``),
        with the same coefficient, exact at c = c*: a signature valid at the amplitude it is tested at (a
        120 s offset, against which the tangent points the other way). Rows without the reference at c*
        keep the tangent.

        Parameters
        ----------
        experiment : str
            Stage whose observation table this is (``"field"``: silent elsewhere).
        level : str
            Level of the observations (``"frame"``: silent elsewhere).
        table : pandas.DataFrame
            The observation table, one row per match-up, with ``dref_dt`` (the reference's time
            derivative, reference units s-1).

        Returns
        -------
        numpy.ndarray or None
            One column, shape (n_rows, 1), in the camera's units per second; None where silent.
        """
        if not _field_frame(experiment, level, table, ("dref_dt",)):
            return None
        k = band_scale(table)
        tangent = -table["dref_dt"].to_numpy(float) * k
        found = _profile_excludes_zero(table)
        if found is None or "ref_at_clock_profile" not in table:
            return tangent[:, None]
        secant = k * (table["ref_at_clock_profile"].to_numpy(float) - table["x_scale"].to_numpy(float)) / found
        return np.where(np.isfinite(secant), secant, tangent)[:, None]

    def amplitude(self, experiment, level, table, coef, cov):
        """The offset c (s, camera minus UTC, as the coefficient of :meth:`columns`) and its 95 % interval.

        The signature is nonlinear in c: the linearised column ref(t + c) = ref(t) + c dref/dt holds only for
        shifts short against the time over which the sky's slope changes (drifting clouds: tens of seconds),
        so its coefficient is no estimate of a longer offset (a reference shifted by 41 s read -11 s, -15 to
        -7; 120 s, -16 s with the wrong sign), whereas the field stage, given the effect, fits the shift
        itself. Where the match-up table carries the stage's profile fit (``clock_profile_offset_s`` and the
        bounds of its chi-square profile at ``field.confidence_level``, ``clock_profile_offset_low_s`` and
        ``_high_s``: the same fit the stage applies with the effect in the model, recorded without it) that
        is the amplitude; where the profile gave no bound, +/-1.96 of its standard error
        (``clock_profile_offset_se_s``, from the curvature); the linearised coefficient otherwise.

        Parameters
        ----------
        experiment : str
            Stage whose table the column was fitted on.
        level : str
            Level of that table within the stage.
        table : pandas.DataFrame
            The match-up table the column was fitted on.
        coef : numpy.ndarray
            Fitted coefficient of the column, shape (1,) (s).
        cov : numpy.ndarray
            Its covariance, shape (1, 1) (s2).

        Returns
        -------
        amplitude : float
            The clock offset c, camera minus UTC (s).
        low : float
            Lower end of its 95 % interval (s).
        high : float
            Upper end of its 95 % interval (s).
        """
        if experiment == "field" and "clock_profile_offset_s" in table and len(table):
            c = float(table["clock_profile_offset_s"].iloc[0])
            se = float(table["clock_profile_offset_se_s"].iloc[0]) if "clock_profile_offset_se_s" in table \
                else float("nan")
            low = float(table["clock_profile_offset_low_s"].iloc[0]) if "clock_profile_offset_low_s" in table \
                else float("nan")
            high = float(table["clock_profile_offset_high_s"].iloc[0]) if "clock_profile_offset_high_s" in table \
                else float("nan")
            if np.isfinite(c) and np.isfinite(low) and np.isfinite(high):
                return c, min(low, c), max(high, c)
            if np.isfinite(c) and np.isfinite(se):
                return c, c - 1.96 * se, c + 1.96 * se
        return super().amplitude(experiment, level, table, coef, cov)



@register
class SpectralMismatch(Effect):
    name = "spectral_mismatch"
    experiments = ("field",)
    #: change over one hour of the exponent a of a factor (lambda / 550 nm)^(-a) on the sky spectrum
    truth_defaults = {"exponent_change_per_h": 1.5}
    amplitude_name = "spectral_mismatch_factor"
    amplitude_units = "1"
    #: with the effect in the model the field stage predicts with the band-convolved reference
    corrects_data = True

    def columns(self, experiment, level, table):
        """k_b (ref_convolved - ref_nearest): the camera follows the band-convolved reference, so
        against the nearest channel the coefficient is 1 (0 when the in-band slope does not matter).

        Parameters
        ----------
        experiment : str
            Stage whose observation table this is (``"field"``: silent elsewhere).
        level : str
            Level of the observations (``"frame"``: silent elsewhere).
        table : pandas.DataFrame
            The observation table, one row per match-up, with ``ref_convolved`` (the reference
            spectrum convolved with the band's response) and ``ref_nearest`` (the nearest reference channel), both in
            reference units.

        Returns
        -------
        numpy.ndarray or None
            One column, shape (n_rows, 1), in the camera's units; None where silent.
        """
        if not _field_frame(experiment, level, table, ("ref_convolved", "ref_nearest")):
            return None
        diff = table["ref_convolved"].to_numpy(float) - table["ref_nearest"].to_numpy(float)
        return (diff * band_scale(table))[:, None]

    predicted_from = ("field", "frame")

    def predicted_shift(self, experiment, level, table, coef, anchor):
        """Field scale against the nearest channel: ln(1 + c (m - 1)), m the band-convolved over the nearest
        channel's reference over the match-ups, c the match-up table's coefficient (1 when the camera follows
        the band-convolved reference).

        Parameters
        ----------
        experiment : str
            Stage of the table whose rows are predicted (``"field"``: silent elsewhere).
        level : str
            Level of that table (``"scale"``: silent elsewhere).
        table : pandas.DataFrame
            The field scale closure's table, one row per band and lens, with ``mismatch_factor`` (m,
            dimensionless).
        coef : numpy.ndarray
            The effect's coefficients fitted on ``anchor``: one, c (dimensionless).
        anchor : pandas.DataFrame
            The observation table of :attr:`predicted_from` on which ``coef`` was fitted.

        Returns
        -------
        numpy.ndarray or None
            Shift of ln(camera / reference scale) of each row of ``table`` (dimensionless), shape (n_rows,); None
            when the table lacks the covariates.
        """
        if experiment != "field" or level != "scale" or "mismatch_factor" not in table:
            return None
        m = table["mismatch_factor"].to_numpy(float)
        return np.log(np.maximum(1.0 + float(coef[0]) * (m - 1.0), 1e-6))


    def sky_spectral_exponent(self, hours_since_start: float) -> float:
        return float(self.params["exponent_change_per_h"]) * float(hours_since_start)
