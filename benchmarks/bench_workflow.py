"""The whole workflow in one run at the real camera's scale, against the decode floor of its frames.

    python benchmarks/bench_workflow.py [--work DIR] [--scale full] [--rolloff-stride K] [--seed 1]

1. Simulates every experiment (``dark`` to ``field``) of the ``full`` scale (6912 x 3456 frames, the
   paper's frame counts), each in its own process, two at a time, into ``--work``/parts/EXPERIMENT, and
   prints each one's time; the parts are then joined, hard-linked, into one dataset, ``--work``/dataset,
   with its MD5SUMS. A part already there is reused.
2. Runs the workflow on it, ``snakemake --cores 2`` in ``--work``/run (results and Snakemake's
   per-job ``benchmark:`` files there), and prints its wall time.
3. Decodes the frames of each stage's jobs once, the decode floor (``bench_full.py --floor``: each
   frame the job reads, read as the stages read it, bytes, MD5 and SHA-256, LibRaw, and that lens's
   region split into R, G, B), the two lenses' floors side by side as the workflow runs the two jobs.
4. Prints per stage and lens: frames, MB decoded, wall and CPU seconds and peak memory of the job
   (from its ``results/benchmarks/STAGE/LENS.tsv``: ``s``, ``cpu_time``, ``max_rss``), the floor's
   wall and CPU seconds and the ratio of the job's wall time to the floor's; the bundle, field,
   diagnostics and report rules' own lines; and the run's total. Also written to ``--work``/bench_workflow.csv.

The whole ``full`` dataset is 1,738 frames, about 83 GB of DNG: more than this machine's free disk
(about 73 GB). ``--rolloff-stride 2`` simulates every second rotation angle of the roll-off
experiment (its 80 dark frames all: 456 of 912 frames), 1,282 frames and about 61 GB; every other
experiment has its paper's frame count. ``--scale tiny`` tries the script in a minute.
"""

from __future__ import annotations

import argparse
import csv
import os
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))   # bench_full's children and helpers
EXPERIMENTS = ("rolloff", "dark", "geometry", "spectral", "immersion", "linearity", "absolute", "field")
LENSES = ("far", "close")


def simulate_parts(work: Path, scale: str, seed: int) -> None:
    """Each experiment into its own dataset folder (``bench_full.simulate``), two processes at a time, the
    longest first."""
    from bench_full import simulate

    parts = work / "parts"
    parts.mkdir(parents=True, exist_ok=True)

    def one(experiment: str) -> str:
        took = simulate(parts / experiment, experiment, scale, seed)
        return f"{experiment}: reused" if took is None else f"{experiment}: simulated in {took:.0f} s"

    with ThreadPoolExecutor(max_workers=2) as pool:
        for line in pool.map(one, EXPERIMENTS):
            print(line, flush=True)


def join_parts(work: Path) -> Path:
    """The parts' experiments hard-linked into one dataset with one dataset.yaml and a new MD5SUMS."""
    from pipeline.io.dataset import write_md5sums

    dataset = work / "dataset"
    if dataset.exists():
        shutil.rmtree(dataset)
    dataset.mkdir()
    for experiment in EXPERIMENTS:
        part = work / "parts" / experiment
        if not (dataset / "dataset.yaml").exists():
            shutil.copy(part / "dataset.yaml", dataset / "dataset.yaml")
        for path in (part / experiment).rglob("*"):
            target = dataset / path.relative_to(part)
            if path.is_dir():
                target.mkdir(parents=True, exist_ok=True)
            else:
                target.parent.mkdir(parents=True, exist_ok=True)
                os.link(path, target)
    t0 = time.perf_counter()
    write_md5sums(dataset)
    print(f"dataset joined, MD5SUMS in {time.perf_counter() - t0:.0f} s", flush=True)
    return dataset


def run_workflow(work: Path, dataset: Path) -> float:
    run = work / "run"
    shutil.rmtree(run / "results", ignore_errors=True)
    run.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    proc = subprocess.run([str(Path(sys.executable).parent / "snakemake"), "-s", str(REPO / "Snakefile"), "-d", str(run),
                           "--cores", "2", "--config", f"dataset={dataset}"],
                          capture_output=True, text=True)
    wall = time.perf_counter() - t0
    (work / "snakemake.log").write_text(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        sys.exit(f"the workflow failed after {wall:.0f} s (log: {work / 'snakemake.log'}):\n{proc.stderr[-3000:]}")
    print(f"workflow: {wall:.0f} s wall ({wall / 60:.1f} min)", flush=True)
    return wall


def job_benchmarks(run: Path) -> dict[tuple[str, str], dict]:
    """Snakemake's ``benchmark:`` record of every job: {(rule, lens or ''): {s, cpu_time, max_rss}}."""
    out = {}
    for tsv in sorted((run / "results" / "benchmarks").rglob("*.tsv")):
        rel = tsv.relative_to(run / "results" / "benchmarks").with_suffix("")
        key = (rel.parts[0], rel.parts[1]) if len(rel.parts) > 1 else (rel.parts[0], "")
        with tsv.open() as fh:
            row = next(csv.DictReader(fh, delimiter="\t"))
        out[key] = {k: float(row[k]) if row.get(k) not in (None, "", "NA", "-") else float("nan")
                    for k in ("s", "cpu_time", "max_rss")}
    return out


def floors(dataset: Path, stages) -> dict[tuple[str, str], dict]:
    """The decode floor of each (experiment, lens) job (``bench_full.decode_floor``), the two lenses side by side."""
    from bench_full import _result, decode_floor

    out = {}
    for experiment, lenses in stages:
        procs = {lens: decode_floor(dataset, experiment, lens) for lens in lenses}
        for lens, proc in procs.items():
            out[(experiment, lens)] = _result(proc)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default=str(HERE / "out" / "workflow"), help="datasets, the run and the CSV go here")
    ap.add_argument("--scale", default="full")
    ap.add_argument("--rolloff-stride", type=int, default=None, metavar="K",
                    help="every K-th rotation angle of the roll-off experiment (its dark frames all)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    from bench_full import frames_and_mb, scale_spec, stage_lenses

    work = Path(args.work)
    simulate_parts(work, scale_spec(args.scale, None, args.rolloff_stride), args.seed)
    dataset = join_parts(work)
    total = run_workflow(work, dataset)
    jobs = job_benchmarks(work / "run")
    stages = [(e, stage_lenses(dataset, e)) for e in EXPERIMENTS]
    floor = floors(dataset, stages)
    rows = []
    for experiment, lenses in stages:
        for lens in lenses:
            job = jobs.get((experiment, lens))
            if job is None:
                continue
            n, mb = frames_and_mb(dataset, experiment, lens)
            f = floor[(experiment, lens)]
            rows.append({"stage": experiment, "lens": lens, "frames": n, "mb": round(mb),
                         "wall_s": round(job["s"], 1), "cpu_s": round(job["cpu_time"], 1),
                         "peak_mib": round(job["max_rss"]), "floor_wall_s": round(f["wall_s"], 1),
                         "floor_cpu_s": round(f["cpu_s"], 1), "wall_over_floor": round(job["s"] / f["wall_s"], 2)})
    for (rule, lens), job in sorted(jobs.items()):
        if rule not in EXPERIMENTS:
            rows.append({"stage": rule, "lens": lens, "frames": "", "mb": "", "wall_s": round(job["s"], 1),
                         "cpu_s": round(job["cpu_time"], 1), "peak_mib": round(job["max_rss"]), "floor_wall_s": "",
                         "floor_cpu_s": "", "wall_over_floor": ""})
    header = list(rows[0])
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for r in rows:
        print("| " + " | ".join(str(r[k]) for k in header) + " |")
    print(f"whole workflow: {total:.0f} s wall; peak of any job {max(j['max_rss'] for j in jobs.values()):.0f} MiB")
    with (work / "bench_workflow.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=header)
        writer.writeheader()
        writer.writerows(rows)
    from record import append_rows

    append_rows("bench_workflow", rows + [{"stage": "workflow (total)", "wall_s": round(total, 1),
                                           "peak_mib": round(max(j["max_rss"] for j in jobs.values()))}])


if __name__ == "__main__":
    main()
