"""The geometry at the rim of the image circle, beyond the boards: fitted theta against the simulator's truth.

    python benchmarks/bench_rim_theta.py SEED [SCALE] [--work DIR]

Simulates the geometry experiment of SEED at SCALE (default ``tiny``; ``medium`` for 576-pixel band
images) into ``--work`` (kept: a second call reuses the frames and the artefacts), runs the geometry
stage for each lens, and prints per lens, medium and band the fitted half field of view against the
true one, and the error of the theta map at four pixels at 0.98 of the true half field of view (azimuths
0, 90, 180, 270 deg) with their stated sigma and the chi-square of the four under their propagated 4 x 4
covariance (chi-square with 4 degrees of freedom when the stated covariance is honest there). Reads the
truth: a measurement of the pipeline, never part of it. README, "Uncertainty of the field angle".
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import xarray as xr
import yaml

from pipeline.config import load_config
from pipeline.geometry.maps import pixel_of_direction
from pipeline.geometry.scaramuzza import FisheyeModel
from pipeline.geometry.theta_uncertainty import theta_covariance
from pipeline.simulate.dataset import simulate_dataset, truth_dir_for
from pipeline.stages.geometry_maps import model_from_dataset
from pipeline.runner.workflow import run_stage

#: where on the true field the rim points sit (fraction of the true half field of view) and their azimuths
RIM_FRACTION = 0.98
PHI_DEG = np.array([0.0, 90.0, 180.0, 270.0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seed", type=int)
    ap.add_argument("scale", nargs="?", default="tiny")
    ap.add_argument("--work", default="/tmp/bench-rim", help="datasets and geometry artefacts go here")
    args = ap.parse_args()
    root = Path(args.work) / f"{args.scale}{args.seed}" / "ds"
    if not root.exists():
        simulate_dataset(root, scale=args.scale, seed=args.seed, experiments=("geometry",), progress=False)
    truth = yaml.safe_load((truth_dir_for(root) / "truth.yaml").read_text())["experiments_truth"]["geometry"]
    config = load_config(overrides={"dataset": str(root)})
    rows = []
    for lens in sorted(truth["models"]):
        out = root.parent / f"geometry_{lens}.nc"
        if not out.exists():
            run_stage("geometry", root, config, {lens: out})
        art = xr.open_dataset(out).load()
        names = [str(n) for n in art["geometry_parameter"].values]
        for medium in ("air", "water"):
            for band in ("R", "G", "B"):
                t = FisheyeModel.from_dict(truth["models"][lens][medium][band]["band"])
                m = model_from_dataset(art, medium, band)
                half_fit = float(art["half_fov_deg"].sel(medium=medium, band=band))
                cov = art["geometry_parameter_covariance"].sel(medium=medium, band=band).values
                u, v = pixel_of_direction(t, np.full(PHI_DEG.size, RIM_FRACTION * t.half_fov_deg), PHI_DEG)
                error = m.theta_phi(u, v)[0] - t.theta_phi(u, v)[0]
                s = theta_covariance(m, names, cov, u, v)
                chi2 = float(error @ np.linalg.solve(s, error))
                print(f"seed {args.seed} {lens}/{medium}/{band}: half_fov fit {half_fit:.2f} true {t.half_fov_deg:.2f} "
                      f"d {half_fit - t.half_fov_deg:+.2f}; rim err {np.round(error, 2)} sigma "
                      f"{np.round(np.sqrt(np.diag(s)), 2)} chi2 {chi2:.2f}", flush=True)
                rows.append({"seed": args.seed, "scale": args.scale, "lens": lens, "medium": medium, "band": band,
                             "half_fov_fit_deg": round(half_fit, 2), "half_fov_true_deg": round(t.half_fov_deg, 2),
                             "rim_rms_error_deg": round(float(np.sqrt(np.mean(error ** 2))), 3),
                             "rim_chi2": round(chi2, 2), "rim_points": error.size})
    from record import append_rows

    append_rows("bench_rim_theta", rows)


if __name__ == "__main__":
    main()
