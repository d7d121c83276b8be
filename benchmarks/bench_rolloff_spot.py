"""One roll-off setting's pixel search at the real camera's scale, on synthetic band images.

    python benchmarks/bench_rolloff_spot.py [--repeat 3] [--band-px 1728] [--spot-px 17]

Times ``stages.rolloff._setting_masks`` (the port spot's peak, pixels and centroid in each band, the
averaging circle, the halo annulus and weights) on three 1728 x 1728 band images with a uniform disc
of 2000 DN and 3 DN of noise, their dark maps and a lit circle, with the stage's default config.
Prints the minimum CPU time of ``--repeat`` runs beside the load average.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from pipeline.io.bands import BANDS
from pipeline.config import load_config
from pipeline.stages.rolloff import _setting_masks


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--band-px", type=int, default=1728)
    ap.add_argument("--spot-px", type=float, default=17.0)
    args = ap.parse_args()
    cfg = load_config()["rolloff"]
    n = args.band_px
    rng = np.random.default_rng(0)
    yy, xx = np.indices((n, n))
    lit = np.hypot(yy - n / 2, xx - n / 2) < 0.49 * n
    disc = np.hypot(yy - 0.52 * n, xx - 0.23 * n) <= args.spot_px
    bands = {b: (rng.normal(0, 3, (n, n)) + 2000 * disc).astype(np.float32) for b in BANDS}
    darks = {b: rng.normal(0, 1, (n, n)) for b in BANDS}
    cpu = []
    for _ in range(args.repeat):
        t0 = time.process_time()
        # noise of a 3 x 3 mean: the frame's sigma 3 DN and the dark's 1 DN, over 3
        _setting_masks(bands, darks, lit, 8.0, 0.05 * n, cfg, np.hypot(3.0, 1.0) / 3.0)
        cpu.append(time.process_time() - t0)
    load = "/".join(f"{v:.1f}" for v in os.getloadavg())
    print(f"one setting's pixel search, {n} x {n} band images: {min(cpu) * 1e3:.0f} ms CPU "
          f"(min of {args.repeat}), load {load}")
    from record import append_rows

    append_rows("bench_rolloff_spot", [{"band_px": n, "spot_px": args.spot_px, "repeat": args.repeat,
                                        "min_cpu_ms": round(min(cpu) * 1e3), "load": load}])


if __name__ == "__main__":
    main()
