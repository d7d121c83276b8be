"""Time the geometry fit's covariance estimates: the board-clustered sandwich against the jackknife.

    python benchmarks/bench_geometry_covariance.py [--boards 12 16 20] [--corners 20] [--repeat 5]

What ``geometry.covariance`` costs per lens, medium and band beside the fit itself: a Jacobian of the
fit's size (2 rows per corner; 8 model parameters plus 6 pose parameters per board, each pose column
non-zero on its own board's rows only, as in pipeline.geometry.calibrate) with random entries, and
random residuals; the values do not change the cost. Prints the median wall time of ``--repeat`` runs
of :func:`pipeline.geometry.calibrate.intrinsic_covariance` (board-clustered) and
:func:`pipeline.geometry.calibrate.jackknife_covariance` per board count.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from pipeline.geometry.calibrate import intrinsic_covariance, jackknife_covariance

N_INTRINSIC = 8


def jacobian(n_boards: int, n_corners: int, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rows = 2 * n_boards * n_corners
    groups = np.repeat(np.arange(n_boards), 2 * n_corners)
    J = np.zeros((rows, N_INTRINSIC + 6 * n_boards))
    J[:, :N_INTRINSIC] = rng.normal(size=(rows, N_INTRINSIC))
    for g in range(n_boards):
        J[groups == g, N_INTRINSIC + 6 * g:N_INTRINSIC + 6 * g + 6] = rng.normal(size=(2 * n_corners, 6))
    return J, rng.normal(size=rows), groups, np.repeat(np.arange(n_boards), 6)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--boards", type=int, nargs="+", default=[12, 16, 20])
    ap.add_argument("--corners", type=int, default=20)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    rows = []
    for n in args.boards:
        J, r, groups, nuisance = jacobian(n, args.corners, rng)
        out = {}
        for name, call in (("board_clustered", lambda: intrinsic_covariance(J, r, N_INTRINSIC, groups)),
                           ("board_jackknife", lambda: jackknife_covariance(J, r, N_INTRINSIC, groups, nuisance))):
            times = []
            for _ in range(args.repeat):
                t0 = time.perf_counter()
                call()
                times.append(time.perf_counter() - t0)
            out[name] = statistics.median(times)
        print(f"{n} boards x {args.corners} corners: " + ", ".join(f"{k} {v * 1e3:.1f} ms" for k, v in out.items()))
        rows += [{"boards": n, "corners": args.corners, "covariance": k, "median_ms": round(v * 1e3, 1)}
                 for k, v in out.items()]
    from record import append_rows

    append_rows("bench_geometry_covariance", rows)


if __name__ == "__main__":
    main()
