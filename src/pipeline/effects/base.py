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

        ``context`` (from the simulator): ``lens_names``, ``lens_shape`` (raw
        pixels of one lens region) and ``image_circle_radius_band_px``.
        """

    def true_exposure_s(self, exposure_s: float) -> float:
        return exposure_s

    def gain_factor(self, iso: float) -> float:
        return 1.0

    def dark_rate_e_per_s(self, lens: str, shape: tuple[int, int]) -> np.ndarray | float:
        return 0.0

    def response_dn(self, signal_dn: np.ndarray, full_scale_dn: float) -> np.ndarray:
        return signal_dn

    def frame_offset_dn(self, rng: np.random.Generator) -> float:
        return 0.0

    def sensitivity_map(self, lens: str, shape: tuple[int, int]) -> np.ndarray | float:
        """Multiplicative per-pixel sensitivity (raw lens shape), e.g. a flat field."""
        return 1.0

    def optics_factor(self, lens: str, medium: str, theta_deg: np.ndarray, phi_deg: np.ndarray,
                      band_index: np.ndarray) -> np.ndarray | float:
        """Multiplicative change of the light reaching each raw pixel (roll-off, immersion)."""
        return 1.0

    def spread_light(self, photo_rate: np.ndarray, lens: str) -> np.ndarray:
        """Redistribute the photo-electron rate image (point-spread function, stray light)."""
        return photo_rate

    def bias_offset_dn(self, temperature_c: float | None) -> float:
        """Black-level change of a frame taken at ``temperature_c``."""
        return 0.0

    def dark_rate_factor(self, temperature_c: float | None) -> float:
        """Factor on every dark-current rate at ``temperature_c``."""
        return 1.0

    def camera_clock_offset_s(self) -> float:
        """Camera clock minus true time (s) of the frames a camera with this effect writes."""
        return 0.0

    def sky_spectral_exponent(self, hours_since_start: float) -> float:
        """Exponent a of a factor (lambda / 550 nm)^(-a) on the simulated sky spectrum at that time."""
        return 0.0

    def sun_glare_wings(self) -> dict | None:
        """Parameters of the simulator's sun glare in the field frames (fraction, core_deg, index), or None."""
        return None

    def truth(self) -> dict:
        """What the simulator writes to the truth folder for this effect."""
        return {k: _plain(v) for k, v in self.params.items()}

    # ------------------------------------------------------------- pipeline
    def columns(self, experiment: str, level: str, table: pd.DataFrame) -> np.ndarray | None:
        """Linearised model columns (n_rows, k) in DN, or None when silent here."""
        return None

    #: the (experiment, level) whose fitted coefficients :meth:`predicted_shift` takes, or None
    predicted_from: ClassVar[tuple[str, str] | None] = None

    def predicted_shift(self, experiment: str, level: str, table: pd.DataFrame, coef: np.ndarray,
                        anchor: pd.DataFrame) -> np.ndarray | None:
        """What the effect, with the coefficients ``coef`` fitted on the table ``anchor`` (of
        :attr:`predicted_from`), changes in the rows of a table it is never fitted to
        (:data:`pipeline.diagnostics.tables.PREDICTED_TABLES`: the field scale closure, ln of the camera/reference
        scale), in that table's units; None when silent there (or when the model already corrects it)."""
        return None

    def amplitude_label(self, experiment: str) -> tuple[str, str]:
        """Name and units of the amplitude that :meth:`amplitude` returns for that experiment."""
        return self.amplitude_name, self.amplitude_units

    def amplitude(self, experiment: str, level: str, table: pd.DataFrame,
                  coef: np.ndarray, cov: np.ndarray) -> tuple[float, float, float]:
        """Physical amplitude and its 95 % interval from the fitted coefficients."""
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
    """Class decorator: make an effect available by its name."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    _REGISTRY[cls.name] = cls
    return cls


def available() -> list[str]:
    return sorted(_REGISTRY)


def get(name: str, **params) -> Effect:
    """An instance of the named effect (InputError naming the known ones otherwise)."""
    if name not in _REGISTRY:
        hint = " (in the catalogue but not implemented yet)" if name in CATALOGUE else ""
        raise InputError(None, f"unknown effect '{name}'{hint}; implemented: {', '.join(available())}")
    return _REGISTRY[name](**params)


def load_plugins(modules: list[str]) -> None:
    """Import user modules that register their own effects."""
    for module in modules or []:
        try:
            importlib.import_module(module)
        except Exception as exc:  # noqa: BLE001 (a module that fails in any way at import is bad input)
            raise InputError(None, f"model.plugins: cannot import '{module}' "
                                   f"({type(exc).__name__}: {exc})") from None


def parse_effect_spec(spec: str) -> tuple[str, dict]:
    """``name[:param=value,...]`` as the simulator's --effect option takes it."""
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
