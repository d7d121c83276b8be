"""The measurement chain (inverse of Eq. 4): each step on hand values, and the whole chain
inverting a forward model written here, independently of the simulator."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.errors import ImpossibleResult
from pipeline.radiometry import measurement as mm

ALL = ("dark_current", "hot_pixels", "shutter_offset", "iso_gain", "nonlinearity", "prnu")


def _dark(**kw):
    base = dict(bias_dn=800.0, read_noise_dn=2.0, bias_dn_sigma=0.1, bias_per_gain_dn=0.7,
                bias_per_gain_dn_sigma=0.05, dark_current_dn_per_s=0.5, dark_current_dn_per_s_sigma=0.02)
    base.update(kw)
    return mm.DarkModel(**base)


def _response(**kw):
    base = dict(conversion_gain_dn_per_e=0.8, shutter_offset_s=4e-4, shutter_offset_s_sigma=2e-5,
                iso_gain_factor=1.05, iso_gain_factor_sigma=0.005, nonlinearity_beta=0.05,
                nonlinearity_beta_sigma=0.002, full_scale_dn=15000.0, saturation_dn=15000.0)
    base.update(kw)
    return mm.ResponseModel(**base)


def _calibration(**kw):
    base = dict(rolloff_coefficients=np.array([1.0, -5e-5, 0.0, 0.0, 0.0]), inverse_responsivity=1.2e-8,
                inverse_responsivity_relative_sigma=0.1, rolloff_covariance=np.diag([0.0, 1e-12, 0, 0, 0]),
                calibrated_field_angle_deg=80.0, immersion_factor=1.7, immersion_factor_sigma=0.017)
    base.update(kw)
    return mm.BandCalibration(**base)


def test_subtract_dark_hand_value():
    frame = mm.FrameSettings(exposure_s=1.0, iso=400.0)
    m = mm.subtract_dark(mm.from_raw(np.array([900.0])), _dark(), frame, ("dark_current",))
    # 800 + 0.7 * 3 + 0.5 * 4 * 1 = 804.1
    np.testing.assert_allclose(m.value, [95.9])
    np.testing.assert_allclose(m.random_var["read"], [4.0])
    np.testing.assert_allclose(m.systematic_var["dark_model"], [0.1**2 + (3 * 0.05) ** 2 + (4 * 0.02) ** 2])
    # without dark_current in the model the level is b0 + b1 (g - 1)
    m = mm.subtract_dark(mm.from_raw(np.array([900.0])), _dark(), frame, ())
    np.testing.assert_allclose(m.value, [97.9])


def test_subtract_dark_temperature():
    frame = mm.FrameSettings(exposure_s=2.0, iso=100.0, temperature_c=30.0)
    dark = _dark(temperature_bias_dn_per_c=0.2, temperature_dark_dn_per_s_per_c=0.1, temperature_reference_c=20.0)
    m = mm.subtract_dark(mm.from_raw(np.array([900.0])), dark, frame, ("dark_current", "temperature"))
    # 800 + 0 + 0.5 * 2 + (0.2 + 0.1 * 2) * 10 = 805
    np.testing.assert_allclose(m.value, [95.0])


def test_bias_drift_takes_the_frames_own_black_level_from_the_unlit_pixels():
    """A frame whose black level sits 7 DN above the dark model (bias drift): with ``bias_drift`` and the
    unlit corners the level is theirs (the model's 804.1 + 7, read-noise scatter of 2 DN drawn here about
    it, so the mean of 4000 is within 4 x 2 / sqrt(4000) = 0.13 DN of it), the term bias_drift is their
    sample variance over their number (4 / 4000 = 1e-3 DN^2, within the chi-square spread of a variance
    from 4000 draws, 4 sqrt(2 / 3999) = 9 %) and replaces dark_model; without the effect the offset stays."""
    rng = np.random.default_rng(7)
    frame = mm.FrameSettings(exposure_s=1.0, iso=400.0)
    unlit = 804.1 + 7.0 + 2.0 * rng.standard_normal(4000)
    raw = np.array([904.1 + 7.0])
    m = mm.subtract_dark(mm.from_raw(raw), _dark(), frame, ("dark_current", "bias_drift"), unlit_dn=unlit)
    assert abs(m.value[0] - 100.0) < 4 * 2.0 / np.sqrt(4000)
    assert "dark_model" not in m.systematic_var
    np.testing.assert_allclose(m.systematic_var["bias_drift"], [4.0 / 4000], rtol=4 * np.sqrt(2 / 3999))
    stale = mm.subtract_dark(mm.from_raw(raw), _dark(), frame, ("dark_current",), unlit_dn=unlit)
    np.testing.assert_allclose(stale.value, [107.0])
    # through the whole chain: the same pixel with and without the frame's offset gives the same radiance
    cal, resp = _calibration(), _response()
    effects = ("dark_current", "bias_drift")
    shifted = mm.measure_band(raw, frame, _dark(), resp, cal, np.array([10.0]), "air", effects, unlit_dn=unlit)
    plain = mm.measure_band(raw - 7.0, frame, _dark(), resp, cal, np.array([10.0]), "air", effects,
                            unlit_dn=unlit - 7.0)
    np.testing.assert_allclose(shifted.value, plain.value, rtol=1e-9)


def test_shot_noise_per_site():
    frame = mm.FrameSettings(exposure_s=1.0, iso=200.0)
    m = mm.Measured(value=np.array([1000.0, -5.0]), units="DN")
    out = mm.add_shot_noise(m, _dark(sites_per_pixel=2), _response(), frame, ("iso_gain",))
    # K = 0.8 * 2 * 1.05 = 1.68 DN/e-; 1000 DN over 2 sites -> 1.68 * 1000 / 2
    np.testing.assert_allclose(out.random_var["shot"], [840.0, 0.0])


def test_flags():
    m = mm.from_raw(np.array([1.0, 2.0, 3.0]), saturated=np.array([False, False, True]))
    m = mm.flag_hot_pixels(m, np.array([1, 0, 0]), ("hot_pixels",))
    assert list(m.flags) == [mm.FLAG_HOT, 0, mm.FLAG_SATURATED]
    m = mm.flag_hot_pixels(mm.from_raw(np.array([1.0])), np.array([1]), ())
    assert list(m.flags) == [0]
    m = mm.flag_saturation(mm.Measured(value=np.array([100.0, 16000.0]), units="DN"), _response())
    assert list(m.flags) == [0, mm.FLAG_SATURATED]


def test_linearise_inverts_the_nonlinearity():
    s = np.array([0.0, 100.0, 5000.0, 12000.0])
    beta, full = 0.05, 15000.0
    reading = s * (1 - beta * s / full)
    m = mm.linearise(mm.Measured(value=reading, units="DN", random_var={"read": np.ones(4)}), _response(), ("nonlinearity",))
    np.testing.assert_allclose(m.value, s, rtol=1e-12, atol=1e-9)
    # ds/dm = 1 / (1 - 2 beta s / F)
    np.testing.assert_allclose(m.random_var["read"], 1 / (1 - 2 * beta * s / full) ** 2)
    # beyond the top of the curve: NaN and flagged
    m = mm.linearise(mm.Measured(value=np.array([full / (4 * beta) + 1]), units="DN"), _response(), ("nonlinearity",))
    assert np.isnan(m.value[0]) and m.flags[0] & mm.FLAG_SATURATED


def test_normalise_exposure_hand_value():
    frame = mm.FrameSettings(exposure_s=0.1, iso=400.0)
    m = mm.Measured(value=np.array([1000.0]), units="DN")
    out = mm.normalise_exposure(m, _response(), frame, ("shutter_offset", "iso_gain"))
    # 1000 / (0.1004 * 4 * 1.05)
    expected = 1000 / (0.1004 * 4 * 1.05)
    np.testing.assert_allclose(out.value, [expected])
    np.testing.assert_allclose(out.systematic_var["shutter_offset"], [(expected / 0.1004 * 2e-5) ** 2])
    np.testing.assert_allclose(out.systematic_var["iso_gain"], [(expected / 1.05 * 0.005) ** 2])
    # Eq. (2) with the nominal settings when the effects are not in the model
    np.testing.assert_allclose(mm.normalise_exposure(m, _response(), frame, ()).value, [2500.0])


def test_flat_rolloff_immersion_radiance_hand_values():
    cal = _calibration()
    m = mm.Measured(value=np.array([1e6, 1e6, 1e6]), units="DN s-1", random_var={"shot": np.array([1.0, 1.0, 1.0])})
    m = mm.correct_flat_field(m, np.array([0.98, 1.0, 1.02]), ("prnu",))
    np.testing.assert_allclose(m.value, 1e6 / np.array([0.98, 1.0, 1.02]))
    m = mm.Measured(value=np.array([1e6, 1e6, 1e6]), units="DN s-1")
    theta = np.array([0.0, 40.0, np.nan])
    m = mm.correct_rolloff(m, theta, cal)
    g = 1 - 5e-5 * 40**2   # 0.92
    np.testing.assert_allclose(m.value[:2], [1e6, 1e6 / g])
    np.testing.assert_allclose(m.systematic_var["rolloff"][1], (1e6 / g * 1e-6 * 40**2 / g) ** 2)
    assert m.flags[2] & mm.FLAG_OUTSIDE_IMAGE_CIRCLE and np.isnan(m.value[2])
    beyond = mm.correct_rolloff(mm.Measured(value=np.array([1.0]), units="1"), np.array([85.0]), cal)
    assert beyond.flags[0] & mm.FLAG_BEYOND_CALIBRATED_ANGLE
    w = mm.correct_immersion(mm.Measured(value=np.array([1e6]), units="DN s-1"), cal, "water")
    np.testing.assert_allclose(w.value, [1.7e6])
    np.testing.assert_allclose(w.systematic_var["immersion_factor"], [(1.7e6 * 0.01) ** 2])
    a = mm.correct_immersion(mm.Measured(value=np.array([1e6]), units="DN s-1"), cal, "air")
    np.testing.assert_allclose(a.value, [1e6])
    r = mm.to_radiance(mm.Measured(value=np.array([1e5]), units="DN s-1"), cal)
    np.testing.assert_allclose(r.value, [1.2e-3])
    np.testing.assert_allclose(np.sqrt(r.systematic_var["inverse_responsivity"]), [1.2e-4])
    assert r.units == "W sr-1 m-2 nm-1"


def test_non_positive_inverse_responsivity_stops():
    with pytest.raises(ImpossibleResult, match="not positive"):
        mm.to_radiance(mm.Measured(value=np.array([1.0]), units="DN s-1"), _calibration(inverse_responsivity=-1e-8))


def _forward_dn(radiance, theta, frame, dark, response, cal, flat, medium):
    """Eq. (1)-(4) forward, written here: radiance -> raw DN, with every effect of the chain."""
    g = cal.rolloff_coefficients[0] + cal.rolloff_coefficients[1] * theta**2
    immersion = cal.immersion_factor if medium == "water" else 1.0
    rate = g / immersion / cal.inverse_responsivity * radiance * flat          # DN s-1 at ISO 100, Eq. (4)
    signal = rate * (frame.exposure_s + response.shutter_offset_s) * frame.iso / 100 * response.iso_gain_factor
    bent = signal * (1 - response.nonlinearity_beta * signal / response.full_scale_dn)
    level = (dark.bias_dn + dark.bias_per_gain_dn * (frame.iso / 100 - 1)
             + dark.dark_current_dn_per_s * frame.iso / 100 * frame.exposure_s)
    return bent + level


@pytest.mark.parametrize("once", [False, True], ids=["steps", "pixel_factors"])
@pytest.mark.parametrize("medium", ["air", "water"])
def test_chain_inverts_the_forward_model(medium, once):
    """The chain recovers the radiance the forward model of this file made (float64: to 1e-9); with
    ``once`` the flat field and roll-off enter as apply's frame-independent product (pixel_factors)."""
    rng = np.random.default_rng(4)
    shape = (20, 30)
    radiance = 10 ** rng.uniform(-5.0, -3.0, shape)
    theta = rng.uniform(0, 75, shape)
    flat = 1 + 0.01 * rng.standard_normal(shape)
    frame = mm.FrameSettings(exposure_s=0.05, iso=200.0)
    dark, response, cal = _dark(), _response(), _calibration()
    raw = _forward_dn(radiance, theta, frame, dark, response, cal, flat, medium)
    assert raw.max() < 800 + response.saturation_dn
    if once:
        factors = mm.pixel_factors(mm.rolloff_map(theta, cal, None, ALL, float), ALL, flat_field=flat,
                                   sites=dark.sites_per_pixel, dtype=float)
        out = mm.measure_band(raw, frame, dark, response, cal, None, medium, ALL, factors=factors)
    else:
        out = mm.measure_band(raw, frame, dark, response, cal, theta, medium, ALL, flat_field=flat)
    np.testing.assert_allclose(out.value, radiance, rtol=1e-9)
    assert out.units == "W sr-1 m-2 nm-1"
    assert not out.flags.any()
    # the split: random terms per pixel, systematic terms of the calibration
    assert set(out.random_var) == {"read", "dark", "shot", "prnu"}
    assert {"dark_model", "shutter_offset", "iso_gain", "nonlinearity", "rolloff", "inverse_responsivity"} <= set(
        out.systematic_var)
    assert ("immersion_factor" in out.systematic_var) == (medium == "water")
    # R^-1's 10 % dominates the systematic part
    rel = out.systematic_sigma / out.value
    assert np.all(rel >= 0.1) and np.all(rel < 0.2)


def test_chain_without_the_effects_is_eq_2_and_4():
    frame = mm.FrameSettings(exposure_s=0.1, iso=100.0)
    cal = _calibration()
    raw = np.array([800.0 + 1200.0])
    out = mm.measure_band(raw, frame, _dark(), _response(), cal, np.array([0.0]), "air", ())
    # (2000 - 800) / 0.1 = 12000 DN/s; times R^-1
    np.testing.assert_allclose(out.value, [12000 * 1.2e-8])


def test_flat_field_where_not_measured():
    m = mm.Measured(value=np.array([100.0, 100.0]), units="DN s-1")
    out = mm.correct_flat_field(m, np.array([1.25, np.nan]), ("prnu",), prnu_sigma_rel=0.01)
    np.testing.assert_allclose(out.value, [80.0, 100.0])
    np.testing.assert_allclose(out.random_var["prnu"], [0.0, 1.0])


def test_rolloff_azimuth_term_is_divided_out_with_its_uncertainty():
    cal = mm.BandCalibration(rolloff_coefficients=np.array([1.0, 0, 0, 0, 0]), inverse_responsivity=1.0,
                             rolloff_azimuth_amplitude=0.03, rolloff_azimuth_amplitude_sigma=0.001,
                             rolloff_azimuth_phi0_deg=30.0, rolloff_azimuth_phi0_deg_sigma=2.0)
    theta, phi = np.array([0.0, 45.0, 90.0, 90.0]), np.array([0.0, 30.0, 210.0, 120.0])
    m = mm.Measured(value=np.ones(4), units="DN s-1")
    out = mm.correct_rolloff(m, theta, cal, phi, ("rolloff_azimuth",))
    # 1 + A (theta / 90) cos(phi - phi0): 1, 1.015, 0.97, 1
    np.testing.assert_allclose(out.value, 1.0 / np.array([1.0, 1.015, 0.97, 1.0]))
    rel = np.sqrt(out.systematic_var["rolloff_azimuth"]) / out.value
    # at phi - phi0 = 90 deg only phi0's uncertainty counts: A sin(90) sigma_phi0
    np.testing.assert_allclose(rel[3], 0.03 * np.radians(2.0), rtol=1e-9)
    np.testing.assert_allclose(rel[2], 0.001 / 0.97, rtol=1e-9)
    # without the effect in the model, nothing
    np.testing.assert_allclose(mm.correct_rolloff(m, theta, cal, phi, ()).value, 1.0)


def test_linearised_shot_noise_is_that_of_the_linear_signal():
    """The sensor bends the noisy signal: a reading m = s (1 - beta s / F) has variance N'(s)^2 k s, so
    after the inverse the shot variance is k s."""
    k, beta, full = 0.8, 0.05, 15000.0
    s = np.array([1000.0, 8000.0])
    reading = s * (1 - beta * s / full)
    m = mm.Measured(value=reading, units="DN", random_var={"shot": k * reading})
    response = mm.ResponseModel(conversion_gain_dn_per_e=k, nonlinearity_beta=beta, full_scale_dn=full)
    out = mm.linearise(m, response, ("nonlinearity",))
    np.testing.assert_allclose(out.value, s, rtol=1e-12)
    np.testing.assert_allclose(out.random_var["shot"], k * s, rtol=1e-12)


def test_flat_field_noise_and_unmeasured_prnu_per_band_pixel():
    """Where the flat field was measured its own noise is the random ``prnu`` term; where it was not,
    the per-site PRNU spread averages over the sites of the band pixel (G: two)."""
    m = mm.Measured(value=np.full(2, 100.0), units="DN s-1")
    out = mm.correct_flat_field(m, np.array([1.0, np.nan]), ("prnu",), prnu_sigma_rel=0.01,
                                flat_field_sigma=np.array([0.003, np.nan]), sites=2)
    np.testing.assert_allclose(out.random_var["prnu"], [(100 * 0.003) ** 2, (100 * 0.01) ** 2 / 2])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_evaluating_into_buffers_gives_the_chains_values(dtype):
    """Two evaluations of one chain: into output buffers (apply's path) and by the properties.

    Every effect, a flat field with unmeasured pixels and a stored roll-off
    map with two relative terms; the values must be the same numbers (the
    same operations in the same order), and a float64 chain taken into
    float32 buffers the property's value cast to float32.
    """
    rng = np.random.default_rng(7)
    shape = (17, 23)
    raw = (rng.uniform(900.0, 9000.0, shape)).astype(dtype)
    flat = 1 + 0.01 * rng.standard_normal(shape)
    flat[0, :5] = np.nan
    theta = rng.uniform(0.0, 85.0, shape)
    theta[3, 3] = np.nan
    cal = _calibration()
    rolloff = mm.rolloff_map(theta, cal, None, ALL, np.result_type(np.float32, raw.dtype),
                             theta_deg_sigma=np.full(shape, 0.05))
    args = (raw, mm.FrameSettings(exposure_s=0.05, iso=200.0), _dark(sites_per_pixel=2), _response(), cal, None,
            "water", ALL)
    kw = dict(flat_field=flat, flat_field_sigma=np.full(shape, 0.002), prnu_sigma_rel=0.01, rolloff=rolloff,
              hot_mask=rng.uniform(size=shape) > 0.95)
    want = mm.measure_band(*args, **kw)
    for buffer_type in (dtype, np.float32):
        got = mm.measure_band(*args, **kw)
        out = [np.full(shape, -1.0, buffer_type) for _ in range(3)]
        got.evaluate_into(*out, scratch=np.empty(shape, buffer_type))
        for name, buffer in zip(("value", "random_sigma", "systematic_sigma"), out):
            expected = getattr(want, name).astype(buffer_type)
            np.testing.assert_array_equal(buffer, expected, err_msg=name)
            np.testing.assert_array_equal(getattr(got, name), expected if buffer_type == dtype else getattr(want, name))
    with pytest.raises(ValueError, match="shape"):
        mm.measure_band(*args, **kw).evaluate_into(np.empty((2, 2), dtype))
