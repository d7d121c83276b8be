"""Stated 95 % intervals cover the truth about 95 % of the time, over simulated labs (issue 8, item 3).

Each seed simulates the absolute experiment of a new lab session with the
lab's systematic errors drawn from that seed (``simulate_dataset(...,
lab_errors=True)``, :mod:`pipeline.simulate.lab_errors`): the spectrometer's
calibration-lamp error (scale ~ N(0, 6.0 %) times the Planck ratio of a
colour-temperature error ~ N(0, 14.9 K): 9.1 % at 400 nm, 6.9 % at 800 nm in
all) and the reference radiometer's scale error at 589 nm (~ N(0, 2.5 %)),
besides the frames' own noise. The absolute stage runs on it with one
upstream calibration (dark, linearity, geometry, roll-off, spectral) of the
session-wide ``calibrated`` camera (a perfect lab: no drawn errors), and:

* R^-1 per band of the far lens is compared with the camera's true R^-1;
* the calibration (the bundle with that seed's absolute artefact) is applied
  with :func:`pipeline.bundle.apply.band_radiance` to a sphere frame of the
  linearity experiment (uniform, known radiance; not used to fit R^-1), one
  exposure-sweep frame per seed in turn (8 ms to 0.5 s); the mean radiance of
  the pixels within ``RADIANCE_MASK_DEG`` of the axis is compared with the
  truth, with sigma = hypot(random part averaged over the pixels, mean
  systematic part).

What varies over seeds: the reference scale error (2.5 %, the largest term),
the lamp's colour-temperature shape (0.1-0.9 % after the rescaling; its scale
part cancels), the spectrometer noise, the absolute frames' noise, and for the
radiance the test frame's noise and exposure. What is one draw for all seeds:
the spectral response (its shape error, including the unmeasured tail below
400 nm that puts about +0.9 % on B), the dark, linearity and roll-off
calibrations (near the axis the roll-off is 1 within its tiny error), and the
photodiode error (zero in the upstream's perfect lab; drawn it moves R^-1 by
about 0.1 %). The varying terms make up nearly all of the stated 2.5-2.7 %,
the common ones under 1 %, so the spread of z over seeds measures whether the
stated uncertainty is the one that propagates: the paper's counting of the
lamp (about 8 %, ``absolute.lamp_model: profile``) states three times too
much and gives a z spread near 0.35, below the chi-square bound; a budget
without the reference term would state too little and fail the count.

Bounds, for N = ``N_SEEDS`` independent labs and each band and quantity,
each at a tail probability of ``TAIL`` (0.1 %):

* under-statement: the number of labs whose 95 % interval covers the truth
  is Binomial(N, 0.95); it must not fall below its TAIL quantile;
* over-statement (which the count cannot see: all N covered has probability
  0.95^N = 29 % at N = 24): the sample variance s^2 of z = (estimate -
  truth) / sigma over seeds, (N - 1) s^2 ~ chi-square(N - 1), must lie inside
  its TAIL and 1 - TAIL quantiles (0.27 to 2.27 at N = 24). The sample
  variance (about the seeds' mean) is blind to the common offsets above.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import yaml
from scipy import stats

from pipeline.bundle.apply import band_radiance
from pipeline.io.artefact import model_effects, read_artefact
from pipeline.io.bands import BANDS
from pipeline.bundle.calibration import BUNDLE_STAGES, build_bundle, read_bundle
from pipeline.io.frames import lens_images
from pipeline.radiometry import measurement as mm
from pipeline.io.rawio import read_raw
from pipeline.simulate import simulate_dataset, truth_dir_for
from pipeline.runner.workflow import run_stage

N_SEEDS = 24
FIRST_SEED = 1000
LENS = "far"
#: tail probability of each bound (two quantities x three bands x two sides: about 1 % in all)
TAIL = 0.001
#: the normal 95 % interval
K95 = stats.norm.ppf(0.975)
#: pixels averaged for the calibrated radiance: near the axis, where the roll-off is 1 within its error
RADIANCE_MASK_DEG = 10.0


@pytest.fixture(scope="module")
def over_seeds(calibrated, config, tmp_path_factory):
    """Per seed and band: (R^-1, sigma, true R^-1) and (radiance, sigma, true radiance)."""
    root, truth, _, artefacts, _, meta = calibrated
    frames = pd.read_csv(root / "linearity" / "frames.csv")
    sphere = frames[(frames["lens"] == LENS) & (frames["kind"] == "signal") & (frames["sweep"] == "exposure")]
    true_radiance = truth["experiments_truth"]["linearity"]["exposure_source_band_radiance"][LENS]
    upstream = {stage: {LENS: artefacts[stage][LENS]} for stage in BUNDLE_STAGES if stage != "absolute"}
    rows = []
    for i in range(N_SEEDS):
        seed = FIRST_SEED + i
        work = tmp_path_factory.mktemp(f"lab{seed}")
        data = simulate_dataset(work / "dataset", scale="tiny", seed=seed, experiments=("absolute",),
                                progress=False, lab_errors=True)
        lab_truth = yaml.safe_load((truth_dir_for(data) / "truth.yaml").read_text())
        absolute = {LENS: work / "absolute" / f"{LENS}.nc"}
        run_stage("absolute", data, config, absolute,
                  {name: upstream[name] for name in ("spectral", "geometry", "dark", "linearity")})
        art = read_artefact(absolute[LENS], "absolute")
        bundle_path = work / "calibration.nc"
        build_bundle({**upstream, "absolute": absolute}, bundle_path, meta["camera"], {LENS: meta["lenses"][LENS]},
                     config)
        bundle = read_bundle(bundle_path)
        effects = model_effects(bundle)
        frame_path = root / "linearity" / sphere["file"].iloc[i % len(sphere)]
        raw = read_raw(frame_path)
        span = bundle["lens_region_px"].sel(lens=LENS).values
        images = lens_images(raw, (tuple(span[0]), tuple(span[1])), LENS)
        settings = mm.FrameSettings(exposure_s=float(raw.exposure_s), iso=float(raw.iso))
        for band in BANDS:
            m = band_radiance(images, bundle, LENS, band, "air", effects, settings, source=frame_path)
            theta = bundle["theta_deg"].sel(lens=LENS, medium="air", band=band).values
            good = (theta < RADIANCE_MASK_DEG) & (m.flags == 0) & np.isfinite(m.value)
            n = int(good.sum())
            assert n >= 4, (seed, band, n)
            radiance = float(np.mean(m.value[good]))
            radiance_sigma = float(np.hypot(np.sqrt(np.sum(m.random_sigma[good] ** 2)) / n,
                                            np.mean(m.systematic_sigma[good])))
            a = art.sel(band=band)
            rows.append({"seed": seed, "band": band,
                         "r_inv": float(a["inverse_responsivity"]), "r_inv_sigma": float(a["inverse_responsivity_sigma"]),
                         "r_inv_true": lab_truth["experiments_truth"]["absolute"]["bands"][band]["inverse_responsivity"],
                         "radiance": radiance, "radiance_sigma": radiance_sigma,
                         "radiance_true": true_radiance[band], "exposure_s": float(raw.exposure_s)})
    return pd.DataFrame(rows)


def _check_coverage(z: np.ndarray, what: str) -> None:
    n = z.size
    covered = int(np.sum(np.abs(z) <= K95))
    # smallest count with P(X < k) <= TAIL for X ~ Binomial(n, 0.95)
    k_min = int(stats.binom.ppf(TAIL, n, 0.95))
    lo, hi = stats.chi2.ppf([TAIL, 1 - TAIL], n - 1) / (n - 1)
    s2 = float(np.var(z, ddof=1))
    info = f"{what}: {covered}/{n} covered (>= {k_min}), s^2(z) = {s2:.2f} in [{lo:.2f}, {hi:.2f}], mean z {z.mean():+.2f}"
    assert covered >= k_min, info
    assert lo <= s2 <= hi, info


@pytest.mark.parametrize("band", BANDS)
def test_inverse_responsivity_interval_covers_the_truth(over_seeds, band):
    t = over_seeds[over_seeds["band"] == band]
    assert t["seed"].nunique() == N_SEEDS >= 20
    z = ((t["r_inv"] - t["r_inv_true"]) / t["r_inv_sigma"]).to_numpy()
    _check_coverage(z, f"R^-1 {band}")


@pytest.mark.parametrize("band", BANDS)
def test_calibrated_radiance_interval_covers_the_truth(over_seeds, band):
    t = over_seeds[over_seeds["band"] == band]
    assert t["exposure_s"].nunique() > 1   # sphere frames at several exposures, none of them fitted R^-1
    z = ((t["radiance"] - t["radiance_true"]) / t["radiance_sigma"]).to_numpy()
    _check_coverage(z, f"radiance {band}")


def test_the_labs_differ(over_seeds):
    """The lab errors are drawn per seed: R^-1 scatters by about the reference's 2.5 % (not by the frame
    noise alone, about 0.3 %); a sample spread below 1.2 % has chance under 1e-4 at N = 24."""
    for band in BANDS:
        t = over_seeds[over_seeds["band"] == band]
        assert float(np.std(t["r_inv"] / t["r_inv_true"], ddof=1)) > 0.012, band
