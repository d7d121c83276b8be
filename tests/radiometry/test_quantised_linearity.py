"""The linearity stage on a quantised (8-bit) sensor whose full well fills before its ADC clips.

The frames come from a stated sensor model written here (not the simulator): one rectilinear region,
uniformly lit, an exposure sweep at ISO 100. Per raw site, in DN,

    value = clip(round(B0 + K min(Poisson(Q t), W) + N(0, READ_DN)), 0, 255)

with the black level B0, the conversion gain K (DN per electron), the photon rate Q (electrons per
second), a full well W of ``WELL_TOP_DN`` / K electrons and the read noise ``READ_DN`` = 0.3 DN (most
dark pixels read B0 in every frame). The well puts every pixel's ceiling at raw 247, eight steps below
the white level 255: no raw value reaches the white level, so only the data can say where the sensor
saturates, by the plateau of the mean or the collapse of the temporal variance. Every draw uses a fixed
seed.
"""

from __future__ import annotations

import copy
import logging
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import xarray as xr
import yaml

from pipeline.io.dataset import write_md5sums
from pipeline.errors import InputError
from pipeline.radiometry.saturation import saturated_settings
from pipeline.io.rawio import write_dng
from pipeline.runner.workflow import run_stage

LENS = "main"
#: raw sites per side of the lens region (a rectilinear region, lit to its edges)
SIDE_PX = 64
META = {
    "layout": 1,
    "camera": {"make": "Generic", "model": "EightBit", "serial": "Q8-0001"},
    "lenses": {LENS: {"rows": [0, SIDE_PX], "cols": [0, SIDE_PX], "projection": "rectilinear"}},
    "chessboard": {"inner_corners": [8, 6], "square_mm": {"air": 30.0, "water": 20.0}},
    "description": "a quantised 8-bit sensor written by tests/radiometry/test_quantised_linearity.py",
}

# the 8-bit sensor model
WHITE_DN = 255
BLACK_DN = 10.0                 # black level
READ_DN = 0.3                   # read noise (below one step)
GAIN_DN_PER_E = 0.1             # conversion gain K at ISO 100
WELL_TOP_DN = WHITE_DN - 8      # raw value of a full well: eight steps below the white level
FULL_WELL_E = (WELL_TOP_DN - BLACK_DN) / GAIN_DN_PER_E
ISO = 100.0
#: signal above black (DN) the sweep's settings aim at, shortest exposure first: up to the well's 237 DN
#: in steps of 30 DN or less, then three settings beyond it
TARGET_SIGNAL_DN = (5.0, 12.0, 25.0, 45.0, 70.0, 95.0, 125.0, 155.0, 185.0, 210.0, 230.0, 260.0, 320.0, 400.0)
PHOTON_RATE_E_PER_S = 4000.0
N_FRAMES = 8
DARK_EXPOSURES_S = (0.001, 0.05, 0.2)
N_DARK_FRAMES = 4
#: a tolerance is this many standard errors of the quantity under the injected noise
K_SIGMA = 4.0


def _exposure_s(target_dn: float) -> float:
    return round(target_dn / GAIN_DN_PER_E / PHOTON_RATE_E_PER_S, 6)


def _frame(rng, t_s: float, light: float = 1.0) -> np.ndarray:
    electrons = np.minimum(rng.poisson(PHOTON_RATE_E_PER_S * light * t_s, (SIDE_PX, SIDE_PX)), FULL_WELL_E)
    value = BLACK_DN + GAIN_DN_PER_E * electrons + rng.normal(0.0, READ_DN, (SIDE_PX, SIDE_PX))
    return np.clip(np.rint(value), 0, WHITE_DN).astype(np.uint16)


def write_dataset(root: Path, *, other_light: dict[int, float] | None = None, seed: int = 5) -> Path:
    """Dark frames at ISO 100 and the lit exposure sweep; ``other_light`` maps a setting's index in
    TARGET_SIGNAL_DN to the fraction of the sweep's light its frames were taken under."""
    rng = np.random.default_rng(seed)
    (root / "dataset.yaml").parent.mkdir(parents=True, exist_ok=True)
    (root / "dataset.yaml").write_text(yaml.safe_dump(META, sort_keys=False))
    start = datetime(2024, 5, 2, 10, 0, 0)
    n = 0

    def write(folder: Path, cfa, t_s) -> str:
        nonlocal n
        name = f"raw/f{n:03d}.dng"
        write_dng(folder / name, cfa, exposure_s=t_s, iso=ISO, time=start + timedelta(seconds=n),
                  black_level=0, white_level=WHITE_DN, make="Generic", model="EightBit", serial="Q8-0001")
        n += 1
        return name

    dark_dir = root / "dark"
    (dark_dir / "raw").mkdir(parents=True)
    rows = [{"file": write(dark_dir, _frame(rng, t, light=0.0), t), "lens": LENS, "kind": "dark"}
            for t in DARK_EXPOSURES_S for _ in range(N_DARK_FRAMES)]
    pd.DataFrame(rows).to_csv(dark_dir / "frames.csv", index=False)
    lin_dir = root / "linearity"
    (lin_dir / "raw").mkdir(parents=True)
    rows = []
    for i, target in enumerate(TARGET_SIGNAL_DN):
        t = _exposure_s(target)
        light = (other_light or {}).get(i, 1.0)
        rows += [{"file": write(lin_dir, _frame(rng, t, light), t), "lens": LENS, "kind": "signal",
                  "sweep": "exposure"} for _ in range(N_FRAMES)]
    pd.DataFrame(rows).to_csv(lin_dir / "frames.csv", index=False)
    write_md5sums(root)
    return root


def _run(root: Path, config: dict, out: Path) -> xr.Dataset:
    dark = {LENS: out / "dark.nc"}
    run_stage("dark", root, config, dark)
    return run_stage("linearity", root, config, {LENS: out / "linearity.nc"}, {"dark": dark})[LENS]


def _n_pixels(art: xr.Dataset, what: str) -> int:
    """The fewest band pixels of any band in the averaging mask (``n_mask``) or the photon-transfer region
    (``n_ptc``), as the artefact's frame table states them."""
    return int(art[f"obs_frame__{what}"].values.min())


def _gain_tolerance(art: xr.Dataset) -> float:
    """Relative tolerance of the conversion gain: K_SIGMA standard errors under the injected noise.

    A setting's temporal variance over N band pixels and n frames has the relative standard error
    r = sqrt(2 / (N (n - 1))) (Gaussian sampling). The photon-transfer line v = K s + c through the
    settings 3 shot-noise sigma below the well, each known to r of its model variance, has the slope's
    standard error of that weighted fit; the three bands share K (each its own c): over sqrt(3)."""
    r = np.sqrt(2.0 / (_n_pixels(art, "n_ptc") * (N_FRAMES - 1)))
    signal = np.array([s for s in TARGET_SIGNAL_DN
                       if s < WELL_TOP_DN - BLACK_DN - 3.0 * np.sqrt(GAIN_DN_PER_E * (WELL_TOP_DN - BLACK_DN))])
    model = GAIN_DN_PER_E * signal + READ_DN**2 + 1.0 / 12.0
    design = np.column_stack([signal, np.ones_like(signal)]) / (r * model)[:, None]
    k_se = float(np.sqrt(np.linalg.inv(design.T @ design)[0, 0]))
    return K_SIGMA * k_se / GAIN_DN_PER_E / np.sqrt(3.0)


def _mean_tolerance_dn(art: xr.Dataset, signal_dn: float) -> float:
    """K_SIGMA standard errors of a setting's mask mean: shot and read noise of one raw site over the
    fewest mask pixels and the frames (a G band pixel averages two sites, which only helps)."""
    site_var = GAIN_DN_PER_E * signal_dn + READ_DN**2 + 1.0 / 12.0
    return K_SIGMA * np.sqrt(site_var / (_n_pixels(art, "n_mask") * N_FRAMES))


def _settings(art: xr.Dataset) -> pd.DataFrame:
    names = [v for v in art.data_vars if v.startswith("obs_setting__")]
    return pd.DataFrame({v.split("__", 1)[1]: art[v].values for v in names})


@pytest.fixture(scope="module")
def quantised(config, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("quantised")
    return _run(write_dataset(tmp / "ds"), config, tmp / "out")


#: the setting of the sweep taken under other light, and the fraction of the sweep's light it had
OTHER_LIGHT_SETTING = 6
OTHER_LIGHT_FRACTION = 0.6


@pytest.fixture(scope="module")
def other_light(config, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("other_light")
    root = write_dataset(tmp / "ds", other_light={OTHER_LIGHT_SETTING: OTHER_LIGHT_FRACTION})
    return _run(root, config, tmp / "out")


def _assert_gain_and_well(art: xr.Dataset) -> None:
    tol = _gain_tolerance(art)
    # the brief's 2 % holds several standard errors of the injected noise (about 0.5 % here)
    assert tol < 0.02, tol
    k = float(art["conversion_gain_dn_per_e"])
    assert abs(k / GAIN_DN_PER_E - 1.0) < 0.02, (k, tol)
    sat = art["saturation_dn"]
    assert int(sat.attrs["reached"]) == 1 and sat.attrs["saturated_by"] == "full well (plateau)", sat.attrs
    # the plateau: every pixel at the well, known to the read noise over the mask
    assert abs(float(sat) - (WELL_TOP_DN - BLACK_DN)) < _mean_tolerance_dn(art, 0.0) + 0.5, float(sat)
    st = _settings(art)
    assert not (st["clipped_at_white_level"] == 1).any()     # the ADC never clipped: the data said it
    target = np.array(TARGET_SIGNAL_DN)[np.argsort(TARGET_SIGNAL_DN)]
    exposures = np.array([_exposure_s(s) for s in target])
    for band, rows in st.groupby("band"):
        rows = rows.sort_values("exposure_s")
        aim = np.interp(rows["exposure_s"], exposures, target)
        sigma_at_well = np.sqrt(GAIN_DN_PER_E * (WELL_TOP_DN - BLACK_DN))
        # settings whose shot noise reaches the well within 2 sigma (230 DN: 1.5 sigma below it) are
        # saturated, the flattened variance as much as the plateau; those 3 sigma below it are used
        near = aim > WELL_TOP_DN - BLACK_DN - 2.0 * sigma_at_well
        assert (rows.loc[near, "saturated"] == 1).all() and (rows.loc[near, "used"] == 0).all(), (band, rows)
        below = aim < WELL_TOP_DN - BLACK_DN - 3.0 * sigma_at_well
        assert (rows.loc[below & (rows["other_light"] == 0), "used"] == 1).all(), (band, rows)


def test_variance_stall_below_the_white_level_is_saturation(quantised):
    """The well fills 8 steps below the white level; the setting whose variance stopped growing (its pixels
    touch the well) is left out with the plateau, and the photon transfer gives the sensor's gain."""
    _assert_gain_and_well(quantised)
    assert int(quantised["n_other_light_settings"]) == 0
    assert quantised["n_other_light_settings"].attrs["settings"] == ""


def test_setting_under_other_light_is_named_and_left_out(other_light, caplog):
    art = other_light
    assert int(art["n_other_light_settings"]) == 1
    line = art["n_other_light_settings"].attrs["settings"]
    t = _exposure_s(TARGET_SIGNAL_DN[OTHER_LIGHT_SETTING])
    first_file = f"f{len(DARK_EXPOSURES_S) * N_DARK_FRAMES + OTHER_LIGHT_SETTING * N_FRAMES:03d}.dng"
    assert "\n" not in line and first_file in line and f"{t:g} s" in line and "other light" in line, line
    expected = float(line.split("neighbours give ")[1].split(" DN")[0])
    measured = float(line.split("it measured ")[1].split(" DN")[0])
    truth = TARGET_SIGNAL_DN[OTHER_LIGHT_SETTING]
    # the neighbours (95 and 155 DN) lie on the line through the true signal; the number is printed to
    # four digits (0.05 DN)
    assert abs(expected - truth) < _mean_tolerance_dn(art, truth) + 0.05, line
    assert abs(measured - OTHER_LIGHT_FRACTION * truth) < _mean_tolerance_dn(art, truth) + 0.05, line
    st = _settings(art)
    stray = np.isclose(st["exposure_s"], t)
    assert (st.loc[stray, "other_light"] == 1).all() and (st.loc[stray, "used"] == 0).all()
    assert (st.loc[stray, "saturated"] == 0).all()       # named, not absorbed as saturated
    assert (st.loc[~stray, "other_light"] == 0).all()
    # the rest of the sweep is fitted as without the stray setting
    _assert_gain_and_well(art)


def test_setting_under_other_light_is_logged(config, tmp_path, caplog):
    """The same line in the log; and a sweep most of whose settings stray (here: more than the configured
    tenth) stops the stage with one line naming the first."""
    root = write_dataset(tmp_path / "ds", other_light={OTHER_LIGHT_SETTING: OTHER_LIGHT_FRACTION, 3: 1.6})
    strict = copy.deepcopy(config)
    strict["linearity"]["non_monotonic_max_fraction"] = 0.1
    with pytest.raises(InputError) as err:
        _run(root, strict, tmp_path / "out")
    message = str(err.value)
    assert "\n" not in message and "2 of 14 settings" in message and "non_monotonic_max_fraction" in message, message
    with caplog.at_level(logging.WARNING, logger="pipeline.linearity"):
        art = _run(root, config, tmp_path / "out2")
    lines = [r.getMessage() for r in caplog.records if "leaves the sweep's rise" in r.getMessage()]
    assert len(lines) == 2 == int(art["n_other_light_settings"]), lines
    assert art["n_other_light_settings"].attrs["settings"] == " | ".join(lines)


def test_rounding_at_low_signal_is_not_a_collapse():
    """0.3 DN of dark noise and 0.01 DN per electron, rounded: the variance falls from 0.25 DN^2 at 0.5 DN
    (half-way between two codes) to 0.11 DN^2 at 1 DN (on a code), below half of it, and then grows with
    the signal; none of it is saturation."""
    rng = np.random.default_rng(8)
    gain_dn_per_e, n_pixels, n_frames = 0.01, 4000, 8
    signal = np.array([0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0])
    frames = np.rint(gain_dn_per_e * rng.poisson(signal[:, None, None] / gain_dn_per_e, (len(signal), n_frames, n_pixels))
                     + rng.normal(0.0, READ_DN, (len(signal), n_frames, n_pixels)))
    variance = frames.var(axis=1, ddof=1).mean(axis=1)
    assert variance[1] < 0.5 * variance[0], variance      # a fall a ratio alone takes for a collapse
    rel_se = np.sqrt(2.0 / (n_pixels * (n_frames - 1)))
    flags = saturated_settings(signal, frames.mean(axis=(1, 2)), variance, 0.5, 0.5, stall_fraction=0.25,
                               variance_rel_se=rel_se, noise_sigma=3.0)
    assert not flags.any(), (variance, flags)
