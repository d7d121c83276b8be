"""Base class and registry of physical effects.

An effect has two faces that share one physics:

* the simulator's forward hooks, called while photons become DN; each returns
  the identity when the effect does nothing at that step;
* the pipeline's linearised model term: :meth:`Effect.columns` returns the
  columns that the effect adds to a stage's weighted linear model, scaled so
  that the fitted coefficient is the effect's physical parameter. A stage
  whose model lists the effect fits those columns; the diagnostics add the
  columns of each effect *not* in the model and measure the drop in
  chi-square: the effect's signature in the residuals.

Observation tables (pandas DataFrames) have one row per independent
measurement (a frame or a setting). Columns used here: ``group`` (block of the
base model: lens and band, sweep), ``value_dn``, ``sigma_dn``, ``pred_dn``
(the current model's prediction), ``iso``, ``gain`` (ISO/100), ``exposure_s``,
``sweep`` and the stage-specific covariates an effect documents.
"""

from __future__ import annotations

import importlib
from typing import ClassVar

import numpy as np
import pandas as pd

from pipeline.errors import InputError

_REGISTRY: dict[str, type["Effect"]] = {}

#: The catalogue of docs/design.md: name -> (physics, signature). The names are fixed.
CATALOGUE: dict[str, tuple[str, str]] = {
    "dark_current": ("thermal signal proportional to exposure time and gain",
                     "dark and low-signal residuals grow with exposure time"),
    "hot_pixels": ("sparse pixels with large dark current",
                   "heavy-tailed dark residuals, same pixels in every long exposure"),
    "shutter_offset": ("true exposure = nominal + constant",
                       "DN per second departs from constant as 1/t at short exposures"),
    "nonlinearity": ("response bends towards saturation",
                     "linearity residuals curve with signal level"),
    "iso_gain": ("true analog gain differs from ISO/100 per ISO step",
                 "one offset per ISO in gain-sweep residuals"),
    "prnu": ("pixel-to-pixel sensitivity (flat field)",
             "spatially fixed multiplicative pattern, stable across frames"),
    "bias_drift": ("black level moves between frames",
                   "per-frame offsets that track the unlit pixels outside the image circle"),
    "temperature": ("bias and dark current change with temperature",
                    "residuals follow the logged temperature; lab-to-field offsets"),
    "rolloff_azimuth": ("decentred or tilted optics",
                        "roll-off fitted in one azimuth plane mispredicts the other, as cos(phi - phi0)"),
    "stray_light": ("a fraction of the flux spread by a wide point-spread function",
                    "excess signal beside bright sources, proportional to nearby flux"),
    "spectral_mismatch": ("broad camera bands against narrow reference channels",
                          "field residuals follow the spectral slope of the scene inside each band"),
    "clock_offset": ("camera clock offset from the reference radiometer",
                     "field residuals proportional to dL/dt of the reference series"),
    "immersion_angle": ("immersion factor varies with field angle",
                        "in-water roll-off residuals grow with theta"),
    "polarization": ("response depends on the polarization of the light",
                     "residuals follow the degree and angle of linear polarization"),
}


class Effect:
    """One physical effect. Subclass, set the class attributes, register.

    Parameters given at construction override ``truth_defaults`` (used by the
    simulator; the pipeline fits its own values).
    """

    name: ClassVar[str] = ""
    #: experiments whose residuals carry the signature (and whose stage fits it)
    experiments: ClassVar[tuple[str, ...]] = ()
    #: simulator parameters and their defaults (units in the names)
    truth_defaults: ClassVar[dict] = {}
    #: name and units of the amplitude the diagnostics report
    amplitude_name: ClassVar[str] = ""
    amplitude_units: ClassVar[str] = "1"
    #: True when the stage applies the effect by correcting the data (masking,
    #: offset removal) rather than by fitting columns of its linear model
    corrects_data: ClassVar[bool] = False
    #: True when the effect's model columns are measured quantities with noise of their own that the
    #: table's ``sigma_dn`` leaves out (the unlit corners' offsets of ``bias_drift``): the excess
    #: chi-square beside such a candidate is no evidence of more structure unless it follows a covariate
    columns_carry_noise: ClassVar[bool] = False

    def __init__(self, **params):
        unknown = set(params) - set(self.truth_defaults)
        if unknown:
            raise InputError(None, f"effect {self.name}: unknown parameter(s) {sorted(unknown)}; "
                                   f"known: {sorted(self.truth_defaults)}")
        self.params = {**self.truth_defaults, **params}

    # ------------------------------------------------------------ simulator
    def prepare(self, rng: np.random.Generator, context: dict) -> None:
        """Draw the static, per-camera part of the effect (pixel maps, per-ISO factors).

        Parameters
        ----------
        rng : numpy.random.Generator
            The simulator's generator of the camera's static patterns (the same seed gives the same camera).
        context : dict
            From the simulator: ``lens_names`` (sequence of str), ``lens_shape`` (rows, columns of one lens region in
            raw pixels) and ``image_circle_radius_band_px`` (radius of the image circle, band pixels).
        """

    def true_exposure_s(self, exposure_s: float) -> float:
        """The time the shutter is really open for a frame of nominal exposure ``exposure_s``.

        Parameters
        ----------
        exposure_s : float
            Exposure time the camera records (s); an effect earlier in the list may have changed it already.

        Returns
        -------
        float
            Exposure time during which light reaches the sensor (s); ``exposure_s`` itself when the effect does not
            act on the shutter.
        """
        return exposure_s

    def gain_factor(self, iso: float) -> float:
        """Factor on the nominal analog gain (ISO/100) of a frame taken at ``iso``.

        Parameters
        ----------
        iso : float
            ISO setting of the frame.

        Returns
        -------
        float
            True gain over nominal gain (dimensionless); 1 when the effect does not act on the gain.
        """
        return 1.0

    def dark_rate_e_per_s(self, lens: str, shape: tuple[int, int]) -> np.ndarray | float:
        """Dark-current rate that the effect adds to each raw pixel of a lens.

        Parameters
        ----------
        lens : str
            Name of the lens whose region is exposed.
        shape : tuple of int
            (rows, columns) of the lens region in raw pixels.

        Returns
        -------
        numpy.ndarray or float
            Dark-current rate (electron s-1 per raw pixel), an array of ``shape`` or a scalar broadcast to it;
            0 when the effect adds none.
        """
        return 0.0

    def response_dn(self, signal_dn: np.ndarray, full_scale_dn: float) -> np.ndarray:
        """The camera's response to a linear signal: how the effect bends the recorded DN.

        Parameters
        ----------
        signal_dn : numpy.ndarray
            Signal above the black level, linear in the collected electrons (DN), any shape.
        full_scale_dn : float
            Largest signal the converter records above the black level (DN): ADC maximum minus bias.

        Returns
        -------
        numpy.ndarray
            Recorded signal above the black level (DN), same shape as ``signal_dn``; ``signal_dn`` itself when the
            response stays linear.
        """
        return signal_dn

    def frame_offset_dn(self, rng: np.random.Generator) -> float:
        """Black-level shift of one whole frame, drawn once per frame (both lenses share it).

        Parameters
        ----------
        rng : numpy.random.Generator
            The frame's generator (its seed fixes the frame).

        Returns
        -------
        float
            Offset added to every raw pixel of the frame (DN); 0 when the effect draws none.
        """
        return 0.0

    def sensitivity_map(self, lens: str, shape: tuple[int, int]) -> np.ndarray | float:
        """Multiplicative per-pixel sensitivity (raw lens shape), e.g. a flat field.

        Parameters
        ----------
        lens : str
            Name of the lens whose region is exposed.
        shape : tuple of int
            (rows, columns) of the lens region in raw pixels.

        Returns
        -------
        numpy.ndarray or float
            Relative sensitivity of each raw pixel (dimensionless), an array of ``shape`` or a scalar; 1 when the
            effect leaves the sensitivity alone.
        """
        return 1.0

    def optics_factor(self, lens: str, medium: str, theta_deg: np.ndarray, phi_deg: np.ndarray,
                      band_index: np.ndarray) -> np.ndarray | float:
        """Multiplicative change of the light reaching each raw pixel (roll-off, immersion).

        Parameters
        ----------
        lens : str
            Name of the lens.
        medium : str
            Medium in front of the lens, ``"air"`` or ``"water"``.
        theta_deg : numpy.ndarray
            Field angle of each raw pixel's viewing direction from the optical axis (degree), lens shape.
        phi_deg : numpy.ndarray
            Azimuth of each raw pixel's viewing direction around the optical axis (degree), lens shape.
        band_index : numpy.ndarray
            Index of each raw pixel's colour band in the mosaic (int), lens shape.

        Returns
        -------
        numpy.ndarray or float
            Factor on the photo-electron rate of each raw pixel (dimensionless); 1 when the effect leaves the
            optics alone.
        """
        return 1.0

    def spread_light(self, photo_rate: np.ndarray, lens: str) -> np.ndarray:
        """Redistribute the photo-electron rate image (point-spread function, stray light).

        Parameters
        ----------
        photo_rate : numpy.ndarray
            Photo-electron rate of each raw pixel of the lens region (electron s-1).
        lens : str
            Name of the lens.

        Returns
        -------
        numpy.ndarray
            Photo-electron rate after the spreading (electron s-1), same shape; ``photo_rate`` itself when the
            effect spreads no light.
        """
        return photo_rate

    def bias_offset_dn(self, temperature_c: float | None) -> float:
        """Black-level change of a frame taken at ``temperature_c``.

        Parameters
        ----------
        temperature_c : float or None
            Sensor temperature logged with the frame (degree Celsius); None when the frame has none.

        Returns
        -------
        float
            Offset added to every raw pixel of the frame (DN); 0 when the effect does not depend on temperature.
        """
        return 0.0

    def dark_rate_factor(self, temperature_c: float | None) -> float:
        """Factor on every dark-current rate at ``temperature_c``.

        Parameters
        ----------
        temperature_c : float or None
            Sensor temperature logged with the frame (degree Celsius); None when the frame has none.

        Returns
        -------
        float
            Factor on the dark-current rates (dimensionless); 1 when the effect does not depend on temperature.
        """
        return 1.0

    def camera_clock_offset_s(self) -> float:
        """Camera clock minus true time (s) of the frames a camera with this effect writes.

        Returns
        -------
        float
            Offset of the camera's time stamps from true time (s); 0 when the effect leaves the clock alone.
        """
        return 0.0

    def sky_spectral_exponent(self, hours_since_start: float) -> float:
        """Exponent a of a factor (lambda / 550 nm)^(-a) on the simulated sky spectrum at that time.

        Parameters
        ----------
        hours_since_start : float
            Time since the start of the simulated field series (hour).

        Returns
        -------
        float
            Angstrom-like exponent a (dimensionless); 0 leaves the sky spectrum as it is.
        """
        return 0.0

    def sun_glare_wings(self) -> dict | None:
        """Parameters of the simulator's sun glare in the field frames (fraction, core_deg, index), or None."""
        return None

    def truth(self) -> dict:
        """What the simulator writes to the truth folder for this effect.

        Returns
        -------
        dict
            The effect's parameters ``params`` (and, for an effect with a static part, what :meth:`prepare`
            drew) as plain Python values (lists for arrays), ready for YAML.
        """
        return {k: _plain(v) for k, v in self.params.items()}

    # ------------------------------------------------------------- pipeline
    def columns(self, experiment: str, level: str, table: pd.DataFrame) -> np.ndarray | None:
        """Linearised model columns (n_rows, k) in DN, or None when silent here.

        Parameters
        ----------
        experiment : str
            Stage whose observation table this is (``"linearity"``, ``"dark"``, ``"rolloff"``, ...).
        level : str
            Level of the observations within the stage (e.g. ``"setting"``, ``"frame"``, ``"water"``).
        table : pandas.DataFrame
            The observation table, one row per independent measurement, with the columns the module's
            docstring lists and the covariates the effect documents.

        Returns
        -------
        numpy.ndarray or None
            Model columns of shape (n_rows, k), in the units of the table's ``value_dn`` (DN unless the table says
            otherwise), scaled so that the fitted coefficients are the effect's physical parameters; None when the
            effect leaves no signature in that table.
        """
        return None

    #: the (experiment, level) whose fitted coefficients :meth:`predicted_shift` takes, or None
    predicted_from: ClassVar[tuple[str, str] | None] = None

    def predicted_shift(self, experiment: str, level: str, table: pd.DataFrame, coef: np.ndarray,
                        anchor: pd.DataFrame) -> np.ndarray | None:
        """What the effect, with the coefficients ``coef`` fitted on the table ``anchor`` (of
        :attr:`predicted_from`), changes in the rows of a table it is never fitted to
        (:data:`pipeline.diagnostics.tables.PREDICTED_TABLES`: the field scale closure, ln of the camera/reference
        scale), in that table's units; None when silent there (or when the model already corrects it).

        Parameters
        ----------
        experiment : str
            Stage of the table whose rows are predicted.
        level : str
            Level of that table within the stage.
        table : pandas.DataFrame
            The table whose rows are predicted.
        coef : numpy.ndarray
            Coefficients of the effect's columns fitted on ``anchor``, shape (k,), in the effect's physical units.
        anchor : pandas.DataFrame
            The observation table of :attr:`predicted_from` on which ``coef`` was fitted.

        Returns
        -------
        numpy.ndarray or None
            Change of each row of ``table``, shape (n_rows,), in that table's units; None when silent there.
        """
        return None

    def amplitude_label(self, experiment: str) -> tuple[str, str]:
        """Name and units of the amplitude that :meth:`amplitude` returns for that experiment.

        Parameters
        ----------
        experiment : str
            Stage whose fitted coefficients the amplitude is made of.

        Returns
        -------
        name : str
            Name of the amplitude, as the diagnostics report it.
        units : str
            Its units (``"1"`` for a dimensionless amplitude).
        """
        return self.amplitude_name, self.amplitude_units

    def amplitude(self, experiment: str, level: str, table: pd.DataFrame,
                  coef: np.ndarray, cov: np.ndarray) -> tuple[float, float, float]:
        """Physical amplitude and its 95 % interval from the fitted coefficients.

        The base class takes the first coefficient and its standard error (normal interval, +- 1.96 sigma).

        Parameters
        ----------
        experiment : str
            Stage whose table the columns were fitted on.
        level : str
            Level of that table within the stage.
        table : pandas.DataFrame
            The observation table the columns were fitted on.
        coef : numpy.ndarray
            Fitted coefficients of the effect's columns, shape (k,).
        cov : numpy.ndarray
            Their covariance, shape (k, k).

        Returns
        -------
        amplitude : float
            The effect's amplitude, in the units :meth:`amplitude_label` gives.
        low : float
            Lower end of its 95 % interval, same units.
        high : float
            Upper end of its 95 % interval, same units.
        """
        se = float(np.sqrt(max(cov[0, 0], 0.0)))
        return float(coef[0]), float(coef[0] - 1.96 * se), float(coef[0] + 1.96 * se)


def _plain(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    return value


def register(cls: type[Effect]) -> type[Effect]:
    """Class decorator: make an effect available by its name.

    Parameters
    ----------
    cls : type
        Subclass of :class:`Effect` with a non-empty ``name``.

    Returns
    -------
    type
        ``cls`` itself, now registered.

    Raises
    ------
    ValueError
        When ``cls`` has no name.
    """
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    _REGISTRY[cls.name] = cls
    return cls


def available() -> list[str]:
    """Names of the registered effects.

    Returns
    -------
    list of str
        The names, sorted.
    """
    return sorted(_REGISTRY)


def get(name: str, **params) -> Effect:
    """An instance of the named effect (InputError naming the known ones otherwise).

    Parameters
    ----------
    name : str
        Name of a registered effect (a key of :data:`CATALOGUE` that is implemented).
    **params
        Simulator parameters overriding the effect's ``truth_defaults``.

    Returns
    -------
    Effect
        The effect, its ``params`` the defaults updated with ``params``.

    Raises
    ------
    pipeline.errors.InputError
        When no effect has that name, or a parameter is not one of the effect's.
    """
    if name not in _REGISTRY:
        hint = " (in the catalogue but not implemented yet)" if name in CATALOGUE else ""
        raise InputError(None, f"unknown effect '{name}'{hint}; implemented: {', '.join(available())}")
    return _REGISTRY[name](**params)


def load_plugins(modules: list[str]) -> None:
    """Import user modules that register their own effects.

    Parameters
    ----------
    modules : list of str
        Dotted names of the modules to import (``model.plugins`` of the configuration); None or empty imports
        nothing.

    Raises
    ------
    pipeline.errors.InputError
        When a module fails to import, naming it and the error.
    """
    for module in modules or []:
        try:
            importlib.import_module(module)
        except Exception as exc:  # noqa: BLE001 (a module that fails in any way at import is bad input)
            raise InputError(None, f"model.plugins: cannot import '{module}' "
                                   f"({type(exc).__name__}: {exc})") from None


def parse_effect_spec(spec: str) -> tuple[str, dict]:
    """``name[:param=value,...]`` as the simulator's --effect option takes it.

    Parameters
    ----------
    spec : str
        The option's value, e.g. ``"shutter_offset:offset_s=0.0002"``.

    Returns
    -------
    name : str
        Name of the effect.
    params : dict[str, float]
        Its parameters, each value read as a float.

    Raises
    ------
    pipeline.errors.InputError
        When an item is not ``param=value`` or a value is not a number.
    """
    name, _, rest = spec.partition(":")
    params = {}
    if rest:
        for item in rest.split(","):
            key, sep, value = item.partition("=")
            if not sep:
                raise InputError(None, f"--effect {spec}: expected param=value, got '{item}'")
            try:
                params[key.strip()] = float(value)
            except ValueError:
                raise InputError(None, f"--effect {spec}: '{value}' is not a number") from None
    return name.strip(), params
