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

from pipeline.effects.base import Effect, register


@register
class ClockOffset(Effect):
    name = "clock_offset"
    experiments = ("field",)
    #: camera clock minus true time (s), after the time-zone offset of site.yaml
    truth_defaults = {"offset_s": 30.0}
    amplitude_name = "clock_offset_s"
    amplitude_units = "s"

    def camera_clock_offset_s(self) -> float:
        return float(self.params["offset_s"])


@register
class SpectralMismatch(Effect):
    name = "spectral_mismatch"
    experiments = ("field",)
    #: change over one hour of the exponent a of a factor (lambda / 550 nm)^(-a) on the sky spectrum
    truth_defaults = {"exponent_change_per_h": 1.5}
    amplitude_name = "spectral_mismatch_factor"
    amplitude_units = "1"

    def sky_spectral_exponent(self, hours_since_start: float) -> float:
        return float(self.params["exponent_change_per_h"]) * float(hours_since_start)
