"""The simulator: same seed same bytes, never overwrites, truth beside the dataset, valid layout."""

from __future__ import annotations

import hashlib

import pytest
import yaml

from pipeline.dataset import open_dataset
from pipeline.errors import InputError
from pipeline.rawio import read_tags
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
