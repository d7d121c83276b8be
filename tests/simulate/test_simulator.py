"""The simulator: same seed same bytes, never overwrites, truth beside the dataset, valid layout."""

from __future__ import annotations

import hashlib

import pytest
import yaml

from pipeline.io.dataset import open_dataset
from pipeline.errors import InputError
from pipeline.io.rawio import read_tags
from pipeline.simulate import simulate_dataset, truth_dir_for


def _digest(root):
    return hashlib.sha256((root / "MD5SUMS").read_bytes()).hexdigest()


def test_same_seed_same_bytes_and_truth_outside(tmp_path):
    a = simulate_dataset(tmp_path / "a", scale="tiny", seed=5, effects=[("bias_drift", {"sigma_dn": 2.0})],
                         experiments=("dark",), progress=False)
    b = simulate_dataset(tmp_path / "b", scale="tiny", seed=5, effects=[("bias_drift", {"sigma_dn": 2.0})],
                         experiments=("dark",), progress=False)
    c = simulate_dataset(tmp_path / "c", scale="tiny", seed=6, effects=[("bias_drift", {"sigma_dn": 2.0})],
                         experiments=("dark",), progress=False)
    assert _digest(a) == _digest(b)          # MD5SUMS lists every file's checksum
    assert _digest(a) != _digest(c)
    truth = truth_dir_for(a)
    assert truth.parent == a.parent and truth.exists() and not (a / "truth.yaml").exists()
    assert yaml.safe_load((truth / "truth.yaml").read_text())["effects"]["bias_drift"]["sigma_dn"] == 2.0
    ds = open_dataset(a)
    assert ds.experiments() == ["dark"]
    tags = read_tags(ds.raw_files("dark")[0])
    assert tags["make"] == "Insta360" and tags["cfa_pattern"] == "RGGB" and tags["exposure_s"] > 0


def test_never_overwrites(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("a user's file")
    with pytest.raises(InputError, match="already exists"):
        simulate_dataset(out, scale="tiny", seed=1, experiments=("dark",), progress=False)
    assert (out / "notes.txt").read_text() == "a user's file"


def test_unknown_effect_is_a_clear_error(tmp_path):
    with pytest.raises(InputError, match="unknown effect 'shutter'"):
        simulate_dataset(tmp_path / "x", scale="tiny", effects=[("shutter", {})], experiments=("dark",),
                         progress=False)
    assert not (tmp_path / "x").exists()


def test_command_line(tmp_path):
    import subprocess
    import sys

    ok = subprocess.run([sys.executable, "-m", "pipeline", "simulate", "--out", str(tmp_path / "d"), "--scale",
                         "tiny", "--seed", "2", "--experiments", "dark", "--effect", "dark_current:rate_e_per_s=2",
                         "--no-progress"], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    truth = yaml.safe_load((tmp_path / "d.truth" / "truth.yaml").read_text())
    assert truth["effects"]["dark_current"]["rate_e_per_s"] == 2.0
    bad = subprocess.run([sys.executable, "-m", "pipeline", "simulate", "--out", str(tmp_path / "e"),
                          "--effect", "dark_current:rate=x"], capture_output=True, text=True)
    assert bad.returncode == 1
    assert bad.stderr.strip().count("\n") == 0 and bad.stderr.startswith("error:")


def test_a_scale_object_sets_the_frame_counts(tmp_path):
    """A benchmark's own Scale (the lens region of one scale, fewer frames per setting) is accepted."""
    from pipeline.simulate.dataset import SCALES, Scale

    fewer = Scale("tiny", lens_px=SCALES["tiny"].lens_px, dark_frames=2, linearity_frames=2)
    root = simulate_dataset(tmp_path / "d", scale=fewer, seed=1, experiments=("dark",), progress=False)
    n_default = len(open_dataset(simulate_dataset(tmp_path / "e", scale="tiny", seed=1, experiments=("dark",),
                                                  progress=False)).frames("dark"))
    assert len(open_dataset(root).frames("dark")) * SCALES["tiny"].dark_frames == n_default * 2
    assert yaml.safe_load((truth_dir_for(root) / "truth.yaml").read_text())["scale"]["dark_frames"] == 2


def test_lab_error_sizes_over_seeds():
    """The drawn lab errors have the stated sizes: over 4000 seeds the spread of the lamp error is the
    manufacturer's 9.1 % at 400 nm and 6.9 % at 800 nm, the reference's 2.5 %, and the photodiode's
    shape (about its mean) stays within 2 % in 96 % of labs (binomial spread 0.3 %: 0.93 to 0.98). The sample standard deviation of n normal draws has
    a relative spread 1 / sqrt(2 n) = 1.1 %: within 4 of it (4.5 %)."""
    import numpy as np

    from pipeline.simulate.lab_errors import draw_lab_errors, lamp_factor, no_lab_errors, photodiode_factor

    n = 4000
    draws = [draw_lab_errors(seed) for seed in range(n)]
    lamp = np.array([lamp_factor([400.0, 800.0], e) - 1 for e in draws])
    tol = 4 / np.sqrt(2 * n)
    assert np.std(lamp[:, 0], ddof=1) == pytest.approx(0.091, rel=tol)
    assert np.std(lamp[:, 1], ddof=1) == pytest.approx(0.069, rel=tol)
    ref = np.array([e["reference_relative_error"] for e in draws])
    assert np.std(ref, ddof=1) == pytest.approx(0.025, rel=tol)
    wl = np.arange(400.0, 701.0, 10.0)
    shape = np.array([photodiode_factor(wl, e) / (1 + e["photodiode_coefficients"][0]) - 1 for e in draws])
    within = np.mean(np.max(np.abs(shape), axis=1) < 0.02)
    assert 0.93 < within < 0.98, within
    # a perfect lab changes nothing, bit for bit
    assert np.all(lamp_factor(wl, no_lab_errors()) == 1.0) and np.all(photodiode_factor(wl, no_lab_errors()) == 1.0)


def test_lab_errors_reach_the_sidecars(tmp_path):
    """With lab_errors the C-OPS reading carries the drawn scale error and the spectrum the lamp's; the truth's
    lab R^-1 is the camera's times that factor (the B band, short of 589 nm, moves most by the lamp's shape)."""
    import numpy as np
    import pandas as pd

    from pipeline.simulate.lab_errors import lamp_factor

    root = simulate_dataset(tmp_path / "d", scale="tiny", seed=3, experiments=("absolute",), progress=False,
                            lab_errors=True)
    plain = simulate_dataset(tmp_path / "e", scale="tiny", seed=3, experiments=("absolute",), progress=False)
    truth = yaml.safe_load((truth_dir_for(root) / "truth.yaml").read_text())
    errors = truth["lab_errors"]
    ref = pd.read_csv(root / "absolute" / "source_reference.csv")
    assert float(ref["radiance_W_sr_m2_nm"].iloc[0]) == pytest.approx(6.8e-4 * (1 + errors["reference_relative_error"]),
                                                                     rel=1e-7)
    assert float(ref["uncertainty_rel"].iloc[0]) == 0.025
    spec, spec0 = (pd.read_csv(p / "absolute" / "source_spectrum.csv") for p in (root, plain))
    # same noise draw, so the ratio is the lamp factor to the file's 8 significant digits
    np.testing.assert_allclose(spec["radiance"] / spec0["radiance"], lamp_factor(spec["wavelength_nm"], errors),
                               rtol=1e-6)
    assert yaml.safe_load((truth_dir_for(plain) / "truth.yaml").read_text())["lab_errors"]["reference_relative_error"] == 0
    absolute = truth["experiments_truth"]["absolute"]
    for lens in absolute["lenses"]:
        for band in "RGB":
            assert absolute["lenses"][lens]["bands"][band]["inverse_responsivity_lab"] \
                != absolute["bands"][band]["inverse_responsivity"]


def test_pixel_sensitivity_multiplies_the_stray_light_too():
    """The flat field (PRNU) is the pixel's own sensitivity: it multiplies all the light that lands on the pixel,
    the part the optics spread (stray light) as well, so a uniform scene's electron rate with PRNU over the rate
    without it is the sensitivity map exactly (to float32 rounding, 1e-6), even with 30 % of the light spread.
    Applied before the spreading, the ratio would be (1 - f) p + f times a smoothed p: its relative spread
    (1 - f) = 0.7 of the map's."""
    import numpy as np

    from pipeline.effects import get as get_effect
    from pipeline.simulate.camera import Camera
    from pipeline.simulate.plan import FrameSpec
    from pipeline.simulate.render import Renderer

    def rates(names):
        effects = [get_effect(n, **({"fraction": 0.3} if n == "stray_light" else {})) for n in names]
        renderer = Renderer(Camera(), 64, 3, effects)
        spec = FrameSpec("both", "signal", 100.0, 0.1, radiance={"R": 1e-3, "G": 1e-3, "B": 1e-3})
        return renderer, renderer.photo_rate("far", spec)

    renderer, with_prnu = rates(["prnu", "stray_light"])
    _, without = rates(["stray_light"])
    lit = renderer.geometry("far", "air").lit & (without > 0)
    sensitivity = renderer.effects[0].maps["far"]
    np.testing.assert_allclose((with_prnu / np.where(lit, without, 1.0))[lit], sensitivity[lit], rtol=1e-6)


def test_lab_noise_draws_have_their_stated_sizes():
    """Jitter sigma and white flicker (from first differences, the drift being smooth) within 4 standard
    errors of a sample spread, sqrt(1 / (2 n)) relative; without lab noise every factor is exactly 1 and
    every offset 0 (the dataset's bytes do not change)."""
    import numpy as np

    from pipeline.simulate.lab_noise import LabNoise, draw_frame_noise, no_lab_noise

    n, noise = 4000, LabNoise()
    draw = draw_frame_noise(noise, 3, 1, n)
    tol = 4 * np.sqrt(1 / (2 * n))
    assert abs(np.std(draw.bias_offset_dn) / noise.bias_jitter_dn - 1) < tol
    flicker = np.std(np.diff(draw.light_factor)) / np.sqrt(2)
    assert abs(flicker / noise.flicker_rel_sigma - 1) < tol + 0.01     # the drift's own steps: under 1 %
    assert np.ptp(draw.light_factor) < 2 * noise.drift_rel_amplitude + 10 * noise.flicker_rel_sigma
    quiet = draw_frame_noise(no_lab_noise(), 3, 1, 50)
    assert np.all(quiet.light_factor == 1.0) and np.all(quiet.bias_offset_dn == 0.0)
