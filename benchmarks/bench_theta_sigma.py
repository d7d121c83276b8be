"""Time the theta-uncertainty map of one band image at the real camera's resolution.

    python benchmarks/bench_theta_sigma.py [--band-px 1728] [--repeat 3]

What the geometry stage adds per lens, medium and band:
``pipeline.geometry.theta_uncertainty.theta_sigma_map`` (first-order
propagation of the fit's parameter covariance to every band pixel) on a
``--band-px`` square band image of the simulator's nominal far lens in air.
The covariance is diagonal with standard deviations of the size the medium
scale's fits give (0.05 px centre, 1e-4 stretch, 1e-4 relative
coefficients); its values do not change the cost. Prints the minimum and
median wall time of ``--repeat`` runs and the peak resident memory.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import time

import numpy as np

from pipeline.geometry.theta_uncertainty import parameter_names, theta_sigma_map
from pipeline.simulate.lens import default_model


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--band-px", type=int, default=1728)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    model = default_model("far", "air", (args.band_px, args.band_px))
    names = parameter_names("symmetric", len(model.poly) - 1)
    sd = [0.05, 0.05, 1e-4, 1e-4] + [1e-4 * abs(model.poly[k]) for k in (0, 2, 3, 4)]
    cov = np.diag(np.square(sd))
    times = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        theta_sigma_map(model, names, cov)
        times.append(time.perf_counter() - t0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"theta_sigma_map {args.band_px} x {args.band_px}: min {min(times):.2f} s, "
          f"median {statistics.median(times):.2f} s, peak {peak:.0f} MiB")
    from record import append_rows

    append_rows("bench_theta_sigma", [{"band_px": args.band_px, "repeat": args.repeat, "min_s": round(min(times), 2),
                                       "median_s": round(statistics.median(times), 2), "peak_mib": round(peak)}])


if __name__ == "__main__":
    main()
