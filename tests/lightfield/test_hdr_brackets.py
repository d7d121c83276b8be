"""HDR from exposure brackets and the bracket-consistency closure, against the simulator's truth.

The tiny camera that the session fixture ``calibrated`` calibrated with the
pipeline's own stages (seed 5, model dark_current + hot_pixels) photographs a
sky with the sun over a dimming ground (:mod:`pipeline.simulate.brackets`:
CIE clear sky, a sun disc far above saturation, the ground falling to 2e-5
of the zenith radiance at the nadir) in one bracket of seven exposures, 1/4000 s
to 1 s. ``lightfield --calibration --frames`` merges it.

- Merged map against truth, per band pixel (both lenses, every pixel above its
  limit of detection, over 5.3 decades of true radiance): the band-common
  scale (one number per band, R^-1's deviation) within 3 of its stated
  relative sigma; the deviations from the scaled truth over the stated
  sigma of what is not band-scale (random, per-exposure, and the roll-off's
  shape: the common sigma less R^-1's), spread 0.6 to 1.5 overall and below 2
  in every decade (measured: 0.74 to 1.07 overall; R's worst decade 1.6, at
  the far lens's rim where the calibrated roll-off's shape error shows).
- Dynamic range: the stated decades against the truth's span between the same
  two pixels, within 3 sigma of the log ratio's noise (the faintest pixel is at
  SNR >= 3: at most 0.43 decade); and at least five decades.
- Pixels saturated in every exposure (the sun): flagged, and every lower bound
  below its true radiance; the sphere cells holding them flagged with a finite
  bound, and E_d states the share of its value from them.
- Bracket consistency: at the noise floor with the right response (the residual
  test not significant, no candidate significant); with the raw DN bent by
  the test's own response, s -> s (1 - 0.06 (s / F)^1.5) (not the package's
  quadratic), significant and ranking ``nonlinearity`` first.

Run time: about 8 s beyond the session fixture ``calibrated``.
"""

from __future__ import annotations

from datetime import datetime, timedelta
from types import SimpleNamespace

import numpy as np
import pytest
import xarray as xr

from pipeline.bundle.apply import BandChain
from pipeline.io.artefact import model_effects
from pipeline.io.bands import BANDS
from pipeline.bundle.calibration import read_bundle
from pipeline.cli import main
from pipeline.errors import InputError
from pipeline.lightfield.hdr import (dynamic_range, exposure_maps, group_brackets, merge_exposures,
                                     pixel_sphere_cells)
from pipeline.io.rawio import read_raw
from pipeline.simulate.brackets import render_bracket

SEED = 3
GRID_DEG = 9.0
BEND = 0.06


def bent_response(cfa, black, white):
    """The test's own nonlinearity on the raw DN: s (1 - 0.06 (s / F)^1.5) above black, the ADC's clip kept."""
    s = cfa.astype(float) - black
    full = white - black
    out = s * (1.0 - BEND * np.clip(s / full, 0.0, None) ** 1.5)
    return np.where(cfa >= white, white, np.clip(np.round(out + black), 0, white))


@pytest.fixture(scope="module")
def bracket(calibrated, tmp_path_factory):
    """The straight and the bent bracket, each merged by the command: {name: (render info, light field)}."""
    bundle_path = calibrated[4]
    out = {}
    for name, transform in (("straight", None), ("bent", bent_response)):
        folder = tmp_path_factory.mktemp(name)
        info = render_bracket(folder, seed=SEED, raw_transform=transform)
        lf = folder / "lf.nc"
        assert main(["lightfield", "--calibration", str(bundle_path), "--frames", str(info["frames_csv"]),
                     "--grid-deg", str(GRID_DEG), *map(str, info["files"]), "-o", str(lf)]) == 0
        with xr.open_dataset(lf) as ds:
            out[name] = (info, ds.load())
    return out


@pytest.fixture(scope="module")
def merged(calibrated, bracket):
    """The straight bracket's merged band pixels, the truth at the same pixels, the bundle's R^-1 sigma."""
    bundle = read_bundle(calibrated[4])
    effects = model_effects(bundle)
    lenses = [str(x) for x in bundle["lens"].values]
    chains = {(lens, band): BandChain(bundle, lens, band, "air", effects) for lens in lenses for band in BANDS}
    info, _ = bracket["straight"]
    maps = [exposure_maps(read_raw(p), bundle, chains, lenses, "air", effects) for p in info["files"]]
    with xr.open_dataset(info["truth"]) as t:
        truth = t["radiance"].sel(lens=lenses).values
    u = bundle["inverse_responsivity_relative_sigma"].sel(lens=lenses).values
    return merge_exposures(maps), truth, u


def test_merged_map_within_its_stated_uncertainty_over_five_decades(merged):
    m, truth, u = merged
    for b, band in enumerate(BANDS):
        L, T = m.radiance[:, b], truth[:, b]
        detect = np.hypot(m.random_sigma[:, b], m.fixed_sigma[:, b])
        ok = np.isfinite(L) & np.isfinite(T) & (L >= 3 * detect)
        assert np.log10(T[ok].max() / T[ok].min()) >= 5.0, band
        # the band-scale part of the common sigma (R^-1) apart: what is left is the roll-off's shape
        shape = np.sqrt(np.clip(m.common_sigma[:, b] ** 2 - (u[:, b][:, None, None] * L) ** 2, 0.0, None))
        s = np.sqrt(m.random_sigma[:, b] ** 2 + m.fixed_sigma[:, b] ** 2 + np.sum(m.exposure_sigma[:, :, b] ** 2, 0)
                    + shape ** 2)
        L, T, s = L[ok], T[ok], s[ok]
        k = np.sum(L * T / s ** 2) / np.sum(T ** 2 / s ** 2)
        assert abs(k - 1.0) <= 3 * float(np.max(u[:, b])), (band, k)
        z = (L - k * T) / s
        assert 0.6 <= z.std() <= 1.5, (band, z.std())
        decade = np.floor(np.log10(T))
        for d in np.unique(decade):
            sel = decade == d
            if sel.sum() >= 30:
                assert z[sel].std() < 2.0, (band, d, z[sel].std())


def test_sphere_map_against_the_truth_binned_alike(calibrated, merged, bracket):
    """The output's merged sphere cells (no attitude: the grid's own frame) against the truth of the same band
    pixels binned alike: the same band scale and spread limits as the pixels'."""
    m, truth, u = merged
    bundle = read_bundle(calibrated[4])
    lenses = [str(x) for x in bundle["lens"].values]
    cells = pixel_sphere_cells(bundle, lenses, "air", "close", GRID_DEG)
    _, ds = bracket["straight"]
    n = ds["sphere_radiance"][0, 0].size
    for b, band in enumerate(BANDS):
        good = m.usable[:, b] & np.isfinite(m.radiance[:, b]) & (cells[:, b] >= 0)
        count = np.bincount(cells[:, b][good], minlength=n)
        T = np.bincount(cells[:, b][good], truth[:, b][good], n) / np.maximum(count, 1)
        L = ds["sphere_radiance"].sel(band=band)[0].values.ravel()
        rnd = ds["sphere_radiance_random_sigma"].sel(band=band)[0].values.ravel()
        common = ds["sphere_radiance_systematic_sigma"].sel(band=band)[0].values.ravel()
        exposure = ds["hdr_exposure_systematic_sigma"].sel(band=band)[0].values.ravel()
        ok = ((ds["sphere_cell_flag"].sel(band=band)[0].values.ravel() == 0)
              & (ds["hdr_cell_flag"].sel(band=band)[0].values.ravel() == 0) & (count > 0) & (L >= 3 * rnd))
        assert np.log10(T[ok].max() / T[ok].min()) >= 5.0, band
        shape = np.sqrt(np.clip(common ** 2 - (float(np.max(u[:, b])) * L) ** 2, 0.0, None))
        s = np.sqrt(rnd ** 2 + exposure ** 2 + shape ** 2)[ok]
        k = np.sum(L[ok] * T[ok] / s ** 2) / np.sum(T[ok] ** 2 / s ** 2)
        assert abs(k - 1.0) <= 3 * float(np.max(u[:, b])), (band, k)
        z = (L[ok] - k * T[ok]) / s
        assert 0.6 <= z.std() <= 1.5, (band, z.std())


def test_dynamic_range_matches_the_truths_span(merged, bracket):
    m, truth, _ = merged
    _, ds = bracket["straight"]
    for b, band in enumerate(BANDS):
        L = m.radiance[:, b].ravel()
        s = np.hypot(m.random_sigma[:, b], m.fixed_sigma[:, b]).ravel()
        decades, hi, lo = dynamic_range(L, s, 3.0)
        assert decades == pytest.approx(float(ds["hdr_pixel_dynamic_range_decades"].sel(band=band)[0]))
        T = truth[:, b].ravel()
        tol = 3 / np.log(10) * np.hypot(s[hi] / L[hi], s[lo] / L[lo])
        assert abs(decades - np.log10(T[hi] / T[lo])) <= tol, (band, decades, np.log10(T[hi] / T[lo]), tol)
        assert decades >= 5.0
        assert float(ds["hdr_dynamic_range_decades"].sel(band=band)[0]) >= 5.0


def test_saturated_everywhere_flagged_with_a_valid_lower_bound(merged, bracket):
    m, truth, _ = merged
    sat = m.saturated_everywhere
    assert sat.sum() >= 3                                      # the sun
    assert np.all(np.isfinite(m.lower_bound[sat])) and np.all(m.lower_bound[sat] <= truth[sat])
    assert np.all(np.isnan(m.radiance[sat]))                   # no measurement where every exposure saturated
    _, ds = bracket["straight"]
    flagged = ds["hdr_cell_flag"].values > 0
    assert flagged.any() and np.all(np.isfinite(ds["hdr_lower_bound"].values[flagged]))
    assert (ds["E_d_lower_bound_fraction"].values > 0).all()   # the sun is in the upper hemisphere


def test_bracket_consistency_at_the_noise_floor_and_naming_a_bent_response(bracket):
    _, straight = bracket["straight"]
    assert straight.attrs["bracket_consistency_effects"] == ""
    assert straight.attrs["bracket_consistency_p_value"] > 0.01
    assert straight["obs_bracket__z"].size >= 50
    _, bent = bracket["bent"]
    assert bent.attrs["bracket_consistency_effects"].split(",")[0] == "nonlinearity"
    assert bent.attrs["bracket_consistency_rms_z"] > 1.5


def test_brackets_refused_with_one_line():
    def frame(name, t, serial="A"):
        return SimpleNamespace(path=name, exposure_s=t, time=None, make="m", model="x", serial=serial, iso=100.0)
    with pytest.raises(InputError, match="one exposure only"):
        group_brackets([frame("a.dng", 0.01), frame("b.dng", 0.01)], {"a.dng": "S", "b.dng": "S"})
    with pytest.raises(InputError, match="mixes cameras"):
        group_brackets([frame("a.dng", 0.01), frame("b.dng", 0.1, "B")], {"a.dng": "S", "b.dng": "S"})
    with pytest.raises(InputError, match="does not list c.dng"):
        group_brackets([frame("c.dng", 0.01)], {"a.dng": "S"})
    with pytest.raises(InputError, match="no DateTimeOriginal"):
        group_brackets([frame("a.dng", 0.01)], None)


def test_brackets_grouped_by_time_window():
    t0 = datetime(2021, 3, 18, 16, 0, 0)

    def frame(name, t, dt_s):
        return SimpleNamespace(path=name, exposure_s=t, time=t0 + timedelta(seconds=dt_s), make="m", model="x",
                               serial="A", iso=100.0)
    frames = [frame("a", 0.1, 0.0), frame("b", 0.001, 1.0), frame("c", 0.01, 20.0), frame("d", 0.1, 21.5)]
    groups = group_brackets(frames, None, window_s=5.0)
    assert [g.frames for g in groups] == [[1, 0], [2, 3]]     # each bracket's frames by exposure


def test_merge_by_hand():
    """Two exposures of one pixel: the inverse-variance mean and the kinds of sigma, computed here by hand."""
    def maps(L, r, e, c, saturated=False):
        one = np.ones((1, 1, 1, 1))
        return SimpleNamespace(radiance=L * one, random_sigma=r * one, exposure_sigma=e * one, common_sigma=c * one,
                               fixed_sigma=0.0 * one, usable=one > 0, saturated=(one > 0) & saturated)
    a, b = maps(1.0, 0.3, 0.4, 0.1), maps(1.2, 0.1, 0.0, 0.2)
    m = merge_exposures([a, b])
    wa, wb = 1 / (0.3 ** 2 + 0.4 ** 2), 1 / 0.1 ** 2
    W = wa + wb
    assert m.radiance.item() == pytest.approx((wa * 1.0 + wb * 1.2) / W)
    assert m.random_sigma.item() == pytest.approx(np.sqrt(wa ** 2 * 0.09 + wb ** 2 * 0.01) / W)
    assert m.exposure_sigma[:, 0, 0, 0, 0] == pytest.approx([wa * 0.4 / W, 0.0])
    assert m.common_sigma.item() == pytest.approx((wa * 0.1 + wb * 0.2) / W)   # not averaged down
    s = merge_exposures([maps(0.5, 0.1, 0, 0, True), maps(2.0, 0.1, 0, 0, True)])
    assert s.saturated_everywhere.item() and np.isnan(s.radiance.item()) and s.lower_bound.item() == 2.0


def test_frames_table_needs_a_calibration(tmp_path, capsys):
    assert main(["lightfield", "--frames", str(tmp_path / "f.csv"), "x.dng", "-o", str(tmp_path / "o.nc")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--calibration" in err[0]
