"""How honest the geometry's stated uncertainty is: fitted centre and theta against the simulator's truth.

    python benchmarks/bench_geometry_honesty.py DATASET RESULTS [--air-only]

DATASET is a simulated dataset (its truth beside it, ``DATASET.truth/``), RESULTS the results folder the
workflow (or ``pipeline.runner.workflow.run_stage``) wrote its geometry artefacts into
(``RESULTS/geometry/<lens>.nc``). Per lens, medium and band: the error of the fitted principal point with
its stated 2 x 2 covariance, and the error of the theta map at four pixels (5, 30, 55 and 70 deg, each at its
own azimuth a quarter turn from the last) with their 4 x 4 propagated covariance. Prints each fit and the
sums, which are chi-square with 2 and 4 degrees of freedom per fit when the stated covariance is honest.
Reads the truth: a measurement of the pipeline, never part of it. The covariance estimate is the
artefact's (``geometry.covariance``; rerun the geometry with another to compare).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import xarray as xr
import yaml
from scipy import stats

from pipeline.geometry.maps import pixel_of_direction
from pipeline.geometry.scaramuzza import FisheyeModel
from pipeline.geometry.theta_uncertainty import theta_covariance
from pipeline.simulate.dataset import truth_dir_for
from pipeline.stages.geometry_maps import model_from_dataset

THETA_DEG = np.array([5.0, 30.0, 55.0, 70.0])
PHI_DEG = np.array([0.0, 90.0, 180.0, 270.0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("results", type=Path)
    ap.add_argument("--air-only", action="store_true", help="theta in air only (water beyond the boards' reach)")
    args = ap.parse_args()
    truth = yaml.safe_load((truth_dir_for(args.dataset) / "truth.yaml").read_text())["experiments_truth"]["geometry"]
    sums = {"centre": [0.0, 0], "theta": [0.0, 0]}
    for lens in sorted(truth["models"]):
        art = xr.open_dataset(args.results / "geometry" / f"{lens}.nc").load()
        names = [str(n) for n in art["geometry_parameter"].values]
        estimate = art["geometry_parameter_covariance"].attrs.get("estimate", "?")
        for medium in ("air", "water"):
            for band in ("R", "G", "B"):
                t = FisheyeModel.from_dict(truth["models"][lens][medium][band]["band"])
                m = model_from_dataset(art, medium, band)
                cov = art["geometry_parameter_covariance"].sel(medium=medium, band=band).values
                e = np.array([m.xc - t.xc, m.yc - t.yc])
                chi_c = float(e @ np.linalg.solve(cov[:2, :2], e))
                sums["centre"][0] += chi_c
                sums["centre"][1] += 2
                line = (f"{lens}/{medium}/{band} ({estimate}): centre error {e[0]:+.3f} {e[1]:+.3f} px, sigma "
                        f"{np.sqrt(cov[0, 0]):.3f} {np.sqrt(cov[1, 1]):.3f}, chi2 {chi_c:.1f}")
                if medium == "air" or not args.air_only:
                    u, v = pixel_of_direction(m, THETA_DEG, PHI_DEG)
                    col, row = np.round(u), np.round(v)
                    fitted = art["theta_deg"].sel(medium=medium, band=band).values[row.astype(int), col.astype(int)]
                    err = fitted - t.theta_phi(col, row)[0]
                    s = theta_covariance(m, names, cov, col, row)
                    chi_t = float(err @ np.linalg.solve(s, err))
                    sums["theta"][0] += chi_t
                    sums["theta"][1] += err.size
                    line += (f"; theta error {np.round(err, 2)} deg, sigma {np.round(np.sqrt(np.diag(s)), 2)}, "
                             f"chi2 {chi_t:.1f}")
                print(line)
    for name, (chi2, dof) in sums.items():
        print(f"{name}: chi2 {chi2:.1f} for {dof} (p = {stats.chi2.sf(chi2, dof):.2g})")
    from record import append_rows

    append_rows("bench_geometry_honesty", [{"quantity": name, "chi2": round(chi2, 1), "dof": dof,
                                            "p": f"{stats.chi2.sf(chi2, dof):.2g}"} for name, (chi2, dof) in sums.items()])


if __name__ == "__main__":
    main()
