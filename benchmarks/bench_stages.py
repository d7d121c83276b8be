"""Time and peak memory of each stage on a simulated dataset.

    python benchmarks/bench_stages.py [--scale tiny|small|medium|full] [--stages dark,linearity,...] [--repeat N]
                                      [--experiments geometry]

Simulates the dataset once (kept in benchmarks/out/), then runs every stage,
one lens at a time (one workflow job), in a fresh Python process, --repeat times, and prints the minimum, median and
maximum wall time, the median CPU time and the peak resident memory of the stage's process. Each
job gets one BLAS/OpenMP thread, as Snakemake gives a rule of ``threads: 1``.
Results go to benchmarks/out/<scale>.csv as well, and are appended to benchmarks/results/bench_stages.csv
(benchmarks/record.py: date, commit, machine, command).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE / "out"
LENSES = ("far", "close")


def child(stage: str, dataset: str, results: str, lens: str) -> None:
    """Run one stage for one lens (one workflow job) in this process; print wall time and peak RSS as JSON."""
    from pipeline.config import load_config
    from pipeline.runner.workflow import STAGES, run_stage

    cfg = load_config(overrides={"dataset": dataset})
    res = Path(results)
    t0, c0 = time.perf_counter(), time.process_time()
    if stage == "diagnostics":
        from pipeline.diagnostics.missing_effects import diagnose_artefacts

        arts = {s: [res / f"{s}/{ln}.nc" for ln in LENSES] for s in STAGES if (res / s).is_dir()}
        d = res / "diagnostics"
        diagnose_artefacts(arts, cfg, d / "m.csv", d / "u.csv", d / "e.csv", d / "ledger", d / "h.csv")
    elif stage in STAGES:
        spec = STAGES[stage]
        upstream = {name: {lens: res / f"{name}/{lens}.nc"} for name in spec.upstream + spec.optional_upstream
                    if (res / f"{name}/{lens}.nc").exists()}
        # as a workflow job runs it: the start-up check (timed by bench_workflow) validated the folder before
        run_stage(stage, dataset, cfg, {lens: res / f"{stage}/{lens}.nc"}, upstream, checked=True)
    else:
        sys.exit(f"unknown stage {stage}")
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"wall_s": wall, "cpu_s": cpu, "peak_rss_mib": peak_mib}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scale", default="small", choices=["tiny", "small", "medium", "full"])
    ap.add_argument("--stages", default="dark,linearity,geometry,rolloff,spectral,absolute,immersion,diagnostics")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--experiments", default=None,
                    help="comma-separated experiments to simulate (default: the simulator's default set)")
    ap.add_argument("--child", nargs=4, metavar=("STAGE", "DATASET", "RESULTS", "LENS"), help=argparse.SUPPRESS)
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
    print("one job per stage and lens, as the workflow runs them (the two lenses run side by side on 2 cores)")
    print(f"{'stage':<12} {'lens':<6} {'min s':>8} {'median s':>9} {'max s':>8} {'CPU s':>8} {'peak MiB':>9}")
    # a workflow job of one thread: Snakemake sets these to the rule's threads
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    for stage in args.stages.split(","):
        for lens in (LENSES if stage != "diagnostics" else ("all",)):
            walls, cpus, peaks = [], [], []
            for _ in range(args.repeat):
                proc = subprocess.run([sys.executable, __file__, "--child", stage, str(dataset), str(results), lens],
                                      capture_output=True, text=True, env=env)
                if proc.returncode != 0:
                    sys.exit(f"{stage} {lens} failed:\n{proc.stderr[-2000:]}")
                m = json.loads(proc.stdout.strip().splitlines()[-1])
                walls.append(m["wall_s"])
                cpus.append(m["cpu_s"])
                peaks.append(m["peak_rss_mib"])
            row = {"scale": args.scale, "stage": stage, "lens": lens, "min_s": min(walls),
                   "median_s": statistics.median(walls), "max_s": max(walls), "median_cpu_s": statistics.median(cpus),
                   "peak_rss_mib": max(peaks)}
            rows.append(row)
            print(f"{stage:<12} {lens:<6} {row['min_s']:8.2f} {row['median_s']:9.2f} {row['max_s']:8.2f} "
                  f"{row['median_cpu_s']:8.2f} {row['peak_rss_mib']:9.0f}")
    import csv

    with open(OUT / f"{args.scale}.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    from record import append_rows

    append_rows("bench_stages", rows)


if __name__ == "__main__":
    main()
