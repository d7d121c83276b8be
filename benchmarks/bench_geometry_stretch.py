"""Stretch auto's stated theta uncertainty against the simulator's truth, and the one-step jackknife against the refit.

    PYTHONPATH=src python benchmarks/bench_geometry_stretch.py DATASET > docs/figures-data/geometry_stretch_simulated.csv

DATASET is a simulated dataset with the geometry experiment (its truth beside it, ``DATASET.truth/``; made
when absent as the medium scale, seed 3, geometry only, as tests/geometry/test_geometry_theta_accuracy.py makes it).
Per lens, medium and band the corners the geometry stage detects are fitted with stretch "symmetric" and
"none" (the latter at the symmetric fit's centre, as stretch auto does), each with the one-step
leave-one-board-out jackknife and with the full refit per board. Columns: the stretch test's p-value and
auto's choice; the chi-square of the theta errors at four pixels (5, 30, 55, 72 deg, a quarter turn apart,
as the test) with the propagated 4 x 4 covariance for: the symmetric fit, the none fit with its own
covariance, auto with the chosen fit's own covariance (what ``select_stretch`` states), and auto with the
symmetric fit's covariance (what it stated before); and the linearised jackknife's sigma of the centre and of theta at those pixels over
the refit's. A last row per lens holds the sums. Reads the truth: a measurement, never part of the pipeline.
"""

from __future__ import annotations

import csv
import datetime
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from pipeline.config import load_config
from pipeline.io.dataset import open_dataset
from pipeline.geometry.calibrate import calibrate, stretch_test
from pipeline.geometry.maps import pixel_of_direction
from pipeline.geometry.scaramuzza import FisheyeModel
from pipeline.geometry.theta_uncertainty import theta_covariance
from pipeline.simulate.dataset import simulate_dataset, truth_dir_for
from pipeline.stages.geometry import reduce_geometry

THETA_DEG = np.array([5.0, 30.0, 55.0, 72.0])
PHI_DEG = np.array([0.0, 90.0, 180.0, 270.0])
CHI2_COLUMNS = ("chi2_symmetric", "chi2_none_own", "chi2_auto_own", "chi2_auto_symmetric_cov")


def embedded(res, names):
    """The covariance of ``res`` over ``names`` (parameters it does not fit with zero variance)."""
    cov = np.zeros((len(names), len(names)))
    at = [names.index(n) for n in res.parameter_names]
    cov[np.ix_(at, at)] = res.parameter_covariance
    return cov


def chi2(model, names, cov, truth):
    u, v = pixel_of_direction(model, THETA_DEG, PHI_DEG)
    err = model.theta_phi(u, v)[0] - truth.theta_phi(u, v)[0]
    return float(err @ np.linalg.solve(theta_covariance(model, names, cov, u, v), err))


def sigmas(res, names, u, v):
    """Stated sigma of xc, yc (px) and of theta (degree) at (u, v)."""
    cov = embedded(res, names)
    s = np.sqrt(np.diag(cov))
    return np.concatenate([[s[0], s[1]], np.sqrt(np.diag(theta_covariance(res.model, names, cov, u, v)))])


def main() -> None:
    root = Path(sys.argv[1])
    if not (root / "dataset.yaml").is_file():
        simulate_dataset(root, scale="medium", seed=3, experiments=("geometry",), progress=False)
    truth = yaml.safe_load((truth_dir_for(root) / "truth.yaml").read_text())["experiments_truth"]["geometry"]
    config = load_config(overrides={"dataset": str(root)})
    cfg = config["geometry"]
    reduced = reduce_geometry(open_dataset(root), config)
    table = pd.DataFrame(reduced["rows"])
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    meta = {"date": datetime.date.today().isoformat(), "commit": commit,
            "machine": f"{platform.node()} {platform.machine()}".strip(),
            "command": f"PYTHONPATH=src python benchmarks/bench_geometry_stretch.py {root}"}
    options = dict(degree=cfg["polynomial_degree"], min_frames=cfg["min_frames"],
                   outlier_factor=cfg["frame_outlier_factor"], point_outlier_factor=cfg["corner_outlier_factor"],
                   covariance="board_jackknife")
    writer = None
    for lens in ("far", "close"):
        sums = dict.fromkeys(CHI2_COLUMNS, 0.0)
        for medium in ("air", "water"):
            centre = None
            for band in ("G", "R", "B"):
                rows = table[(table["lens"] == lens) & (table["medium"] == medium) & (table["band"] == band)]
                pts = [r["corners"] if r["found"] else None for _, r in rows.sort_values("frame").iterrows()]
                shape = reduced["maxima"][(lens, medium, band)].shape
                board = reduced["boards"][medium].corners_mm()
                t = FisheyeModel.from_dict(truth["models"][lens][medium][band]["band"])
                fits = {}
                for stretch in ("symmetric", "none"):
                    guess = centre if stretch == "symmetric" else (fits["symmetric", 0].model.xc,
                                                                   fits["symmetric", 0].model.yc)
                    for refit in (0, 1000):
                        fits[stretch, refit] = calibrate(pts, board, shape, stretch=stretch, centre_guess=guess,
                                                         jackknife_refit_max_boards=refit, **options)
                sym, none = fits["symmetric", 0], fits["none", 0]
                if band == "G":
                    centre = (sym.model.xc, sym.model.yc)
                names = list(sym.parameter_names)
                p = stretch_test(sym)["p_value"]
                chosen = "symmetric" if p < cfg["stretch_significance"] else "none"
                auto = fits[chosen, 0]
                values = {"chi2_symmetric": chi2(sym.model, names, sym.parameter_covariance, t),
                          "chi2_none_own": chi2(none.model, names, embedded(none, names), t),
                          "chi2_auto_own": chi2(auto.model, names, embedded(auto, names), t),
                          "chi2_auto_symmetric_cov": chi2(auto.model, names, sym.parameter_covariance, t)}
                for k in CHI2_COLUMNS:
                    sums[k] += values[k]
                row = {"lens": lens, "medium": medium, "band": band, "boards": len(sym.used_frames),
                       "stretch_p_value": round(p, 3), "auto_chosen": chosen,
                       **{k: round(v, 2) for k, v in values.items()}}
                for stretch in ("symmetric", "none"):
                    u, v = pixel_of_direction(fits[stretch, 0].model, THETA_DEG, PHI_DEG)
                    ratio = sigmas(fits[stretch, 0], names, u, v) / sigmas(fits[stretch, 1000], names, u, v)
                    row[f"{stretch}_one_step_over_refit_centre_min"] = round(float(ratio[:2].min()), 2)
                    row[f"{stretch}_one_step_over_refit_theta_min"] = round(float(ratio[2:].min()), 2)
                    row[f"{stretch}_one_step_over_refit_theta_max"] = round(float(ratio[2:].max()), 2)
                if writer is None:
                    writer = csv.DictWriter(sys.stdout, fieldnames=list(row) + list(meta))
                    writer.writeheader()
                writer.writerow({**row, **meta})
                sys.stdout.flush()
        writer.writerow({"lens": lens, "medium": "all", "band": "sum", **{k: round(v, 1) for k, v in sums.items()},
                         **meta})
        sys.stdout.flush()


if __name__ == "__main__":
    main()
