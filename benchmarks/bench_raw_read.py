"""Raw read of one full-resolution frame: rawpy against the direct read of uncompressed DNG and the read floor.

    python benchmarks/bench_raw_read.py [--rounds 15] [--folder DIR]

Writes one frame of the simulator's full scale (both lenses stacked: 2 x 3456 rows by 3456 columns, 14-bit
values in 16-bit samples, one uncompressed strip, written by ``write_dng`` as the simulator writes every frame;
the values are random, which changes nothing for an uncompressed read) and times, in rounds that alternate the
methods so that a change of machine load falls on all of them alike, the CPU seconds (user + system of this
process) per frame of:

- ``floor``: ``np.fromfile`` of the whole file (the bytes from the page cache, nothing decoded);
- ``rawpy``, ``direct read`` and ``direct mapped``: ``read_raw`` without checksums, through rawpy, with the
  file read into memory, and with the file memory-mapped (apply's read);
- the same three followed by the band split (``split_bands`` of the whole mosaic: R, G, B float32 planes);
- ``rawpy + checksums`` and ``direct + checksums``: the stages' read (MD5 and SHA-256 of the bytes).

Prints the median CPU and wall seconds per frame and their ratio to the floor's, and appends one row per
method to ``benchmarks/results/bench_raw_read.csv``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from datetime import datetime
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--folder", default=None, help="where to write the frame (default: a temporary folder)")
    args = ap.parse_args()
    from pipeline.io.bands import split_bands
    from pipeline.io.rawio import read_raw, write_dng
    from pipeline.simulate.dataset import SCALES

    lens_px = SCALES["full"].lens_px
    with tempfile.TemporaryDirectory(dir=args.folder) as tmp:
        path = Path(tmp) / "full.dng"
        cfa = np.random.default_rng(0).integers(0, 16384, (2 * lens_px, lens_px), dtype=np.uint16)
        write_dng(path, cfa, exposure_s=0.01, iso=100, time=datetime(2021, 3, 18, 16, 0, 0), black_level=512,
                  white_level=16383)
        del cfa

        def split(frame):
            return split_bands(frame.cfa, frame.cfa_pattern)

        methods = {
            "floor": lambda: np.fromfile(path, np.uint8),
            "rawpy": lambda: read_raw(path, checksums=False, decoder="rawpy"),
            "direct read": lambda: read_raw(path, checksums=False, mapped=False),
            "direct mapped": lambda: read_raw(path, checksums=False, mapped=True),
            "rawpy + band split": lambda: split(read_raw(path, checksums=False, decoder="rawpy")),
            "direct read + band split": lambda: split(read_raw(path, checksums=False, mapped=False)),
            "direct mapped + band split": lambda: split(read_raw(path, checksums=False, mapped=True)),
            "rawpy + checksums": lambda: read_raw(path, decoder="rawpy"),
            "direct + checksums": lambda: read_raw(path),
        }
        assert read_raw(path, checksums=False).decoder == "direct"
        cpu = {name: [] for name in methods}
        wall = {name: [] for name in methods}
        for run in methods.values():     # warm the page cache and every code path once
            run()
        for _ in range(args.rounds):
            for name, run in methods.items():
                c0, w0 = time.process_time(), time.perf_counter()
                run()
                cpu[name].append(time.process_time() - c0)
                wall[name].append(time.perf_counter() - w0)
        size_mb = path.stat().st_size / 1e6

    floor_cpu, floor_wall = float(np.median(cpu["floor"])), float(np.median(wall["floor"]))
    records = []
    print(f"one {2 * lens_px} x {lens_px} frame, {size_mb:.1f} MB, median of {args.rounds} rounds")
    for name in methods:
        c, w = float(np.median(cpu[name])), float(np.median(wall[name]))
        print(f"{name:28s} cpu {c:7.4f} s ({c / floor_cpu:5.1f} x floor)   wall {w:7.4f} s ({w / floor_wall:5.1f} x)")
        records.append({"method": name, "frame": f"{2 * lens_px} x {lens_px} uint16", "file_mb": round(size_mb, 1),
                        "rounds": args.rounds, "cpu_s_per_frame": c, "wall_s_per_frame": w,
                        "cpu_x_floor": round(c / floor_cpu, 2), "wall_x_floor": round(w / floor_wall, 2)})
    from record import append_rows

    append_rows("bench_raw_read", records)


if __name__ == "__main__":
    main()
