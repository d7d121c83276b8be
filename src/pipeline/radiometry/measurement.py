"""The measurement model: Eq. (4) inverted, one named step each (Larouche et al. 2024, Section 2.1).

Eq. (4) with Eq. (2) says what a band pixel reads for a spectral radiance L,

    y_raw = dark(ISO, t, T) + N( (t + dt) * g * f_ISO * F(x, y) * g(theta, phi) / I * R * L ),

with ``dark`` the dark model (Section 2.8), ``dt`` the shutter offset, ``g =
ISO/100`` and ``f_ISO`` the fitted per-ISO gain factor, ``N`` the
nonlinearity ``s -> s (1 - beta s / full_scale)``, ``F`` the flat field,
``g(theta, phi)`` the roll-off (Eq. 13), ``I`` the immersion factor in water
(Eq. 11) and ``R`` the responsivity (``R^-1``: Eq. 9). The chain below undoes
it one step at a time, on a whole band image at once:

    raw band DN -> subtract_dark -> add_shot_noise -> flag_hot_pixels -> flag_saturation ->
    linearise -> normalise_exposure -> correct_flat_field -> correct_rolloff ->
    correct_immersion -> to_radiance   [W sr-1 m-2 nm-1]

Each step applies only the effects of ``model.effects`` that it owns
(``dark_current`` and ``temperature`` in the dark level, ``hot_pixels``,
``nonlinearity``, ``shutter_offset`` and ``iso_gain``, ``prnu``); roll-off,
immersion and responsivity are the base model. The nonlinearity bends the
dark-corrected signal in DN (the linearity stage fits it there), so its
inverse is taken before the division by exposure and gain; that is the
exposure-and-gain step of docs/design.md's chain written in DN.

Uncertainty goes forward with the value, to first order, in two parts kept as
named variances (in the units of the current value):

* random, different from pixel to pixel (and, but for the fixed patterns,
  frame to frame): ``shot`` (signal electrons, from the photon-transfer
  conversion gain), ``read`` (the dark stage's temporal noise at that ISO),
  ``dark`` (dark-current electrons and the pixel-to-pixel offset pattern that
  the mean dark level leaves), ``prnu`` (sensitivity of pixels the flat field
  does not cover);
* systematic, common to every pixel of a band (calibration terms): the dark
  model's parameters, shutter offset, ISO gain factor, nonlinearity, roll-off
  (from its covariance, a function of theta), immersion factor and the R^-1
  budget. Terms of different names are taken as independent.

Every step is a pure function of a :class:`Measured` value and a small
parameter object, so each is tested on hand values without files.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from pipeline.errors import ImpossibleResult
from pipeline.radiometry.dark import dark_model_level_dn, temperature_model_shift_dn
from pipeline.radiometry.exposure import gain_from_iso
from pipeline.radiometry.rolloff import rolloff_on_image, rolloff_slope_on_image

__all__ = [
    "FLAG_SATURATED", "FLAG_HOT", "FLAG_OUTSIDE_IMAGE_CIRCLE", "FLAG_BEYOND_CALIBRATED_ANGLE", "FLAG_MEANINGS",
    "Measured", "FrameSettings", "DarkModel", "ResponseModel", "BandCalibration",
    "RolloffMap", "rolloff_map", "PixelFactors", "pixel_factors", "flat_field_terms", "correct_pixel_factors",
    "from_raw", "subtract_dark", "add_shot_noise", "flag_hot_pixels", "flag_saturation", "linearise", "normalise_exposure",
    "correct_flat_field", "correct_rolloff", "correct_immersion", "to_radiance", "measure_band",
    "check_inverse_responsivity",
]

#: quality flag bits of a pixel's radiance
FLAG_SATURATED = 1                  # a CFA site at the white level, or the signal above the saturation level
FLAG_HOT = 2                        # hot pixel of the dark stage's mask
FLAG_OUTSIDE_IMAGE_CIRCLE = 4       # no viewing direction: radiance NaN
FLAG_BEYOND_CALIBRATED_ANGLE = 8    # field angle beyond the largest angle the roll-off was measured at
FLAG_MEANINGS = {"saturated": FLAG_SATURATED, "hot_pixel": FLAG_HOT,
                 "outside_image_circle": FLAG_OUTSIDE_IMAGE_CIRCLE,
                 "beyond_calibrated_field_angle": FLAG_BEYOND_CALIBRATED_ANGLE}


class Measured:
    """A band image on its way through the chain: value, named variances, quality flags.

    ``random_var`` and ``systematic_var`` map a term name to its variance in
    the units of ``value`` (arrays broadcastable to it). Inside, a step that
    scales the value (Eq. 2's exposure and gain, the flat field, the roll-off,
    the immersion factor, R^-1) neither multiplies the image nor touches the
    terms: the value is kept as ``base`` times the product of the factors
    applied since (a scalar ``factor`` and the maps ``factor_maps``), taken
    once when the value is read; each term is kept either as an absolute
    variance in the units of ``base`` (times the factors squared in those of
    the value: read, dark and shot noise, the dark model) or as a relative
    variance (times the value squared: the calibration terms, whose relative
    uncertainty a scaling does not change). The standard uncertainties are
    then |factors| sqrt(absolute + base^2 relative), in one array each.
    """

    def __init__(self, value, units: str, random_var=None, systematic_var=None, flags=None):
        self.base = value
        self.factor = 1.0
        self.factor_maps = ()
        self.units = units
        self.flags = flags
        #: absolute variances, in the units of ``base``
        self.random_abs = dict(random_var or {})
        self.systematic_abs = dict(systematic_var or {})
        #: relative variances
        self.random_rel = {}
        self.systematic_rel = {}

    def _replace(self, **changes) -> "Measured":
        new = object.__new__(Measured)
        for name in ("base", "factor", "factor_maps", "units", "flags", "random_abs", "systematic_abs",
                     "random_rel", "systematic_rel"):
            setattr(new, name, changes.pop(name, getattr(self, name)))
        if changes:
            raise TypeError(f"unknown fields {sorted(changes)}")
        return new

    @property
    def unscaled(self) -> bool:
        """True when the value is its base (no factor applied since the last change of the value itself)."""
        return not self.factor_maps and self.factor == 1.0

    def _scale_of(self, x, squared: bool = False, out=None):
        """``x`` times the factors (or their squares): in a new array unless there is no factor.

        With ``out`` (the product's shape and type: see :meth:`evaluate_into`) the product is taken there.
        """
        if out is not None and self.unscaled:
            np.copyto(out, x)
            return out
        if self.unscaled:
            return x
        power = 2 if squared else 1
        out = np.multiply(x, self.factor**power, out=out)
        for f in self.factor_maps:
            f = np.square(f) if squared else f
            # in place when the product keeps the array's shape and type (it is new: the first product made it)
            in_place = isinstance(out, np.ndarray) and out.shape == np.broadcast_shapes(out.shape, np.shape(f)) \
                and out.dtype == np.result_type(out, f)
            out = np.multiply(out, f, out=out if in_place else None)
        return out

    def in_base_units(self, variance):
        """A variance in the units of the value, in those of ``base`` (over the factors squared).

        Parameters
        ----------
        variance : numpy.ndarray or float
            A variance in the units of ``value`` squared, broadcastable to the value.

        Returns
        -------
        numpy.ndarray or float
            The same variance in the units of ``base`` squared; ``variance`` itself when no factor is applied.
        """
        if self.unscaled:
            return variance
        return variance / self._scale_of(np.ones(np.shape(self.base), np.result_type(np.float32, self.base)),
                                         squared=True)

    @cached_property
    def value(self) -> np.ndarray:
        """The value in ``units``: base times the factors (computed once)."""
        return self._scale_of(self.base)

    def _terms(self, absolute: dict, relative: dict) -> dict:
        out = {k: self._scale_of(np.asarray(v), squared=True) for k, v in absolute.items()}
        if relative:
            v2 = np.square(self.value)
            out.update({k: v2 * r for k, r in relative.items()})
        return out

    @cached_property
    def random_var(self) -> dict:
        """Random variances by name, in the units of ``value``."""
        return self._terms(self.random_abs, self.random_rel)

    @cached_property
    def systematic_var(self) -> dict:
        """Systematic variances by name, in the units of ``value``."""
        return self._terms(self.systematic_abs, self.systematic_rel)

    @cached_property
    def random_sigma(self) -> np.ndarray:
        """sqrt of the sum of the random variances (computed once per value)."""
        return self._sigma(self.random_abs, self.random_rel)

    @cached_property
    def systematic_sigma(self) -> np.ndarray:
        """sqrt of the sum of the systematic variances (computed once per value)."""
        return self._sigma(self.systematic_abs, self.systematic_rel)

    def _sigma(self, absolute: dict, relative: dict, out=None, scratch=None) -> np.ndarray:
        """|factors| sqrt(sum(absolute) + base^2 sum(relative)), in one array of the value's shape.

        Into ``out`` when given (the value's shape and float type; else a new
        array); ``scratch``, an array like ``out``, holds a sum of variance
        maps on the way (else a new one). The same operations in the same
        order either way, so the result does not depend on the buffers.
        """
        # the value's float type (a float32 image stays float32), at least float32
        dtype = np.result_type(np.float32, self.base)
        shape = np.broadcast_shapes(np.shape(self.base), *(np.shape(f) for f in self.factor_maps))
        total = np.empty(shape, dtype) if out is None else _check_buffer(out, shape, dtype)
        if relative:
            np.square(np.broadcast_to(self.base, shape), out=total, dtype=dtype)
            total *= _sum_terms(relative.values(), _buffer_for(relative.values(), scratch, shape, dtype))
            a = _sum_terms(absolute.values(), _buffer_for(absolute.values(), scratch, shape, dtype))
            total += a
        else:
            a = _sum_terms(absolute.values(), _buffer_for(absolute.values(), total, shape, dtype))
            if a is not total:
                np.copyto(total, np.broadcast_to(a, shape), casting="unsafe")
        np.sqrt(total, out=total)
        if not self.unscaled:
            total *= abs(self.factor)
            for f in self.factor_maps:
                total *= f
            np.abs(total, out=total)  # a negative factor map (|f| * sigma); nothing changes where all are positive
        return total

    def evaluate_into(self, value=None, random_sigma=None, systematic_sigma=None, scratch=None) -> "Measured":
        """Take ``value``, ``random_sigma`` and ``systematic_sigma`` into the arrays given (returns ``self``).

        Each given array receives what the property of that name returns. Where the array has
        the property's float type it is computed there, without a temporary
        image, and the property then returns that array; otherwise the property is
        computed as usual and copied in (cast to the array's type).

        Parameters
        ----------
        value : numpy.ndarray, optional
            Receives the value (in ``units``); the value's shape, e.g. a slot of an output map.
        random_sigma : numpy.ndarray, optional
            Receives the random standard uncertainty (in ``units``), same shape.
        systematic_sigma : numpy.ndarray, optional
            Receives the systematic standard uncertainty (in ``units``), same shape.
        scratch : numpy.ndarray, optional
            An array like them (shape, float type of the uncertainties) that holds a sum of variance maps on the
            way; ignored when it is not of that shape and type.

        Returns
        -------
        Measured
            ``self``, its properties now the arrays given where computed there.

        Raises
        ------
        ValueError
            When a given array's shape is not the value's.
        """
        shape = np.broadcast_shapes(np.shape(self.base), *(np.shape(f) for f in self.factor_maps))
        value_type = np.result_type(self.base) if self.unscaled else np.result_type(self.base, *self.factor_maps,
                                                                                     self.factor)
        sigma_type = np.result_type(np.float32, self.base)
        if scratch is not None and (scratch.shape != shape or scratch.dtype != sigma_type):
            scratch = None
        for name, buffer, dtype in (("value", value, value_type), ("random_sigma", random_sigma, sigma_type),
                                    ("systematic_sigma", systematic_sigma, sigma_type)):
            if buffer is None:
                continue
            if buffer.shape != shape:
                raise ValueError(f"output buffer of shape {buffer.shape} for a value of shape {shape}")
            if buffer.dtype != dtype or name in self.__dict__:
                np.copyto(buffer, getattr(self, name), casting="same_kind")
            elif name == "value":
                self.__dict__[name] = self._scale_of(self.base, out=buffer)
            else:
                terms = (self.random_abs, self.random_rel) if name == "random_sigma" else (self.systematic_abs,
                                                                                           self.systematic_rel)
                self.__dict__[name] = self._sigma(*terms, out=buffer, scratch=scratch)
        return self

    def scaled(self, factor, units: str, relative_systematic=None, **extra_systematic) -> "Measured":
        """value * factor (every variance then times factor^2), plus new systematic terms.

        Parameters
        ----------
        factor : float or numpy.ndarray
            The factor on the value: a scalar, or a map broadcastable to the value (e.g. 1 / g(theta)).
        units : str
            Units of the scaled value.
        relative_systematic : dict[str, float or numpy.ndarray], optional
            New systematic terms as relative variances (dimensionless: the factor's relative uncertainty squared);
            a term of an existing name replaces it.
        **extra_systematic
            New systematic terms as absolute variances, already in the new ``units`` squared.

        Returns
        -------
        Measured
            A new value; ``self`` is left unchanged.
        """
        if np.ndim(factor) == 0:
            out = self._replace(factor=self.factor * float(factor), units=units)
        else:
            out = self._replace(factor_maps=self.factor_maps + (np.asarray(factor),), units=units)
        out.systematic_abs = dict(self.systematic_abs)
        out.systematic_abs.update({k: out.in_base_units(v) for k, v in extra_systematic.items()})
        out.systematic_rel = {**self.systematic_rel, **(relative_systematic or {})}
        return out

    def transformed(self, value, slope) -> "Measured":
        """The value mapped by a nonlinear function with derivative ``slope``: every variance times slope^2.

        ``value`` becomes the new base (no factor); the terms go with it, all as absolute variances
        (the relative ones were relative to the old value).

        Parameters
        ----------
        value : numpy.ndarray
            The mapped value f(value), in the current units (the value's shape).
        slope : numpy.ndarray or float
            The derivative df/dvalue at each pixel (dimensionless), broadcastable to the value.

        Returns
        -------
        Measured
            A new value with the same units and flags.
        """
        out = {}
        for name in ("random", "systematic"):
            terms = getattr(self, f"{name}_var")
            out[f"{name}_abs"] = {k: v * np.square(slope) for k, v in terms.items()}
            out[f"{name}_rel"] = {}
        return self._replace(base=value, factor=1.0, factor_maps=(), **out)

    def flagged(self, where, bit: int) -> "Measured":
        """These flags with one bit set where a condition holds.

        Parameters
        ----------
        where : array_like of bool
            Pixels to flag, broadcastable to the value.
        bit : int
            The flag bit (one of the ``FLAG_*`` constants).

        Returns
        -------
        Measured
            A new value with the flags ORed; value and variances unchanged.
        """
        flags = np.zeros(np.shape(self.base), np.uint8) if self.flags is None else self.flags.copy()
        np.bitwise_or(flags, np.uint8(bit), out=flags, where=np.asarray(where, bool))
        return self._replace(flags=flags)

    def flagged_by(self, bits) -> "Measured":
        """Flags ORed with a map of flag bits (uint8, broadcastable to the value).

        Parameters
        ----------
        bits : array_like of numpy.uint8
            Flag bits of each pixel (ORs of the ``FLAG_*`` constants).

        Returns
        -------
        Measured
            A new value with the flags ORed; value and variances unchanged.
        """
        flags = np.zeros(np.shape(self.base), np.uint8) if self.flags is None else self.flags.copy()
        flags |= np.asarray(bits, np.uint8)
        return self._replace(flags=flags)


def _sum_terms(terms, out=None):
    """Sum of variance terms: the scalars first (as a Python float), then the maps; 0.0 when there is none.

    The maps' sum is a new array, or ``out`` when given (see :func:`_buffer_for`).
    """
    const, maps = 0.0, []
    for t in terms:
        if np.ndim(t) == 0:
            const += float(t)
        else:
            maps.append(t)
    if not maps:
        return const
    if out is not None:
        np.add(np.broadcast_to(maps[0], out.shape), const, out=out)
        for t in maps[1:]:
            out += t
        return out
    total = maps[0] + const  # always a new array: the caller may work in it
    for t in maps[1:]:
        if np.shape(total) == np.broadcast_shapes(np.shape(total), np.shape(t)):
            total += t
        else:
            total = total + t
    return total


def _buffer_for(terms, buffer, shape, dtype):
    """``buffer`` when the sum of the maps among ``terms`` is of ``shape`` and ``dtype`` in it (else None: a new array).

    The sum is then the same number in the buffer as in a new array: every map of the float type ``dtype``.
    """
    if buffer is None:
        return None
    maps = [t for t in terms if np.ndim(t) != 0]
    if not maps or any(np.asarray(t).dtype != dtype for t in maps) or buffer.shape != shape or buffer.dtype != dtype \
            or np.broadcast_shapes(*(np.shape(t) for t in maps)) != shape:
        return None
    return buffer


def _check_buffer(out, shape, dtype):
    if not isinstance(out, np.ndarray) or out.shape != tuple(shape) or out.dtype != dtype:
        raise ValueError(f"output buffer {getattr(out, 'dtype', None)} {np.shape(out)} is not {np.dtype(dtype)} {shape}")
    return out


@dataclass(frozen=True)
class FrameSettings:
    """The exposure parameters of one frame, from its tags (and a logged temperature)."""

    exposure_s: float
    iso: float
    temperature_c: float | None = None


@dataclass(frozen=True)
class DarkModel:
    """The dark stage's model of one band (Section 2.8): level = b0 + b1 (g - 1) + D g t [+ temperature].

    ``read_noise_dn``: temporal noise of one raw site at the frame's ISO;
    ``offset_pattern_dn``: spatial spread of the pixel offsets about the mean
    level (the fixed pattern the dark model does not remove);
    ``sites_per_pixel``: raw sites averaged in a band pixel (2 for G).
    """

    bias_dn: float
    read_noise_dn: float
    bias_dn_sigma: float = 0.0
    bias_per_gain_dn: float = 0.0
    bias_per_gain_dn_sigma: float = 0.0
    dark_current_dn_per_s: float = 0.0
    dark_current_dn_per_s_sigma: float = 0.0
    temperature_bias_dn_per_c: float = 0.0
    temperature_dark_dn_per_s_per_c: float = 0.0
    temperature_reference_c: float = float("nan")
    offset_pattern_dn: float = 0.0
    sites_per_pixel: int = 1


@dataclass(frozen=True)
class ResponseModel:
    """What the linearity stage fitted for one band (Section 2.2), at the frame's ISO.

    ``conversion_gain_dn_per_e``: photon-transfer gain at ISO 100 (DN per
    electron); ``iso_gain_factor``: true gain over ISO/100 at this ISO (1 at
    ISO 100); ``nonlinearity_beta`` and ``full_scale_dn`` of
    ``s (1 - beta s / full_scale)``; ``saturation_dn`` the saturation level
    above dark (NaN when not reached).
    """

    conversion_gain_dn_per_e: float
    shutter_offset_s: float = 0.0
    shutter_offset_s_sigma: float = 0.0
    iso_gain_factor: float = 1.0
    iso_gain_factor_sigma: float = 0.0
    nonlinearity_beta: float = 0.0
    nonlinearity_beta_sigma: float = 0.0
    full_scale_dn: float = float("nan")
    saturation_dn: float = float("nan")


@dataclass(frozen=True)
class BandCalibration:
    """The calibration terms of one band, lens and medium: roll-off, immersion, R^-1.

    ``rolloff_coefficients`` (a0, a2, a4, a6, a8) for theta in degrees with
    ``rolloff_covariance``; ``calibrated_field_angle_deg`` the largest angle
    the roll-off was measured at; ``immersion_factor`` 1 in air;
    ``inverse_responsivity`` in W sr-1 m-2 nm-1 per DN s-1 (ISO 100); the
    ``rolloff_azimuth_*`` terms the azimuthal part of the roll-off (``rolloff_azimuth``).
    """

    rolloff_coefficients: np.ndarray
    inverse_responsivity: float
    inverse_responsivity_relative_sigma: float = 0.0
    rolloff_covariance: np.ndarray | None = None
    calibrated_field_angle_deg: float = float("inf")
    immersion_factor: float = 1.0
    immersion_factor_sigma: float = 0.0
    #: ``rolloff_azimuth``: g(theta, phi) = g(theta) (1 + A (theta / theta_ref) cos(phi - phi0)), the
    #: roll-off stage's odd term (its polynomial is the even part, fitted with that term removed)
    rolloff_azimuth_amplitude: float = 0.0
    rolloff_azimuth_amplitude_sigma: float = 0.0
    rolloff_azimuth_phi0_deg: float = 0.0
    rolloff_azimuth_phi0_deg_sigma: float = 0.0
    rolloff_azimuth_theta_ref_deg: float = 90.0


# --------------------------------------------------------------------------- the steps
def from_raw(image_dn, saturated=None) -> Measured:
    """A raw band image (DN) entering the chain.

    A float32 image (the band split's) stays float32 through the chain, anything else becomes float64.

    Parameters
    ----------
    image_dn : array_like
        The band image's raw readings (DN), black level included.
    saturated : array_like of bool, optional
        Band pixels with a CFA site at the white level; flagged :data:`FLAG_SATURATED`.

    Returns
    -------
    Measured
        The value in ``DN``, no variance yet, flags of the image's shape.
    """
    image = np.asarray(image_dn)
    value = image if image.dtype == np.float32 else image.astype(float)
    flags = np.zeros(value.shape, np.uint8)
    if saturated is not None:
        np.bitwise_or(flags, np.uint8(FLAG_SATURATED), out=flags, where=np.asarray(saturated, bool))
    return Measured(value=value, units="DN", flags=flags)


def subtract_dark(m: Measured, dark: DarkModel, frame: FrameSettings, effects, unlit_dn=None,
                  frame_black_dn=None) -> Measured:
    """Raw DN -> DN above the dark level of the dark model at the frame's ISO, exposure and temperature.

    Adds the random variances of the raw reading (per band pixel: read noise
    and, with the dark current, its electrons; the offset pattern) and the
    dark model's parameter uncertainty as the systematic ``dark_model`` term.
    The signal's shot noise needs the signal, so the next step adds it
    (:func:`add_shot_noise`).

    With ``bias_drift`` in the model and ``unlit_dn`` (Section 3.7) the
    frame's own black level replaces the model's: the level is the unlit
    pixels' mean (which moves with the frame's offset), and the standard
    error of that mean, their sample variance over their number, is the
    systematic term ``bias_drift`` (common to every pixel of this frame's
    band image, independent between frames). The dark model's parameter
    term then no longer applies to the level and is dropped. A lens without
    unlit pixels (a rectilinear region) gives the frame's black level as
    ``frame_black_dn`` instead.

    Parameters
    ----------
    m : Measured
        The raw band image (DN).
    dark : DarkModel
        The dark stage's model of the band.
    frame : FrameSettings
        Exposure time, ISO and temperature of the frame.
    effects : collection of str
        The names of ``model.effects``; this step owns ``dark_current``, ``temperature`` and ``bias_drift``.
    unlit_dn : array_like, optional
        Raw values (DN) of this band image's unlit pixels, outside the image circle; used with ``bias_drift``
        when there are at least two.
    frame_black_dn : tuple of float, optional
        ``(level_dn, variance_dn2)``: the level of the band pixels measured by the sensor's optically black
        pixels (DN) and the variance of that level (DN2); used with ``bias_drift`` when ``unlit_dn`` is not given.

    Returns
    -------
    Measured
        The signal above dark (DN), with the random terms ``read`` and ``dark`` and the systematic term
        ``dark_model`` or ``bias_drift``.
    """
    gain = gain_from_iso(frame.iso)
    current = dark.dark_current_dn_per_s if "dark_current" in effects else 0.0
    level = dark_model_level_dn(dark.bias_dn, dark.bias_per_gain_dn, current, gain, frame.exposure_s)
    if "temperature" in effects and frame.temperature_c is not None and np.isfinite(frame.temperature_c) \
            and np.isfinite(dark.temperature_reference_c):
        level += temperature_model_shift_dn(dark.temperature_bias_dn_per_c, dark.temperature_dark_dn_per_s_per_c,
                                            dark.temperature_reference_c, gain, frame.exposure_s, frame.temperature_c)
    sites = dark.sites_per_pixel
    if not m.unscaled:
        # a shift, not a scaling: the factors go into the value first
        m = m.transformed(m.value, 1.0)
    # the same for every pixel: scalars (broadcast), in DN^2 of the raw reading
    rand = dict(m.random_abs)
    rand["read"] = float(dark.read_noise_dn**2 / sites)
    rand["dark"] = float(dark.offset_pattern_dn**2)
    sys_abs = dict(m.systematic_abs)
    unlit = None if unlit_dn is None else np.asarray(unlit_dn, dtype=float).ravel()
    if "bias_drift" in effects and unlit is not None and unlit.size > 1:
        level = float(unlit.mean())
        sys_abs["bias_drift"] = float(unlit.var(ddof=1) / unlit.size)
    elif "bias_drift" in effects and frame_black_dn is not None:
        level = float(frame_black_dn[0])
        sys_abs["bias_drift"] = float(frame_black_dn[1])
    else:
        sys_abs["dark_model"] = float(dark.bias_dn_sigma**2 + ((gain - 1.0) * dark.bias_per_gain_dn_sigma) ** 2
                                      + ((gain * frame.exposure_s * dark.dark_current_dn_per_s_sigma) ** 2
                                         if "dark_current" in effects else 0.0))
    # a Python float keeps a float32 image float32 (NumPy 2 promotion)
    return m._replace(base=m.base - float(level), random_abs=rand, systematic_abs=sys_abs)


def add_shot_noise(m: Measured, dark: DarkModel, response: ResponseModel, frame: FrameSettings, effects) -> Measured:
    """Poisson noise of the electrons of a dark-corrected signal (DN): K_ISO * s per site, over the sites.

    K_ISO = K_100 * ISO/100 * f_ISO (photon-transfer gain, Janesick 2007);
    the dark current's electrons join the ``dark`` term.

    Parameters
    ----------
    m : Measured
        The signal above dark (DN), from :func:`subtract_dark`.
    dark : DarkModel
        The dark model (sites per band pixel, dark current).
    response : ResponseModel
        The linearity stage's fit (conversion gain K_100, ISO gain factor f_ISO).
    frame : FrameSettings
        Exposure time and ISO of the frame.
    effects : collection of str
        The names of ``model.effects`` (``iso_gain``, ``dark_current`` matter here).

    Returns
    -------
    Measured
        The same value with the random term ``shot`` (DN2; negative signals count as 0) and, with
        ``dark_current``, the dark electrons added to ``dark``.
    """
    k_iso = response.conversion_gain_dn_per_e * gain_from_iso(frame.iso) * (
        response.iso_gain_factor if "iso_gain" in effects else 1.0)
    sites = dark.sites_per_pixel
    rand = dict(m.random_abs)
    shot = np.clip(m.value, 0.0, None)
    shot *= float(k_iso / sites)
    rand["shot"] = m.in_base_units(shot)
    if "dark_current" in effects:
        dark_dn = dark.dark_current_dn_per_s * gain_from_iso(frame.iso) * frame.exposure_s
        rand["dark"] = rand.get("dark", 0.0) + m.in_base_units(float(k_iso * max(dark_dn, 0.0) / sites))
    return m._replace(random_abs=rand)


def flag_hot_pixels(m: Measured, hot_mask, effects) -> Measured:
    """Flag the dark stage's hot pixels (``hot_pixels`` effect); their values are kept, flagged.

    Parameters
    ----------
    m : Measured
        The band image.
    hot_mask : array_like or None
        The dark stage's hot-pixel mask (non-zero: hot), the band image's shape; None flags nothing.
    effects : collection of str
        The names of ``model.effects``; without ``hot_pixels`` nothing is flagged.

    Returns
    -------
    Measured
        The band image with :data:`FLAG_HOT` set on the hot pixels (``m`` itself when nothing is flagged).
    """
    if "hot_pixels" not in effects or hot_mask is None:
        return m
    return m.flagged(np.asarray(hot_mask) > 0, FLAG_HOT)


def flag_saturation(m: Measured, response: ResponseModel) -> Measured:
    """Flag dark-corrected signals at or above the saturation level found by the linearity stage.

    Parameters
    ----------
    m : Measured
        The signal above dark (DN).
    response : ResponseModel
        The linearity stage's fit; ``saturation_dn`` NaN (not reached) flags nothing.

    Returns
    -------
    Measured
        The band image with :data:`FLAG_SATURATED` set where the signal is at or above ``saturation_dn``.
    """
    if not np.isfinite(response.saturation_dn):
        return m
    return m.flagged(m.value >= float(response.saturation_dn), FLAG_SATURATED)


def linearise(m: Measured, response: ResponseModel, effects) -> Measured:
    """Inverse of the nonlinearity m = s (1 - beta s / F) (``nonlinearity`` effect), in DN above dark.

    s = 2 m / (1 + sqrt(1 - 4 beta m / F)); ds/dm = 1 / sqrt(1 - 4 beta m / F).
    A reading beyond the curve's top (4 beta m > F) has no inverse: NaN, flagged saturated.

    Parameters
    ----------
    m : Measured
        The signal above dark (DN), bent by the response.
    response : ResponseModel
        The linearity stage's fit: ``nonlinearity_beta`` (dimensionless), its sigma and ``full_scale_dn`` F (DN).
    effects : collection of str
        The names of ``model.effects``; without ``nonlinearity`` (or with beta 0) nothing changes.

    Returns
    -------
    Measured
        The linear signal s (DN), variances propagated with ds/dm, the shot term rescaled to the linear signal,
        and the relative systematic term ``nonlinearity``.

    Raises
    ------
    pipeline.errors.ImpossibleResult
        When the full scale is not a positive number.
    """
    beta, full = response.nonlinearity_beta, response.full_scale_dn
    if "nonlinearity" not in effects or beta == 0.0:
        return m
    if not np.isfinite(full) or full <= 0:
        raise ImpossibleResult(None, f"nonlinearity full scale {full} DN is not positive: rerun the linearity stage")
    beta, full = float(beta), float(full)
    disc = 1.0 - 4.0 * beta * m.value / full
    beyond = disc <= 0
    root = np.sqrt(np.where(beyond, np.nan, disc))
    s = 2.0 * m.value / (1.0 + root)
    out = m.transformed(s, 1.0 / root)
    if "shot" in m.random_abs:
        # the electrons' Poisson noise is k s in the linear signal s (the sensor bends the noisy signal):
        # the shot term k m of the bent reading m becomes k s, not k m slope^2
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.where(m.value > 0, s / np.where(m.value > 0, m.value, 1.0), 1.0)
        out.random_abs["shot"] = m.random_var["shot"] * ratio
    # ds/dbeta = s^2 / (F root): relative to s, s / (F root)
    out.systematic_rel["nonlinearity"] = np.square(s / (full * root) * float(response.nonlinearity_beta_sigma))
    return out.flagged(beyond, FLAG_SATURATED)


def normalise_exposure(m: Measured, response: ResponseModel, frame: FrameSettings, effects) -> Measured:
    """Eq. (2) with the true exposure and gain: DN -> DN s-1 at ISO 100.

    y = s / ((t + dt) * ISO/100 * f_ISO), with the shutter offset dt
    (``shutter_offset``) and the per-ISO gain factor f_ISO (``iso_gain``).

    Parameters
    ----------
    m : Measured
        The linear signal above dark (DN).
    response : ResponseModel
        The linearity stage's fit: shutter offset dt (s), ISO gain factor f_ISO and their sigmas.
    frame : FrameSettings
        Nominal exposure time t (s) and ISO of the frame.
    effects : collection of str
        The names of ``model.effects``; dt and f_ISO apply only with their effects.

    Returns
    -------
    Measured
        The signal rate in DN s-1 at ISO 100, with the relative systematic terms ``shutter_offset`` and
        ``iso_gain`` of the effects applied.

    Raises
    ------
    pipeline.errors.ImpossibleResult
        When the true exposure t + dt is not positive.
    """
    offset = response.shutter_offset_s if "shutter_offset" in effects else 0.0
    factor = response.iso_gain_factor if "iso_gain" in effects else 1.0
    exposure = frame.exposure_s + offset
    if exposure <= 0:
        raise ImpossibleResult(None, f"true exposure {exposure:g} s (nominal {frame.exposure_s:g} s + shutter offset "
                                     f"{offset:g} s) is not positive")
    rel = {}
    if "shutter_offset" in effects:
        rel["shutter_offset"] = float(response.shutter_offset_s_sigma / exposure) ** 2
    if "iso_gain" in effects:
        rel["iso_gain"] = float(response.iso_gain_factor_sigma / factor) ** 2
    return m.scaled(float(1.0 / (exposure * gain_from_iso(frame.iso) * factor)), "DN s-1", relative_systematic=rel)


def correct_flat_field(m: Measured, flat_field, effects, prnu_sigma_rel: float = 0.0,
                       flat_field_sigma=None, sites: int = 1) -> Measured:
    """Divide by the relative pixel sensitivity (``prnu``: the linearity stage's flat field, mean 1).

    Where the flat field was not measured (NaN: outside the region the
    linearity stage saw), the pixel's sensitivity is unknown by the fitted
    PRNU spread: value kept, random term ``prnu`` = (value * prnu_sigma_rel)^2 / sites.
    Where it was measured, ``prnu`` is the noise of the measured flat field,
    (value * flat_field_sigma)^2: fixed from frame to frame, random from pixel
    to pixel.

    Parameters
    ----------
    m : Measured
        The band image (any units; kept).
    flat_field : array_like or None
        Relative sensitivity F of each band pixel (dimensionless, mean 1; NaN or non-positive where not
        measured); None leaves the image as it is.
    effects : collection of str
        The names of ``model.effects``; without ``prnu`` nothing changes.
    prnu_sigma_rel : float, default 0.0
        Relative spread of the sensitivity of one raw site (the linearity stage's S^2 / sites term).
    flat_field_sigma : array_like, optional
        Standard uncertainty of the measured flat field (dimensionless), the band image's shape.
    sites : int, default 1
        Raw sites averaged in a band pixel (2 for G): the pixel averages their patterns.

    Returns
    -------
    Measured
        The band image over F, with the relative random term ``prnu``.
    """
    if "prnu" not in effects or flat_field is None:
        return m
    inverse, rel = flat_field_terms(flat_field, flat_field_sigma, prnu_sigma_rel, sites, np.result_type(np.float32, m.base))
    out = m.scaled(inverse, m.units)
    return out._replace(random_rel={**out.random_rel, "prnu": rel})


def flat_field_terms(flat_field, flat_field_sigma=None, prnu_sigma_rel: float = 0.0, sites: int = 1, dtype=np.float32):
    """What :func:`correct_flat_field` multiplies by (1 / F, 1 where F is not measured) and its ``prnu`` relative variance.

    Parameters
    ----------
    flat_field : array_like
        Relative sensitivity F of each band pixel (dimensionless; NaN or non-positive where not measured).
    flat_field_sigma : array_like, optional
        Standard uncertainty of the measured F (dimensionless); None: no term where measured.
    prnu_sigma_rel : float, default 0.0
        Relative sensitivity spread of one raw site, used where F is not measured.
    sites : int, default 1
        Raw sites averaged in a band pixel.
    dtype : numpy dtype, default numpy.float32
        Float type of the returned maps.

    Returns
    -------
    inverse : numpy.ndarray
        1 / F, 1 where F is not measured (dimensionless).
    relative_variance : numpy.ndarray
        The ``prnu`` term's relative variance: (sigma_F / F)^2 where measured, prnu_sigma_rel^2 / sites elsewhere.
    """
    flat = np.asarray(flat_field, dtype=dtype)
    measured = np.isfinite(flat) & (flat > 0)
    flat = np.where(measured, flat, 1.0).astype(dtype, copy=False)
    flat_rel = 0.0 if flat_field_sigma is None else np.nan_to_num(np.asarray(flat_field_sigma, dtype)) / flat
    rel = np.where(measured, np.square(flat_rel), float(prnu_sigma_rel) ** 2 / sites).astype(dtype, copy=False)
    return (1.0 / flat).astype(dtype, copy=False), rel


@dataclass(frozen=True)
class RolloffMap:
    """What the roll-off step divides a band image by, for each pixel: 1 / g(theta, phi), its terms, its flags.

    ``inverse`` 1 / (g(theta) [1 + A (theta / theta_ref) cos(phi - phi0)]);
    ``relative_var`` the systematic terms as relative variances (``rolloff``
    and, with the azimuthal term, ``rolloff_azimuth``); ``flags`` the bits
    :data:`FLAG_OUTSIDE_IMAGE_CIRCLE` (theta NaN) and
    :data:`FLAG_BEYOND_CALIBRATED_ANGLE`. It depends only on the lens, band
    and medium, so the calibration bundle stores it (:func:`rolloff_map`).
    """

    inverse: np.ndarray
    relative_var: dict
    flags: np.ndarray


def rolloff_map(theta_deg, calibration: BandCalibration, phi_deg=None, effects=(), dtype=float,
                theta_deg_sigma=None) -> RolloffMap:
    """Eq. (13) and its azimuthal term on a band image's angles, with the relative variances from the covariance.

    With ``theta_deg_sigma`` also the systematic term
    ``field_angle``: (g'(theta) / g * sigma_theta)^2, the roll-off read at a
    field angle that is itself uncertain (the azimuthal factor's own
    dependence on theta is left out: A theta / theta_ref changes by A
    sigma_theta / theta_ref, below 1e-5 for the fitted A and sigma_theta).
    Evaluated in float64 (the variance polynomial cancels), returned in ``dtype``.

    Parameters
    ----------
    theta_deg : array_like
        Field angle of each band pixel (degree); NaN outside the image circle.
    calibration : BandCalibration
        The band's roll-off coefficients, covariance, calibrated field angle and azimuthal term.
    phi_deg : array_like, optional
        Azimuth of each band pixel (degree); needed for the azimuthal term.
    effects : collection of str, default ()
        The names of ``model.effects``; the azimuthal term applies with ``rolloff_azimuth``.
    dtype : numpy dtype, default float
        Float type of the returned maps.
    theta_deg_sigma : array_like, optional
        The geometric fit's standard uncertainty of each pixel's field angle (degree), common to all frames.

    Returns
    -------
    RolloffMap
        1 / g(theta, phi) (dimensionless), the relative variances ``rolloff`` (and ``field_angle``,
        ``rolloff_azimuth``) and the geometry flags.
    """
    theta = np.asarray(theta_deg, dtype=float)
    if calibration.rolloff_covariance is None:
        g, g_sigma = rolloff_on_image(calibration.rolloff_coefficients, theta), np.zeros(theta.shape)
    else:
        g, g_sigma = rolloff_on_image(calibration.rolloff_coefficients, theta, calibration.rolloff_covariance)
    rel = {"rolloff": np.square(g_sigma / g).astype(dtype, copy=False)}
    if theta_deg_sigma is not None:
        slope = rolloff_slope_on_image(calibration.rolloff_coefficients, theta)
        rel["field_angle"] = np.square(slope / g * np.nan_to_num(np.asarray(theta_deg_sigma, float))).astype(
            dtype, copy=False)
    if "rolloff_azimuth" in effects and phi_deg is not None and calibration.rolloff_azimuth_amplitude != 0.0:
        c = calibration
        u = np.minimum(theta, 100.0) / c.rolloff_azimuth_theta_ref_deg
        dphi = np.radians(np.asarray(phi_deg, dtype=float) - c.rolloff_azimuth_phi0_deg)
        a = 1.0 + c.rolloff_azimuth_amplitude * u * np.cos(dphi)
        rel["rolloff_azimuth"] = (((u * np.cos(dphi) * c.rolloff_azimuth_amplitude_sigma) ** 2
                                   + (c.rolloff_azimuth_amplitude * u * np.sin(dphi)
                                      * np.radians(c.rolloff_azimuth_phi0_deg_sigma)) ** 2) / a**2).astype(dtype, copy=False)
        g = g * a
    flags = np.where(np.isfinite(theta), 0, FLAG_OUTSIDE_IMAGE_CIRCLE).astype(np.uint8)
    flags[theta > calibration.calibrated_field_angle_deg] |= np.uint8(FLAG_BEYOND_CALIBRATED_ANGLE)  # NaN: False
    return RolloffMap(inverse=(1.0 / g).astype(dtype, copy=False), relative_var=rel, flags=flags)


def correct_rolloff(m: Measured, theta_deg, calibration: BandCalibration, phi_deg=None, effects=(),
                    rolloff: RolloffMap | None = None) -> Measured:
    """Divide by the roll-off g(theta), Eq. (13) (Section 2.4); systematic term ``rolloff`` from its covariance.

    With ``rolloff_azimuth`` (and the pixel azimuths ``phi_deg``) also by its
    azimuthal factor 1 + A (theta / theta_ref) cos(phi - phi0); systematic
    term ``rolloff_azimuth`` from the uncertainties of A and phi0.

    Pixels without a viewing direction (theta NaN) are flagged outside the
    image circle; field angles beyond the calibrated one are flagged.

    Parameters
    ----------
    m : Measured
        The band image (any units; kept).
    theta_deg : array_like
        Field angle of each band pixel (degree), NaN outside the image circle.
    calibration : BandCalibration
        The band's roll-off calibration.
    phi_deg : array_like, optional
        Azimuth of each band pixel (degree).
    effects : collection of str, default ()
        The names of ``model.effects``.
    rolloff : RolloffMap, optional
        The :func:`rolloff_map` of these pixels, when already at hand (``theta_deg`` and ``phi_deg`` are then
        not used).

    Returns
    -------
    Measured
        The band image over g(theta, phi), with the roll-off's relative systematic terms and geometry flags.
    """
    if rolloff is None:
        rolloff = rolloff_map(theta_deg, calibration, phi_deg, effects, np.result_type(np.float32, m.base))
    out = m.scaled(rolloff.inverse, m.units, relative_systematic=rolloff.relative_var)
    return out.flagged_by(rolloff.flags)


@dataclass(frozen=True)
class PixelFactors:
    """The frame-independent per-pixel part of the chain, taken once: flat field, hot pixels and roll-off together.

    ``inverse`` the product of the flat-field step's 1 / F (``prnu``) and the
    roll-off step's 1 / g(theta, phi); ``systematic_rel`` the roll-off's
    relative variances (:attr:`RolloffMap.relative_var`); ``random_rel`` the
    flat field's (``prnu``, empty without the effect); ``flags`` the roll-off
    map's geometry bits ORed with :data:`FLAG_HOT` of the hot-pixel mask
    (``hot_pixels``; None for a caller that keeps these pixels apart by other means and
    needs no flag map: ``apply`` with the sphere grid only). :func:`measure_band` with them applies in one step what
    :func:`flag_hot_pixels`, :func:`correct_flat_field` and
    :func:`correct_rolloff` apply in three: the same factors and terms (the
    product of the two maps is rounded once in float32).
    """

    inverse: np.ndarray
    systematic_rel: dict
    random_rel: dict
    flags: np.ndarray

    def window(self, key) -> "PixelFactors":
        """These factors on a window of the image (views).

        Parameters
        ----------
        key : slice or tuple of slice
            A slice of rows or a (rows, columns) pair of slices.

        Returns
        -------
        PixelFactors
            The factors, terms and flags of the window (scalars kept as they are).
        """
        def cut(x):
            return x[key] if np.ndim(x) else x
        return PixelFactors(cut(self.inverse), {k: cut(v) for k, v in self.systematic_rel.items()},
                            {k: cut(v) for k, v in self.random_rel.items()}, cut(self.flags))


def pixel_factors(rolloff: RolloffMap, effects, *, hot_mask=None, flat_field=None, flat_field_sigma=None,
                  prnu_sigma_rel: float = 0.0, sites: int = 1, dtype=np.float32) -> PixelFactors:
    """The :class:`PixelFactors` of a band image from its roll-off map and, per ``effects``, flat field and hot pixels.

    Parameters
    ----------
    rolloff : RolloffMap
        The band image's :func:`rolloff_map`.
    effects : collection of str
        The names of ``model.effects`` (``prnu`` and ``hot_pixels`` matter here).
    hot_mask : array_like, optional
        The dark stage's hot-pixel mask (non-zero: hot).
    flat_field : array_like, optional
        Relative sensitivity F of each band pixel (dimensionless; NaN where not measured).
    flat_field_sigma : array_like, optional
        Standard uncertainty of the measured F (dimensionless).
    prnu_sigma_rel : float, default 0.0
        Relative sensitivity spread of one raw site, used where F is not measured.
    sites : int, default 1
        Raw sites averaged in a band pixel.
    dtype : numpy dtype, default numpy.float32
        Float type of the maps.

    Returns
    -------
    PixelFactors
        1 / (F g), the roll-off's systematic and the flat field's random relative variances, and the flags.
    """
    inverse = np.asarray(rolloff.inverse, dtype)
    flags = np.asarray(rolloff.flags, np.uint8)
    random_rel = {}
    if "prnu" in effects and flat_field is not None:
        flat_inverse, random_rel["prnu"] = flat_field_terms(flat_field, flat_field_sigma, prnu_sigma_rel, sites, dtype)
        inverse = np.multiply(inverse, flat_inverse, dtype=dtype)
    if "hot_pixels" in effects and hot_mask is not None:
        flags = flags | np.where(np.asarray(hot_mask) > 0, np.uint8(FLAG_HOT), np.uint8(0))
    rel = {k: np.asarray(v, dtype) for k, v in rolloff.relative_var.items()}
    return PixelFactors(inverse=inverse, systematic_rel=rel, random_rel=random_rel, flags=flags)


def correct_pixel_factors(m: Measured, factors: PixelFactors) -> Measured:
    """Hot pixels, flat field and roll-off in one step (:class:`PixelFactors`; ``flags`` None: no flag added).

    Parameters
    ----------
    m : Measured
        The band image (any units; kept).
    factors : PixelFactors
        The frame-independent per-pixel factors of the image, from :func:`pixel_factors`.

    Returns
    -------
    Measured
        The band image times ``factors.inverse``, with their terms and flags.
    """
    out = m.scaled(factors.inverse, m.units, relative_systematic=factors.systematic_rel)
    if factors.random_rel:
        out = out._replace(random_rel={**out.random_rel, **factors.random_rel})
    return out if factors.flags is None else out.flagged_by(factors.flags)


def correct_immersion(m: Measured, calibration: BandCalibration, medium: str) -> Measured:
    """In water multiply by the immersion factor I, Eq. (4) and (11); term ``immersion_factor``. In air, nothing.

    Parameters
    ----------
    m : Measured
        The band image (any units; kept).
    calibration : BandCalibration
        The band's immersion factor I (dimensionless) and its sigma.
    medium : str
        ``"water"`` or ``"air"``.

    Returns
    -------
    Measured
        The band image times I in water, with the relative systematic term ``immersion_factor``; ``m`` in air.

    Raises
    ------
    pipeline.errors.ImpossibleResult
        When the immersion factor is not a positive number.
    """
    if medium != "water":
        return m
    i = calibration.immersion_factor
    if not np.isfinite(i) or i <= 0:
        raise ImpossibleResult(None, f"immersion factor {i} is not positive: rerun the immersion stage")
    rel = float(calibration.immersion_factor_sigma / i) ** 2
    return m.scaled(float(i), m.units, relative_systematic={"immersion_factor": rel})


def check_inverse_responsivity(value: float, where: str = "") -> None:
    """A non-positive (or non-finite) R^-1 is no calibration: stop with a clear message.

    Parameters
    ----------
    value : float
        The inverse responsivity R^-1 (W sr-1 m-2 nm-1 per DN s-1).
    where : str, default ""
        Where it comes from, put in the message (with a trailing space, e.g. ``"of band R "``).

    Raises
    ------
    pipeline.errors.ImpossibleResult
        When ``value`` is not finite or not positive.
    """
    if not np.isfinite(value) or value <= 0:
        raise ImpossibleResult(None, f"inverse responsivity R^-1 {where}is {value}, not positive: "
                                     "rerun the absolute stage")


def to_radiance(m: Measured, calibration: BandCalibration) -> Measured:
    """Eq. (9) turned round: L = R^-1 y, in W sr-1 m-2 nm-1; term ``inverse_responsivity`` (its budget).

    Parameters
    ----------
    m : Measured
        The corrected signal rate y (DN s-1 at ISO 100).
    calibration : BandCalibration
        The band's inverse responsivity R^-1 (W sr-1 m-2 nm-1 per DN s-1) and its relative sigma.

    Returns
    -------
    Measured
        Spectral radiance L (W sr-1 m-2 nm-1), with the relative systematic term ``inverse_responsivity``.

    Raises
    ------
    pipeline.errors.ImpossibleResult
        When R^-1 is not a positive number.
    """
    check_inverse_responsivity(calibration.inverse_responsivity)
    rel = float(calibration.inverse_responsivity_relative_sigma) ** 2
    return m.scaled(float(calibration.inverse_responsivity), "W sr-1 m-2 nm-1",
                    relative_systematic={"inverse_responsivity": rel})


# --------------------------------------------------------------------------- the chain
def measure_band(image_dn, frame: FrameSettings, dark: DarkModel, response: ResponseModel,
                 calibration: BandCalibration, theta_deg, medium: str, effects, *, saturated=None,
                 hot_mask=None, flat_field=None, prnu_sigma_rel: float = 0.0, phi_deg=None,
                 flat_field_sigma=None, rolloff: RolloffMap | None = None, unlit_dn=None,
                 frame_black_dn=None, factors: PixelFactors | None = None) -> Measured:
    """One band image of one lens from raw DN to spectral radiance: the whole inverse of Eq. (4).

    Parameters
    ----------
    image_dn : array_like
        The band image's raw readings (DN).
    frame : FrameSettings
        Exposure time, ISO and temperature of the frame.
    dark : DarkModel
        The dark stage's model of the band.
    response : ResponseModel
        The linearity stage's fit of the band at the frame's ISO.
    calibration : BandCalibration
        The band's roll-off, immersion factor and R^-1 for the lens and medium.
    theta_deg : array_like
        Field angle of each band pixel (degree), NaN outside the image circle.
    medium : str
        ``"air"`` or ``"water"``.
    effects : collection of str
        The names of ``model.effects``.
    saturated : array_like of bool, optional
        Band pixels with a CFA site at the white level.
    hot_mask : array_like, optional
        The dark stage's hot-pixel mask.
    flat_field : array_like, optional
        Relative sensitivity of each band pixel (dimensionless, NaN where not measured).
    prnu_sigma_rel : float, default 0.0
        Relative sensitivity spread of one raw site.
    phi_deg : array_like, optional
        Azimuth of each band pixel (degree).
    flat_field_sigma : array_like, optional
        Standard uncertainty of the flat field (dimensionless).
    rolloff : RolloffMap, optional
        The :func:`rolloff_map` of the image's pixels when already at hand (the bundle stores it).
    unlit_dn : array_like, optional
        Raw values (DN) of the band image's unlit pixels (``bias_drift``, :func:`subtract_dark`).
    frame_black_dn : tuple of float, optional
        The frame's black level (DN) and its variance (DN2) from optically black pixels (:func:`subtract_dark`).
    factors : PixelFactors, optional
        The :func:`pixel_factors` of the image's pixels (hot pixels, flat field and roll-off taken once for
        many frames); ``hot_mask``, the flat field, ``rolloff``, ``theta_deg`` and ``phi_deg`` are then not used.

    Returns
    -------
    Measured
        Spectral radiance (W sr-1 m-2 nm-1) of each band pixel with its named random and systematic
        variances and quality flags.
    """
    effects = tuple(effects)
    m = from_raw(image_dn, saturated)
    m = subtract_dark(m, dark, frame, effects, unlit_dn, frame_black_dn)
    m = add_shot_noise(m, dark, response, frame, effects)
    if factors is None:
        m = flag_hot_pixels(m, hot_mask, effects)
    m = flag_saturation(m, response)
    m = linearise(m, response, effects)
    m = normalise_exposure(m, response, frame, effects)
    if factors is None:
        m = correct_flat_field(m, flat_field, effects, prnu_sigma_rel, flat_field_sigma, dark.sites_per_pixel)
        m = correct_rolloff(m, theta_deg, calibration, phi_deg, effects, rolloff)
    else:
        m = correct_pixel_factors(m, factors)
    m = correct_immersion(m, calibration, medium)
    return to_radiance(m, calibration)
