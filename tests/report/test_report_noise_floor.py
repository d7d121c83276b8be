"""The report's noise floor: SNR against radiance from NER and the limit of detection."""

from __future__ import annotations

import numpy as np
import xarray as xr

from pipeline.report import snr_against_radiance
from pipeline.report.render import render_fragment
from pipeline.report.sections.noise_floor import noise_floor_blocks


def test_snr_curve_passes_through_ner_and_the_limit_of_detection():
    ner, lod = 1.1e-7, 4.6e-7          # the paper's R band (Section 3.8)
    np.testing.assert_allclose(snr_against_radiance([ner, lod], ner, lod, 3.0), [1.0, 3.0], rtol=1e-12)
    # far above the floor the noise is shot noise: SNR grows as sqrt(L)
    high = snr_against_radiance([1e-2, 4e-2], ner, lod, 3.0)
    assert abs(high[1] / high[0] - 2.0) < 0.01


def test_noise_floor_section_lists_every_lens_and_band_and_draws_the_curve():
    bundle = xr.Dataset(
        {"noise_equivalent_radiance": (("lens", "band"), [[1.1e-7, 4.5e-8, 1.1e-7], [1.2e-7, 4.6e-8, 1.0e-7]]),
         "limit_of_detection": (("lens", "band"), [[4.6e-7, 1.8e-7, 4.6e-7], [4.7e-7, 1.9e-7, 4.4e-7]],
                                {"snr": 3.0, "iso": 100.0, "exposure_s": 1.0})},
        coords={"lens": ["far", "close"], "band": ["R", "G", "B"]})
    html = render_fragment(noise_floor_blocks(bundle))
    assert html.count("<tr>") >= 7 and "4.5e-08" in html and "1.9e-07" in html
    assert "<img" in html and "ISO 100, 1 s" in html
    assert noise_floor_blocks(None) == []
