"""Built-in effects of the dark and linearity experiments.

Each class holds the simulator's physics and the pipeline's linearised term
for one catalogue entry (docs/design.md). Coefficients of :meth:`columns` are the
physical parameters themselves, so a fitted coefficient compares directly
with the simulator's truth.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.effects.base import Effect, register

#: the smallest factor a predicted shift takes the logarithm of (a parameter far outside its physical range)
_TINY = 1e-6


def _field_scale(experiment: str, level: str, table: pd.DataFrame, needed: tuple[str, ...]) -> bool:
    """True on the field scale closure's table when it carries the covariates ``needed`` (the field stage
    writes them only for the effects the model lacks)."""
    return experiment == "field" and level == "scale" and all(c in table for c in needed)


#: ISO settings a camera offers (ISO 100 doubling to 3200): the per-ISO draws of
#: ``iso_gain`` are made for these, in this order, so that they do not depend on
#: which experiments are simulated.
STANDARD_ISOS = (100.0, 200.0, 400.0, 800.0, 1600.0, 3200.0)


@register
class DarkCurrent(Effect):
    """Thermal signal: ``rate_e_per_s`` electrons per second in every pixel.

    Model term (dark stage, one value per setting): ``D * gain * t`` with D in
    DN/s at ISO 100 (equal to rate_e_per_s times the ISO 100 conversion gain).
    """

    name = "dark_current"
    experiments = ("dark",)
    truth_defaults = {"rate_e_per_s": 0.9}
    amplitude_name = "dark_current_dn_per_s_iso100"
    amplitude_units = "DN s-1"

    def dark_rate_e_per_s(self, lens, shape):
        return float(self.params["rate_e_per_s"])

    def columns(self, experiment, level, table):
        if experiment != "dark" or level != "setting":
            return None
        return (table["gain"] * table["exposure_s"]).to_numpy()[:, None]

    predicted_from = ("dark", "setting")

    def predicted_shift(self, experiment, level, table, coef, anchor):
        """Field scale: the dark signal D x ISO/100 x t that a dark model without it leaves in the field
        frames' mask, over their signal: ln(1 + D (ISO/100 t / S)). The absolute experiment subtracts its own dark
        frames (docs/dataset-format.md), which hold the dark current, so it adds no term of its own.

        Parameters
        ----------
        experiment : str
            Stage of the table whose rows are predicted (``"field"``: silent elsewhere).
        level : str
            Level of that table (``"scale"``: silent elsewhere).
        table : pandas.DataFrame
            The field scale closure's table, one row per band and lens, with ``field_dark_s_per_dn``
            (ISO/100 t / S of the field frames, s DN-1).
        coef : numpy.ndarray
            The effect's coefficients fitted on ``anchor``: one, the dark-current rate D (DN s-1 at
            ISO 100).
        anchor : pandas.DataFrame
            The observation table of :attr:`predicted_from` on which ``coef`` was fitted.

        Returns
        -------
        numpy.ndarray or None
            Shift of ln(camera / reference scale) of each row of ``table`` (dimensionless), shape (n_rows,); None
            when the table lacks the covariates.
        """
        if not _field_scale(experiment, level, table, ("field_dark_s_per_dn",)):
            return None
        return np.log(np.maximum(1.0 + float(coef[0]) * table["field_dark_s_per_dn"].to_numpy(float), _TINY))


@register
class HotPixels(Effect):
    """Sparse pixels with a large dark current (log-normal rates).

    The dark stage flags pixels whose dark signal is an outlier in every one of
    the longest exposures; the model term is the excess those pixels add to the
    mean dark level (covariate ``hot_excess_dn``), whose coefficient is 1 when
    the sparse pixels explain the residuals.
    """

    name = "hot_pixels"
    experiments = ("dark",)
    truth_defaults = {"fraction": 5e-4, "median_rate_e_per_s": 400.0, "log_sigma": 0.6}
    amplitude_name = "hot_pixel_fraction"
    amplitude_units = "1"
    corrects_data = True

    def prepare(self, rng, context):
        self.maps = {}
        for lens in context["lens_names"]:
            shape = context["lens_shape"]
            hot = rng.random(shape) < self.params["fraction"]
            rates = np.zeros(shape, dtype=np.float32)
            n = int(hot.sum())
            rates[hot] = self.params["median_rate_e_per_s"] * np.exp(
                self.params["log_sigma"] * rng.standard_normal(n))
            self.maps[lens] = rates

    def dark_rate_e_per_s(self, lens, shape):
        return self.maps[lens]

    def truth(self):
        out = super().truth()
        out["count_raw_pixels"] = {lens: int((m > 0).sum()) for lens, m in self.maps.items()}
        return out

    def columns(self, experiment, level, table):
        if experiment != "dark" or level != "setting" or "hot_excess_dn" not in table:
            return None
        return table["hot_excess_dn"].to_numpy()[:, None]

    def amplitude(self, experiment, level, table, coef, cov):
        n_hot = float(table["n_hot"].iloc[0])
        n_pix = float(table["n_pixels"].iloc[0])
        half = 1.96 * np.sqrt(max(n_hot, 1.0))
        return n_hot / n_pix, max(n_hot - half, 0.0) / n_pix, (n_hot + half) / n_pix


@register
class ShutterOffset(Effect):
    """True exposure = nominal + ``offset_s``.

    In the light field's bracket-consistency table (``lightfield``, ``bracket``): ``1 / t_l - 1 / t_s`` of the
    exposure pair, coefficient the offset in seconds.

    Linearity model term for the exposure sweep: ``rate * gain * offset_s``
    where ``rate`` (DN/s at ISO 100) is the group's fitted slope, so the
    coefficient is the offset in seconds, shared by all bands. Each lens's linearity job fits its own
    offset; as a candidate in the pooled diagnostics the column is one value for both lenses, and
    whether one value is enough is :func:`pipeline.diagnostics.cross_closure.lens_interaction_tests`' question.
    """

    name = "shutter_offset"
    experiments = ("linearity",)
    truth_defaults = {"offset_s": 4e-4}
    amplitude_name = "shutter_offset_s"
    amplitude_units = "s"

    def true_exposure_s(self, exposure_s):
        return exposure_s + self.params["offset_s"]

    def columns(self, experiment, level, table):
        if experiment == "lightfield" and level == "bracket":
            # ln(L_l / L_s) of an exposure pair with the chain dividing by t: about dt (1 / t_l - 1 / t_s)
            return (1.0 / table["exposure_long_s"].to_numpy(float)
                    - 1.0 / table["exposure_short_s"].to_numpy(float))[:, None]
        if experiment != "linearity" or level != "setting":
            return None
        is_exposure = (table["sweep"] == "exposure").to_numpy()
        return (table["rate_dn_per_s"] * table["gain"]).to_numpy()[:, None] * is_exposure[:, None]

    predicted_from = ("linearity", "setting")

    def predicted_shift(self, experiment, level, table, coef, anchor):
        """Field scale: R^-1 was made at the absolute experiment's exposure t_a and the field frames are at t_f;
        with the true exposure t + dt and the chain dividing by t, the field radiance is off by
        ln((1 + dt / t_f) / (1 + dt / t_a)) (exact, not linearised: at 1/4000 s a 0.4 ms offset is a factor 2.6).

        Parameters
        ----------
        experiment : str
            Stage of the table whose rows are predicted (``"field"``: silent elsewhere).
        level : str
            Level of that table (``"scale"``: silent elsewhere).
        table : pandas.DataFrame
            The field scale closure's table, one row per band and lens, with ``inv_field_exposure_per_s``
            (1 / t_f, s-1) and ``calibration_exposure_s`` (t_a, s).
        coef : numpy.ndarray
            The effect's coefficients fitted on ``anchor``: one, the shutter offset dt (s).
        anchor : pandas.DataFrame
            The observation table of :attr:`predicted_from` on which ``coef`` was fitted.

        Returns
        -------
        numpy.ndarray or None
            Shift of ln(camera / reference scale) of each row of ``table`` (dimensionless), shape (n_rows,); None
            when the table lacks the covariates.
        """
        if not _field_scale(experiment, level, table, ("inv_field_exposure_per_s", "calibration_exposure_s")):
            return None
        dt = float(coef[0])
        field = 1.0 + dt * table["inv_field_exposure_per_s"].to_numpy(float)
        lab = 1.0 + dt / table["calibration_exposure_s"].to_numpy(float)
        return np.log(np.maximum(field, _TINY)) - np.log(np.maximum(lab, _TINY))


@register
class Nonlinearity(Effect):
    """Response bends towards saturation: ``s -> s * (1 - beta * s / full_scale)``.

    Linearity model term: ``-pred**2 / full_scale`` (both sweeps), coefficient beta; in the light field's
    bracket-consistency table (``lightfield``, ``bracket``): ``-(s_l - s_s) / full_scale`` of the exposure pair's
    signals, coefficient beta.
    """

    name = "nonlinearity"
    experiments = ("linearity",)
    truth_defaults = {"beta": 0.05}
    amplitude_name = "nonlinearity_beta"
    amplitude_units = "1"

    def response_dn(self, signal_dn, full_scale_dn):
        return signal_dn * (1.0 - self.params["beta"] * signal_dn / full_scale_dn)

    def columns(self, experiment, level, table):
        if experiment == "lightfield" and level == "bracket":
            # ln(L_l / L_s) of an exposure pair: ln(1 - beta s_l / F) - ln(1 - beta s_s / F), about
            # -beta (s_l - s_s) / F
            return (-(table["signal_long_dn"].to_numpy(float) - table["signal_short_dn"].to_numpy(float))
                    / table["full_scale_dn"].to_numpy(float))[:, None]
        if experiment != "linearity" or level != "setting":
            return None
        pred = table["pred_linear_dn"].to_numpy()
        return (-pred**2 / table["full_scale_dn"].to_numpy())[:, None]

    predicted_from = ("linearity", "setting")

    def predicted_shift(self, experiment, level, table, coef, anchor):
        """Field scale: ln((1 - beta S_f / FS) / (1 - beta S_a / FS)), the response's bend at the field
        frames' level S_f against the absolute experiment's S_a (FS: the linearity table's full scale).

        Parameters
        ----------
        experiment : str
            Stage of the table whose rows are predicted (``"field"``: silent elsewhere).
        level : str
            Level of that table (``"scale"``: silent elsewhere).
        table : pandas.DataFrame
            The field scale closure's table, one row per band and lens, with ``field_signal_dn`` (S_f, DN)
            and ``calibration_signal_dn`` (S_a, DN); ``anchor`` has ``full_scale_dn`` (FS, DN).
        coef : numpy.ndarray
            The effect's coefficients fitted on ``anchor``: one, beta (dimensionless).
        anchor : pandas.DataFrame
            The observation table of :attr:`predicted_from` on which ``coef`` was fitted.

        Returns
        -------
        numpy.ndarray or None
            Shift of ln(camera / reference scale) of each row of ``table`` (dimensionless), shape (n_rows,); None
            when the table lacks the covariates.
        """
        needed = ("field_signal_dn", "calibration_signal_dn")
        if not _field_scale(experiment, level, table, needed) or "full_scale_dn" not in anchor:
            return None
        beta, full = float(coef[0]), float(np.nanmedian(anchor["full_scale_dn"].to_numpy(float)))
        field = 1.0 - beta * table["field_signal_dn"].to_numpy(float) / full
        lab = 1.0 - beta * table["calibration_signal_dn"].to_numpy(float) / full
        return np.log(np.maximum(field, _TINY)) - np.log(np.maximum(lab, _TINY))


@register
class IsoGain(Effect):
    """True analogue gain = ISO/100 times a factor per ISO step (1 at ISO 100).

    Linearity model term for the gain sweep: one column ``pred * [iso == k]`` per
    ISO above the lowest, coefficient = factor - 1.
    """

    name = "iso_gain"
    experiments = ("linearity",)
    truth_defaults = {"rel_sigma": 0.03}
    amplitude_name = "largest_gain_error"
    amplitude_units = "1"

    def prepare(self, rng, context):
        draws = rng.standard_normal(len(STANDARD_ISOS))
        self.factors = {iso: (1.0 if iso == 100.0 else 1.0 + self.params["rel_sigma"] * d)
                        for iso, d in zip(STANDARD_ISOS, draws)}

    def gain_factor(self, iso):
        return self.factors.get(float(iso), 1.0)

    def truth(self):
        out = super().truth()
        out["factors"] = {str(int(k)): float(v) for k, v in self.factors.items()}
        return out

    @staticmethod
    def isos_fitted(table: pd.DataFrame) -> list[float]:
        """The ISO settings whose gain factor the model fits: those of the gain sweep but the lowest (the reference,
        factor 1).

        Parameters
        ----------
        table : pandas.DataFrame
            The linearity stage's setting table, with the columns ``sweep`` and ``iso``.

        Returns
        -------
        list of float
            The fitted ISO settings, ascending; one coefficient of :meth:`columns` each.
        """
        gains = table.loc[table["sweep"] == "gain", "iso"]
        isos = sorted(set(gains.astype(float)))
        return isos[1:]

    def columns(self, experiment, level, table):
        if experiment != "linearity" or level != "setting":
            return None
        isos = self.isos_fitted(table)
        if not isos:
            return None
        pred = table["pred_linear_dn"].to_numpy()
        in_gain = (table["sweep"] == "gain").to_numpy()
        iso = table["iso"].to_numpy(dtype=float)
        return np.column_stack([pred * in_gain * (iso == k) for k in isos])

    predicted_from = ("linearity", "setting")

    def predicted_shift(self, experiment, level, table, coef, anchor):
        """Field scale: ln(f(ISO_f) / f(ISO_a)), the fitted gain factors (1 at the lowest ISO) at the field
        frames' ISO and the absolute experiment's; silent when an ISO is neither fitted nor the lowest.

        Parameters
        ----------
        experiment : str
            Stage of the table whose rows are predicted (``"field"``: silent elsewhere).
        level : str
            Level of that table (``"scale"``: silent elsewhere).
        table : pandas.DataFrame
            The field scale closure's table, one row per band and lens, with ``field_iso`` and
            ``calibration_iso``.
        coef : numpy.ndarray
            The effect's coefficients fitted on ``anchor``: f - 1 at each ISO of :meth:`isos_fitted`
            (dimensionless).
        anchor : pandas.DataFrame
            The observation table of :attr:`predicted_from` on which ``coef`` was fitted.

        Returns
        -------
        numpy.ndarray or None
            Shift of ln(camera / reference scale) of each row of ``table`` (dimensionless), shape (n_rows,); None
            when the table lacks the covariates or an ISO has no factor.
        """
        if not _field_scale(experiment, level, table, ("field_iso", "calibration_iso")) or "sweep" not in anchor:
            return None
        isos = self.isos_fitted(anchor)
        lowest = float(anchor.loc[anchor["sweep"] == "gain", "iso"].astype(float).min())
        factors = {lowest: 1.0, **{iso: 1.0 + float(c) for iso, c in zip(isos, coef)}}
        out = []
        for f_iso, a_iso in zip(table["field_iso"].to_numpy(float), table["calibration_iso"].to_numpy(float)):
            if f_iso not in factors or a_iso not in factors:
                return None
            out.append(np.log(max(factors[f_iso], _TINY)) - np.log(max(factors[a_iso], _TINY)))
        return np.array(out)

    def amplitude(self, experiment, level, table, coef, cov):
        i = int(np.argmax(np.abs(coef)))
        se = float(np.sqrt(max(cov[i, i], 0.0)))
        return float(coef[i]), float(coef[i] - 1.96 * se), float(coef[i] + 1.96 * se)


@register
class BiasDrift(Effect):
    """The black level of a whole frame moves by N(0, ``sigma_dn``) between frames.

    Frame-level model term: the frame's deviation of the unlit (corner) pixels
    from their setting mean, coefficient 1. The stage corrects each frame by it.
    """

    name = "bias_drift"
    experiments = ("dark", "linearity")
    truth_defaults = {"sigma_dn": 3.0}
    amplitude_name = "bias_drift_sigma_dn"
    amplitude_units = "DN"
    corrects_data = True
    columns_carry_noise = True

    def frame_offset_dn(self, rng):
        return float(self.params["sigma_dn"] * rng.standard_normal())

    def columns(self, experiment, level, table):
        if level != "frame" or "corner_dev_dn" not in table:
            return None
        return table["corner_dev_dn"].to_numpy()[:, None]

    def amplitude(self, experiment, level, table, coef, cov):
        return drift_sigma(table)


def drift_sigma(table: pd.DataFrame) -> tuple[float, float, float]:
    """Frame-to-frame spread of the black level from the unlit pixels, with 95 % interval.

    Each row's corner deviation from its setting mean has variance (tau^2 + s_i^2) f, with
    s_i = ``sigma_corner_dn`` (the corners' own noise, large at high ISO) and f = dof / n the share
    the setting means leave; tau^2 is the weighted moment estimate, weights 1 / (tau^2 + s_i^2)^2
    (iterated), so that the noisy high-ISO corners do not swamp a small drift. The interval is the
    chi-square one for the weighted total tau^2 + s_w^2, its degrees of freedom counted in raw frames
    when the table says which frame a row came from (``file_index``: the rows of one frame, both
    lenses and three bands, share its offset, so they are one draw, and each distinct set of frames
    averaged into a setting mean takes one), times the weights' efficiency (sum w)^2 / (n sum w^2).

    Parameters
    ----------
    table : pandas.DataFrame
        Observation table with ``corner_dev_dn`` (each row's unlit-corner deviation from its setting mean, DN)
        and ``sigma_corner_dn`` (the corners' own noise, DN); optionally ``lens``, ``band``, ``sweep``,
        ``setting`` (the groups of the setting means) and ``file_index``.

    Returns
    -------
    sigma : float
        Frame-to-frame standard deviation tau of the black level (DN).
    low : float
        Lower end of its 95 % interval (DN), 0 at the least.
    high : float
        Upper end of its 95 % interval (DN).
    """
    from scipy import stats

    keys = [c for c in ("lens", "band", "sweep", "setting") if c in table]
    dev2 = table["corner_dev_dn"].to_numpy(float) ** 2
    s2 = table["sigma_corner_dn"].to_numpy(float) ** 2
    n = len(dev2)
    n_groups = table.groupby(keys).ngroups if keys else 1
    dof = max(n - n_groups, 1)
    share = dof / max(n, 1)
    tau2 = max(float(np.mean(dev2) / share - np.mean(s2)), 0.0)
    for _ in range(20):
        w = 1.0 / (s2 + tau2) ** 2
        new = max(float(np.sum(w * (dev2 / share - s2)) / np.sum(w)), 0.0)
        converged = abs(new - tau2) <= 1e-9 * max(new, 1e-12)
        tau2 = new
        if converged:
            break
    w = 1.0 / (s2 + tau2) ** 2
    if "file_index" in table and keys:
        frame_sets = table.groupby(keys)["file_index"].agg(lambda f: tuple(sorted(set(f))))
        dof = max(table["file_index"].nunique() - frame_sets.nunique(), 1)
    dof_w = max(dof * float(np.sum(w)) ** 2 / (n * float(np.sum(w**2))), 1.0)
    s2w = float(np.sum(w * s2) / np.sum(w))
    total = tau2 + s2w
    lo_var = total * dof_w / stats.chi2.ppf(0.975, dof_w) - s2w
    hi_var = total * dof_w / stats.chi2.ppf(0.025, dof_w) - s2w
    root = lambda v: float(np.sqrt(max(v, 0.0)))  # noqa: E731
    return root(tau2), root(lo_var), root(hi_var)


@register
class Temperature(Effect):
    """Bias and dark current change with the sensor temperature.

    Simulator: black level + ``bias_dn_per_c`` (T - ``reference_c``); dark current
    times 2^((T - reference_c) / ``dark_doubling_c``). The temperature must be
    logged (``temperature_c`` in frames.csv) for the pipeline to see it.

    Model terms (dark stage), with T_ref the experiment's mean logged temperature:
    setting level ``T - T_ref`` (coefficient: DN per degree C) and
    ``gain * t * (T - T_ref)`` (DN/s at ISO 100 per degree C); frame level the
    frame's temperature departure from its setting mean (DN per degree C).
    """

    name = "temperature"
    experiments = ("dark",)
    truth_defaults = {"bias_dn_per_c": 0.3, "dark_doubling_c": 7.0, "reference_c": 25.0}
    amplitude_name = "bias_dn_per_c"
    amplitude_units = "DN degree_C-1"

    def bias_offset_dn(self, temperature_c):
        if temperature_c is None:
            return 0.0
        return self.params["bias_dn_per_c"] * (temperature_c - self.params["reference_c"])

    def dark_rate_factor(self, temperature_c):
        if temperature_c is None:
            return 1.0
        return 2.0 ** ((temperature_c - self.params["reference_c"]) / self.params["dark_doubling_c"])

    def columns(self, experiment, level, table):
        if experiment != "dark" or "temperature_c" not in table:
            return None
        temp = table["temperature_c"].to_numpy(dtype=float)
        if not np.all(np.isfinite(temp)) or np.ptp(temp) == 0:
            return None
        if level == "setting":
            dt = temp - table["temperature_ref_c"].to_numpy(dtype=float)
            return np.column_stack([dt, (table["gain"] * table["exposure_s"]).to_numpy() * dt])
        if level == "frame":
            dev = temp - table.groupby(["lens", "band", "setting"])["temperature_c"].transform("mean").to_numpy()
            return dev[:, None]
        return None


@register
class Prnu(Effect):
    """Pixel-to-pixel sensitivity: each raw pixel's response times 1 + ``sigma_rel`` N(0, 1).

    Model term (linearity stage, level ``flat``): ``S^2 / sites``, whose
    coefficient is sigma_rel^2; the amplitude reported is sigma_rel.
    """

    name = "prnu"
    experiments = ("linearity",)
    truth_defaults = {"sigma_rel": 0.01}
    amplitude_name = "prnu_sigma_rel"
    amplitude_units = "1"

    def prepare(self, rng, context):
        self.maps = {lens: (1.0 + self.params["sigma_rel"] * rng.standard_normal(context["lens_shape"])).astype(np.float32)
                     for lens in context["lens_names"]}

    def sensitivity_map(self, lens, shape):
        return self.maps[lens]

    def columns(self, experiment, level, table):
        if experiment != "linearity" or level != "flat":
            return None
        return table["signal_sq_per_site_dn2"].to_numpy()[:, None]

    def amplitude(self, experiment, level, table, coef, cov):
        se = float(np.sqrt(max(cov[0, 0], 0.0)))
        root = lambda v: float(np.sqrt(max(v, 0.0)))  # noqa: E731
        return root(coef[0]), root(coef[0] - 1.96 * se), root(coef[0] + 1.96 * se)
