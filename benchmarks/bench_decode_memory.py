"""Peak memory of the stages' decode loop against the number of frames read.

    python benchmarks/bench_decode_memory.py DATASET EXPERIMENT [--frames 64] [--ahead 1]

Reads the experiment's frames as a stage does (``frames.iter_frames``: bytes, MD5 and SHA-256,
LibRaw, every lens region split into bands and saturation maps, ``--ahead`` frames decoded in
the background thread), cycling through frames.csv until ``--frames`` frames are read, and adds
each frame's far-lens G band to float64 running sums, as a streaming reduction does. Prints the
process's peak resident memory (VmHWM) and current resident memory (VmRSS) after a quarter, a
half and all of the frames: a loop that keeps nothing between frames must stay flat.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pandas as pd


def memory_mib() -> dict[str, float]:
    """VmHWM (peak since exec) and VmRSS of this process, MiB (Linux)."""
    out = {}
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(("VmHWM:", "VmRSS:")):
                out[line.split(":")[0]] = int(line.split()[1]) / 1024
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset")
    ap.add_argument("experiment")
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--ahead", type=int, default=1, help="frames decoded ahead (performance.decode_ahead_frames)")
    args = ap.parse_args()
    from pipeline.io.dataset import open_dataset
    from pipeline.io.frames import iter_frames

    ds = open_dataset(args.dataset)
    table = ds.frames(args.experiment)
    rows = pd.concat([table] * -(-args.frames // len(table)), ignore_index=True).iloc[:args.frames]
    lens = next(iter(ds.lenses))
    s1 = s2 = None
    marks = {args.frames // 4, args.frames // 2, args.frames}
    records = []
    t0 = time.perf_counter()
    for i, dec in enumerate(iter_frames(ds, args.experiment, rows, decode_ahead_frames=args.ahead), start=1):
        g = dec.lenses[lens].bands["G"]
        if s1 is None:
            s1, s2 = np.zeros(g.shape), np.zeros(g.shape)
        s1 += g
        s2 += np.square(g, dtype=np.float64)
        if i in marks:
            m = memory_mib()
            print(f"{i:>5} frames  peak {m['VmHWM']:7.0f} MiB  now {m['VmRSS']:7.0f} MiB  "
                  f"{time.perf_counter() - t0:6.0f} s", flush=True)
            records.append({"experiment": args.experiment, "ahead": args.ahead, "frames": i,
                            "peak_mib": round(m["VmHWM"]), "now_mib": round(m["VmRSS"]),
                            "wall_s": round(time.perf_counter() - t0, 1)})
    from record import append_rows

    append_rows("bench_decode_memory", records)


if __name__ == "__main__":
    main()
