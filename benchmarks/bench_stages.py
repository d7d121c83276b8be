"""Time and peak memory of each stage on a simulated dataset.

    python benchmarks/bench_stages.py [--scale tiny|small|full] [--stages dark,linearity,...] [--repeat N]
                                      [--experiments geometry]

Simulates the dataset once (kept in benchmarks/out/), then runs every stage
in a fresh Python process, --repeat times, and prints the minimum, median and
maximum wall time and the peak resident memory of the stage's process.
Results go to benchmarks/out/<scale>.csv as well.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE / "out"
LENSES = ("far", "close")


def child(stage: str, dataset: str, results: str) -> None:
    """Run one stage in this process and print wall time and peak RSS as JSON."""
    from pipeline.config import load_config
    from pipeline import stage_io

    cfg = load_config(overrides={"dataset": dataset})
    res = Path(results)
    dark = {lens: res / f"dark/{lens}.nc" for lens in LENSES}

    def paths(stage_name):
        return {lens: res / f"{stage_name}/{lens}.nc" for lens in LENSES}
    t0 = time.perf_counter()
    if stage == "dark":
        stage_io.run_dark(dataset, cfg, dark)
    elif stage == "linearity":
        stage_io.run_linearity(dataset, cfg, dark, {lens: res / f"linearity/{lens}.nc" for lens in LENSES})
    elif stage == "diagnostics":
        arts = {s: [res / f"{s}/{lens}.nc" for lens in LENSES] for s in ("dark", "linearity")}
        d = res / "diagnostics"
        stage_io.run_diagnostics(arts, cfg, d / "m.csv", d / "u.csv", d / "e.csv", d / "h.csv")
    elif stage == "geometry":
        from pipeline.stages import geometry

        geometry.run(dataset, cfg, paths("geometry"))
    elif stage == "rolloff":
        from pipeline.stages import rolloff

        rolloff.run(dataset, cfg, None, paths("geometry"), paths("rolloff"))
    elif stage == "spectral":
        from pipeline.stages import spectral

        spectral.run(dataset, cfg, paths("geometry"), paths("spectral"))
    elif stage == "absolute":
        from pipeline.stages import absolute

        absolute.run(dataset, cfg, paths("spectral"), paths("geometry"), paths("absolute"))
    elif stage == "immersion":
        from pipeline.stages import immersion

        immersion.run(dataset, cfg, None, paths("geometry"), paths("immersion"),
                      spectral_path=paths("spectral")[LENSES[0]])
    else:
        sys.exit(f"unknown stage {stage}")
    wall = time.perf_counter() - t0
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"wall_s": wall, "peak_rss_mib": peak_mib}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scale", default="small", choices=["tiny", "small", "full"])
    ap.add_argument("--stages", default="dark,linearity,geometry,rolloff,spectral,absolute,immersion,diagnostics")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--experiments", default=None,
                    help="comma-separated experiments to simulate (default: the simulator's default set)")
    ap.add_argument("--child", nargs=3, metavar=("STAGE", "DATASET", "RESULTS"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(*args.child)
        return
    from pipeline.simulate import simulate_dataset

    experiments = tuple(args.experiments.split(",")) if args.experiments else None
    tag = args.scale + ("-" + "-".join(experiments) if experiments else "")
    dataset = OUT / f"dataset-{tag}"
    results = OUT / f"results-{tag}"
    if not dataset.exists():
        t0 = time.perf_counter()
        extra = {"experiments": experiments} if experiments else {}
        simulate_dataset(dataset, scale=args.scale, seed=args.seed,
                         effects=[("dark_current", {}), ("hot_pixels", {})], **extra)
        print(f"simulated {dataset} in {time.perf_counter() - t0:.1f} s")
    size_mb = sum(p.stat().st_size for p in dataset.rglob("*") if p.is_file()) / 1e6
    rows = []
    print(f"scale {args.scale}: {size_mb:.0f} MB of raw data; {args.repeat} runs per stage")
    print(f"{'stage':<12} {'min s':>8} {'median s':>9} {'max s':>8} {'peak MiB':>9}")
    for stage in args.stages.split(","):
        walls, peaks = [], []
        for _ in range(args.repeat):
            proc = subprocess.run([sys.executable, __file__, "--child", stage, str(dataset), str(results)],
                                  capture_output=True, text=True)
            if proc.returncode != 0:
                sys.exit(f"{stage} failed:\n{proc.stderr[-2000:]}")
            m = json.loads(proc.stdout.strip().splitlines()[-1])
            walls.append(m["wall_s"])
            peaks.append(m["peak_rss_mib"])
        row = {"scale": args.scale, "stage": stage, "min_s": min(walls), "median_s": statistics.median(walls),
               "max_s": max(walls), "peak_rss_mib": max(peaks)}
        rows.append(row)
        print(f"{stage:<12} {row['min_s']:8.2f} {row['median_s']:9.2f} {row['max_s']:8.2f} {row['peak_rss_mib']:9.0f}")
    import csv

    with open(OUT / f"{args.scale}.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


if __name__ == "__main__":
    main()
