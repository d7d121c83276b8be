"""Valid but degenerate dark acquisition designs, and a quantised (8-bit) sensor, written by the test itself.

The frames come from a stated sensor model, not from the simulator (which always sweeps ISO and
exposure): per raw site, in DN,

    value = round(B0 + B1 (g - 1) + pattern + k g Poisson(D / k t) + N(0, sigma_read(g)))

with g = ISO / 100, a fixed offset pattern of spread ``PATTERN_DN`` (one seed), dark current D (DN/s
at ISO 100) made of electrons at a conversion gain k (DN per electron at ISO 100), and read noise
sigma_read(g) = READ0_DN + READ_SLOPE_DN (g - 1). Every draw uses a fixed seed.

The matrix {one ISO, several} x {one exposure, several} x {one frame per setting, several}: the dark
stage completes with several frames per setting and gives the parameters the design determines within
tolerances derived from the injected noise (:func:`_tolerances`), and marks the others not measured; with
one frame per setting it stops with one line (the temporal noise is a frame-to-frame variance).

The linearity stage's lit frames (an image circle, a source) are not rewritten here: its one-ISO and
one-exposure designs are the session's simulated tiny dataset with the rows of the other settings
deleted (:func:`_subset`), which the simulator cannot write itself but a lab that skips a sweep does.
"""

from __future__ import annotations

import shutil
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import xarray as xr
import yaml

from pipeline.io.bands import BANDS
from pipeline.bundle.calibration import _dark_part, dark_parameters
from pipeline.io.dataset import write_md5sums
from pipeline.errors import InputError
from pipeline.radiometry.dark import dark_level_dn
from pipeline.radiometry.exposure import gain_from_iso
from pipeline.radiometry import measurement as mm
from pipeline.io.rawio import write_dng
from pipeline.runner.workflow import run_stage

LENS = "main"
#: raw sites of the lens region (a fisheye region: its corners are the unlit pixels)
SIDE_PX = 64
META = {
    "layout": 1,
    "camera": {"make": "Insta360", "model": "ONE", "serial": "SIM-0001"},
    "lenses": {LENS: {"rows": [0, SIDE_PX], "cols": [0, SIDE_PX]}},
    "chessboard": {"inner_corners": [8, 6], "square_mm": {"air": 30.0, "water": 20.0}},
    "description": "degenerate dark designs written by tests/stages/test_degenerate_designs.py",
}

# the 12-bit sensor model
B0_DN = 800.0            # black level at ISO 100
B1_DN = 2.0              # black level change per unit of g - 1
PATTERN_DN = 1.0         # spread of the fixed offset pattern
READ0_DN = 2.0           # read noise at ISO 100
READ_SLOPE_DN = 0.5      # read noise change per unit of g - 1
DARK_DN_PER_S = 4.0      # dark current at ISO 100
GAIN_DN_PER_E = 0.5      # conversion gain at ISO 100
WHITE_12BIT = 4095

ISOS = {"one ISO": (400.0,), "several ISOs": (100.0, 400.0, 1600.0)}
EXPOSURES = {"one exposure": (0.5,), "several exposures": (0.001, 0.5, 1.0)}
FRAMES = {"one frame": 1, "several frames": 4}
#: a tolerance is this many standard errors of the quantity under the injected noise
K_SIGMA = 5.0


def read_noise_dn(gain):
    return READ0_DN + READ_SLOPE_DN * (gain - 1.0)


def _frame(rng, pattern, iso, t, *, bias0, bias1, read0, read_slope, dark_dn_per_s, white, hot_dn_per_s=None):
    g = gain_from_iso(iso)
    mean = bias0 + bias1 * (g - 1.0) + pattern
    electrons = rng.poisson(dark_dn_per_s / GAIN_DN_PER_E * t, pattern.shape)
    signal = mean + GAIN_DN_PER_E * g * electrons + rng.normal(0.0, read0 + read_slope * (g - 1.0), pattern.shape)
    if hot_dn_per_s is not None:
        signal = signal + hot_dn_per_s * g * t
    return np.clip(np.rint(signal), 0, white).astype(np.uint16)


def write_dark_dataset(root: Path, isos, exposures, n_frames, *, seed=3, bias0=B0_DN, bias1=B1_DN,
                       pattern_dn=PATTERN_DN, read0=READ0_DN, read_slope=READ_SLOPE_DN,
                       dark_dn_per_s=DARK_DN_PER_S, white=WHITE_12BIT, hot_dn_per_s=None) -> Path:
    """A dataset with a dark experiment only: ``n_frames`` frames at every (ISO, exposure)."""
    rng = np.random.default_rng(seed)
    pattern = rng.normal(0.0, pattern_dn, (SIDE_PX, SIDE_PX)) if pattern_dn else np.zeros((SIDE_PX, SIDE_PX))
    folder = root / "dark"
    (folder / "raw").mkdir(parents=True)
    (root / "dataset.yaml").write_text(yaml.safe_dump(META, sort_keys=False))
    rows, start = [], datetime(2024, 5, 2, 10, 0, 0)
    for iso in isos:
        for t in exposures:
            for _ in range(n_frames):
                name = f"raw/d{len(rows):03d}.dng"
                cfa = _frame(rng, pattern, iso, t, bias0=bias0, bias1=bias1, read0=read0, read_slope=read_slope,
                             dark_dn_per_s=dark_dn_per_s, white=white, hot_dn_per_s=hot_dn_per_s)
                write_dng(folder / name, cfa, exposure_s=t, iso=iso, time=start + timedelta(seconds=len(rows)),
                          black_level=0, white_level=white)
                rows.append({"file": name, "lens": LENS, "kind": "dark"})
    pd.DataFrame(rows).to_csv(folder / "frames.csv", index=False)
    write_md5sums(root)
    return root


def _run_dark(root: Path, config: dict, out: Path) -> xr.Dataset:
    return run_stage("dark", root, config, {LENS: out / "dark.nc"})[LENS]


def _n_circle(art: xr.Dataset) -> int:
    """Band pixels inside the image circle (the dark model's pixels), from the artefact."""
    return int(art["obs_setting__n_pixels"].values.min())


def _tolerances(art: xr.Dataset, isos, exposures, n_frames) -> dict[str, float]:
    """Each fitted quantity's tolerance: K_SIGMA standard errors under the injected noise.

    With n band pixels and (bounding from above) one frame: b0 carries the pattern's mean over the
    pixels, PATTERN_DN / sqrt(n), and the read noise at the highest gain, sigma_read(g_max) / sqrt(n);
    b1 the read noise of the highest and lowest gains over (g_max - g_min); D the read noise of two
    exposures and the dark shot noise of the longest, over the exposure span. The read noise of one
    raw pixel has the relative standard error 1 / sqrt(2 n (frames - 1)) (Gaussian sampling).
    """
    n = _n_circle(art)
    g = gain_from_iso(np.array(isos))
    b0 = K_SIGMA * np.hypot(PATTERN_DN, read_noise_dn(g.max())) / np.sqrt(n)
    out = {"b0_dn": b0, "read_rel": K_SIGMA / np.sqrt(2.0 * n * (n_frames - 1))}
    if len(isos) > 1:
        out["b1_dn"] = K_SIGMA * np.hypot(read_noise_dn(g.max()), read_noise_dn(g.min())) / np.sqrt(n) / np.ptp(g)
    if len(exposures) > 1:
        span = np.ptp(exposures)
        shot = GAIN_DN_PER_E * g.max() * DARK_DN_PER_S * g.max() * max(exposures)
        out["d_dn_per_s"] = K_SIGMA * np.sqrt(2.0 * read_noise_dn(g.max()) ** 2 + shot) / np.sqrt(n) / span / g.max()
    return out


def _expected(isos, exposures) -> dict[str, float]:
    """The dark model's parameters the design determines, from the sensor model.

    One ISO: b1 is fixed at 0 and b0 is the black level at that ISO. One exposure: D is fixed at 0
    and its signal D g t = D t + D t (g - 1) goes into b0 (and, with several ISOs, into b1).
    """
    g_ref = gain_from_iso(isos[0]) if len(isos) == 1 else 1.0
    b0, b1, d = B0_DN + B1_DN * (g_ref - 1.0), B1_DN, DARK_DN_PER_S
    if len(exposures) == 1:
        t = exposures[0]
        b0 += DARK_DN_PER_S * g_ref * t if len(isos) == 1 else DARK_DN_PER_S * t
        b1 += DARK_DN_PER_S * t
        d = 0.0
    return {"b0_dn": b0, "b1_dn": b1 if len(isos) > 1 else 0.0, "d_dn_per_s": d}


def _true_read_noise_dn(iso, t) -> float:
    """Temporal noise of one raw pixel at (iso, t): read noise, dark shot noise and rounding (1/12 DN^2)."""
    g = gain_from_iso(iso)
    return float(np.sqrt(read_noise_dn(g) ** 2 + GAIN_DN_PER_E * g * DARK_DN_PER_S * g * t + 1.0 / 12.0))


@pytest.mark.parametrize("frames", list(FRAMES))
@pytest.mark.parametrize("exposures", list(EXPOSURES))
@pytest.mark.parametrize("isos", list(ISOS))
def test_dark_stage_on_every_design(isos, exposures, frames, config, tmp_path):
    iso_values, times, n_frames = ISOS[isos], EXPOSURES[exposures], FRAMES[frames]
    root = write_dark_dataset(tmp_path / "ds", iso_values, times, n_frames)
    if n_frames == 1:
        # not a design the dark stage can reduce: the read noise is a frame-to-frame variance
        with pytest.raises(InputError) as err:
            _run_dark(root, config, tmp_path / "out")
        message = str(err.value)
        assert "\n" not in message and "d000.dng" in message and "at least 2 frames" in message, message
        return
    art = _run_dark(root, config, tmp_path / "out")
    tol = _tolerances(art, iso_values, times, n_frames)
    want = _expected(iso_values, times)

    for band in BANDS:
        b = art.sel(band=band)
        assert abs(float(b["bias_dn"]) - want["b0_dn"]) < tol["b0_dn"], (band, float(b["bias_dn"]), want, tol)
        if len(iso_values) > 1:
            assert abs(float(b["bias_per_gain_dn"]) - want["b1_dn"]) < tol["b1_dn"], (band, float(b["bias_per_gain_dn"]))
        for iso in iso_values:
            fitted = float(b["read_noise_dn"].sel(iso=iso))
            truth = _true_read_noise_dn(iso, min(times))
            assert abs(fitted / truth - 1.0) < tol["read_rel"], (band, iso, fitted, truth)

    one_iso, one_exposure = len(iso_values) == 1, len(times) == 1
    assert art["bias_per_gain_dn"].attrs["measured"] == int(not one_iso)
    assert art["dark_current_dn_per_s"].attrs["measured"] == int(not one_exposure)
    assert art["hot_pixel_mask"].attrs["measured"] == int(not one_exposure)
    if one_iso:
        assert np.all(art["bias_per_gain_dn"].values == 0.0)
        assert "no gain sweep" in art["bias_per_gain_dn"].attrs["not_measured"]
        assert art["bias_dn"].attrs["reference_iso"] == iso_values[0]
    if one_exposure:
        assert float(art["dark_current_dn_per_s"]) == 0.0
        assert "one exposure time" in art["dark_current_dn_per_s"].attrs["not_measured"]
        assert int(art["hot_pixel_count"].sum()) == 0
    else:
        d = float(art["dark_current_dn_per_s"])
        assert abs(d - want["d_dn_per_s"]) < tol["d_dn_per_s"], (d, want, tol)
    # the model predicts every setting's level within the noise (nothing left in the residuals)
    assert float(art["rms_z"]) < 3.0


# ---------------------------------------------------------------- the one-ISO dark model downstream
def test_one_iso_dark_model_holds_at_its_iso_and_refuses_another(config, tmp_path):
    root = write_dark_dataset(tmp_path / "ds", (400.0,), EXPOSURES["several exposures"], 3)
    art = _run_dark(root, config, tmp_path / "out")
    level = dark_level_dn(art, "R", 400.0, 1.0)
    truth = B0_DN + B1_DN * 3.0 + DARK_DN_PER_S * 4.0 * 1.0
    assert abs(level - truth) < 0.5, (level, truth)
    with pytest.raises(InputError, match="ISO 400 only"):
        dark_level_dn(art, "R", 100.0, 1.0)


def test_one_iso_bundle_gives_a_dark_model_at_its_iso_only(config, tmp_path):
    root = write_dark_dataset(tmp_path / "ds", (400.0,), EXPOSURES["several exposures"], 3)
    art = _run_dark(root, config, tmp_path / "out")
    bundle = _dark_part(art).expand_dims(lens=[LENS])
    frame = mm.FrameSettings(iso=400.0, exposure_s=1.0)
    dark = dark_parameters(bundle, LENS, "R", frame)
    assert dark.bias_per_gain_dn == 0.0
    assert abs(dark.bias_dn - (B0_DN + 3.0 * B1_DN)) < 0.5
    with pytest.raises(InputError, match="ISO 400 only"):
        dark_parameters(bundle, LENS, "R", mm.FrameSettings(iso=800.0, exposure_s=1.0))


# ---------------------------------------------------------------- a quantised (8-bit) sensor
EIGHT_BIT = {"bias0": 10.0, "bias1": 0.0, "pattern_dn": 0.0, "read0": 0.3, "read_slope": 0.0,
             "dark_dn_per_s": 0.0, "white": 255}
#: raw sites (row, column) of the injected hot pixels: R sites (even row, even column of RGGB) inside the circle
HOT_SITES = ((20, 20), (24, 40), (32, 32), (40, 26), (44, 44))
HOT_DN_PER_S = 20.0


def test_eight_bit_sensor_without_hot_pixels_flags_none(config, tmp_path):
    """Dark noise 0.3 DN: most pixels read 10 in every frame, a robust spread of zero. With the
    quantisation floor a flag needs a rise of 6 x sqrt(1/12 (1/4 + 1/4)) = 1.22 DN in both long
    exposures, five steps more over four frames than the short exposure's four: about 1e-5 per pixel
    and exposure (each frame leaves 10 with probability 0.096), under 0.1 pixels expected over the
    three bands' 3072 pixels; the data hold none."""
    root = write_dark_dataset(tmp_path / "ds", (100.0,), EXPOSURES["several exposures"], 4, **EIGHT_BIT)
    art = _run_dark(root, config, tmp_path / "out")
    assert int(art["hot_pixel_count"].sum()) == 0, art["hot_pixel_count"].values
    assert abs(float(art["bias_dn"].sel(band="R")) - 10.0) < 0.1


def test_eight_bit_sensor_finds_its_hot_pixels(config, tmp_path):
    hot = np.zeros((SIDE_PX, SIDE_PX))
    for r, c in HOT_SITES:
        hot[r, c] = HOT_DN_PER_S
    root = write_dark_dataset(tmp_path / "ds", (100.0,), EXPOSURES["several exposures"], 4, hot_dn_per_s=hot,
                              **EIGHT_BIT)
    art = _run_dark(root, config, tmp_path / "out")
    mask = art["hot_pixel_mask"].sel(band="R").values
    assert {(int(y), int(x)) for y, x in zip(*np.nonzero(mask))} == {(r // 2, c // 2) for r, c in HOT_SITES}
    assert int(art["hot_pixel_count"].sel(band=["G", "B"]).sum()) == 0


# ---------------------------------------------------------------- the linearity stage on one ISO or one exposure
def _subset(source: Path, root: Path, keep: dict) -> Path:
    """A copy of ``source`` with only the frames.csv rows of each experiment that ``keep[experiment](row, tags)``
    keeps (the other frames deleted, MD5SUMS rewritten): the same frames in a design with fewer settings."""
    from pipeline.io.rawio import read_tags

    shutil.copytree(source, root)
    for experiment, wanted in keep.items():
        frames = pd.read_csv(root / experiment / "frames.csv", keep_default_na=False)
        kept = [wanted(row, read_tags(root / experiment / row["file"])) for _, row in frames.iterrows()]
        for name in frames.loc[[not k for k in kept], "file"]:
            (root / experiment / name).unlink()
        frames[kept].to_csv(root / experiment / "frames.csv", index=False)
    (root / "MD5SUMS").unlink(missing_ok=True)
    write_md5sums(root)
    return root


def _run_linearity(root: Path, config: dict, out: Path) -> dict[str, xr.Dataset]:
    lenses = list(yaml.safe_load((root / "dataset.yaml").read_text())["lenses"])
    dark = {lens: out / "dark" / f"{lens}.nc" for lens in lenses}
    run_stage("dark", root, config, dark)
    return run_stage("linearity", root, config, {lens: out / "linearity" / f"{lens}.nc" for lens in lenses},
                     {"dark": dark})


def test_linearity_with_one_iso(make_dataset, config, tmp_path):
    """The exposure sweep alone (no gain sweep) and dark frames at its ISO only: the photon transfer is
    measured at that ISO (the simulator's truth 0.8 DN per electron at ISO 100, within 5 stated sigma)."""
    source, truth = make_dataset()
    root = _subset(source, tmp_path / "ds", {"linearity": lambda row, tags: row["sweep"] == "exposure",
                                             "dark": lambda row, tags: float(tags["iso"]) == 100.0})
    for lens, art in _run_linearity(root, config, tmp_path / "out").items():
        k, k_sigma = float(art["conversion_gain_dn_per_e"]), float(art["conversion_gain_dn_per_e_sigma"])
        true_k = float(truth["derived"]["conversion_gain_dn_per_e_iso100"])
        assert abs(k - true_k) < 5.0 * k_sigma, (lens, k, k_sigma, true_k)
        # no photon counts in frames.csv: no responsivity or quantum efficiency, and the artefact says why
        assert np.isnan(art["quantum_efficiency"].values).all()
        assert "photons_per_pixel" in art["quantum_efficiency"].attrs["not_measured"]


def test_linearity_with_one_exposure_says_the_photon_transfer_is_not_measured(make_dataset, config, tmp_path):
    source, _ = make_dataset()
    root = _subset(source, tmp_path / "ds", {"linearity": lambda row, tags: row["sweep"] == "gain"})
    for art in _run_linearity(root, config, tmp_path / "out").values():
        assert np.isnan(float(art["conversion_gain_dn_per_e"]))
        assert art["conversion_gain_dn_per_e"].attrs["measured"] == 0
        assert "exposure sweep" in art["conversion_gain_dn_per_e"].attrs["not_measured"]
        assert np.isnan(art["dynamic_range"].values).all()
        assert "exposure sweep" in art["dynamic_range"].attrs["not_measured"]


def test_gain_sweep_on_a_one_iso_dark_model_stops_with_one_line(make_dataset, config, tmp_path):
    source, _ = make_dataset()
    root = _subset(source, tmp_path / "ds", {"dark": lambda row, tags: float(tags["iso"]) == 100.0})
    with pytest.raises(InputError) as err:
        _run_linearity(root, config, tmp_path / "out")
    assert "\n" not in str(err.value) and "measured at ISO 100 only" in str(err.value), str(err.value)
