"""The simulator's default camera: facts from the papers in one place.

Numbers come from ``docs/design.md`` ("The simulator's default camera")
and from Larouche et al. (2024): Section 3.7 for the dark frames (black level
800.2 to 801.9 ADU from 1/4000 s to 2 s at ISO 100; 801.0 to 823.4 ADU between
ISO 100 and 3200 at 1 s), Section 3.1 for the linearity sweeps and the
saturation level, Table 1 for the responsivities.

The sensor parameters were chosen so that those published figures come out of
the simulator: a bias of 800.2 ADU that does not depend on gain plus a dark
current of 0.9 e-/s at a conversion gain of 0.8 ADU/e- at ISO 100 gives
800.9 ADU at 1 s, 801.6 ADU at 2 s and 823.2 ADU at ISO 3200 and 1 s.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

#: Raw lens image size (pixels) on which the published fits were made.
RAW_SIZE_PX = 3456

#: 14-bit analogue-to-digital converter.
ADC_MAX_DN = 2**14 - 1


@dataclass(frozen=True)
class SensorParams:
    """Electronic parameters of one sensor (both lenses share them)."""

    bias_dn: float = 800.2
    #: system gain at ISO 100 (ADU per electron); gain is proportional to ISO.
    conversion_gain_dn_per_e_iso100: float = 0.8
    #: temporal read noise before the amplifier (electrons, RMS).
    read_noise_e: float = 2.0
    #: offset fixed-pattern noise before the amplifier (electrons, RMS): grows with gain.
    offset_fpn_e: float = 1.4
    #: offset fixed-pattern noise after the amplifier (ADU, RMS): independent of gain.
    offset_fpn_dn: float = 1.5
    adc_max_dn: int = ADC_MAX_DN
    #: full-well capacity (electrons); None: the well never fills before the ADC clips (the default
    #: camera, whose exposure sweep saturates at the 14-bit top). A finite well clips each pixel's
    #: electrons, so at low ISO the signal can plateau below the white level.
    full_well_e: float | None = None

    def conversion_gain(self, iso: float) -> float:
        """Nominal ADU per electron at ``iso``."""
        return self.conversion_gain_dn_per_e_iso100 * iso / 100.0


@dataclass(frozen=True)
class RadiometricParams:
    """Band responsivities from Table 1 of the paper (ISO 100)."""

    #: ADU/s per W sr-1 m-2 nm-1 at ISO 100 (Table 1: 61e3, 65e3, 21.9e3 ADU/s for
    #: 0.74, 0.48, 0.26 mW sr-1 m-2 nm-1).
    responsivity_dn_s_per_radiance: dict = field(
        default_factory=lambda: {
            "R": 61e3 / 0.74e-3,
            "G": 65e3 / 0.48e-3,
            "B": 21.9e3 / 0.26e-3,
        }
    )
    #: effective band radiance of the lab's integrating sphere (W sr-1 m-2 nm-1) through the close lens's
    #: response; the far lens sees it through its own (simulate.absolute.lens_band_radiance).
    sphere_band_radiance: dict = field(
        default_factory=lambda: {"R": 0.74e-3, "G": 0.48e-3, "B": 0.26e-3}
    )


@dataclass(frozen=True)
class DarkPlan:
    """Dark-frame settings of Section 2.8 and Fig. 9 (ISO, exposure time)."""

    exposures_s: tuple = (1 / 4000, 1 / 1000, 1 / 240, 1 / 60, 1 / 15, 1 / 5, 1.0, 2.0)
    exposure_sweep_iso: float = 100.0
    isos: tuple = (100.0, 200.0, 400.0, 800.0, 1600.0, 3200.0)
    gain_sweep_exposure_s: float = 1.0
    frames_per_setting: int = 15

    def settings(self) -> list[tuple[float, float]]:
        """Unique (iso, exposure_s) pairs in acquisition order."""
        out = [(self.exposure_sweep_iso, t) for t in self.exposures_s]
        out += [(iso, self.gain_sweep_exposure_s) for iso in self.isos]
        seen, unique = set(), []
        for s in out:
            if s not in seen:
                seen.add(s)
                unique.append(s)
        return unique


@dataclass(frozen=True)
class LinearityPlan:
    """Linearity sweeps of Section 2.2."""

    exposures_s: tuple = (0.00833, 0.01667, 0.03333, 0.06667, 0.1, 0.2, 0.5)
    exposure_sweep_iso: float = 100.0
    isos: tuple = (100.0, 200.0, 400.0, 800.0, 1600.0, 3200.0)
    gain_sweep_exposure_s: float = 0.00833
    frames_per_setting: int = 4
    #: source band radiance as a fraction of the absolute-calibration sphere: the
    #: exposure sweep reaches saturation in G at 500 ms as in Fig. 3.
    exposure_source_fraction: float = 0.5
    #: dimmer source for the gain sweep so that ISO 3200 stays below saturation.
    gain_source_fraction: float = 0.5


@dataclass(frozen=True)
class Camera:
    sensor: SensorParams = field(default_factory=SensorParams)
    radiometry: RadiometricParams = field(default_factory=RadiometricParams)
    make: str = "Insta360"
    model: str = "ONE"
    serial: str = "SIM-0001"
    lens_names: tuple = ("far", "close")
    #: full-resolution lens region (raw pixels, square)
    lens_px_full: int = RAW_SIZE_PX

    def to_dict(self) -> dict:
        return asdict(self)
