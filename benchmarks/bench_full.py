"""The workflow's stages at the real camera's scale, one experiment at a time, against the decode floor.

    python benchmarks/bench_full.py [--experiments dark,linearity,...] [--work DIR] [--keep]
    python benchmarks/bench_full.py --scaling dark [--factors 1,2,4] [--base-frames 3] [--lens far]
    [--frames-per-setting K]: simulate K frames per dark and linearity setting (full scale: 15 and 4)
    [--rolloff-stride K]: simulate every K-th rotation angle of the roll-off experiment (all its darks)
    [--true-geometry]: the simulator's true geometry artefacts where --work/results has none
    python benchmarks/bench_full.py --experiments field --bundle BUNDLE [--work DIR]

Default mode: for each experiment in turn, simulates it at the ``full`` scale (6912 x 3456
frames, the paper's frame counts; the simulator's time printed) into ``--work``, runs the
stage that reads it for each lens (one workflow job each, in a fresh process with one
BLAS/OpenMP thread, as Snakemake runs a ``threads: 1`` rule, the two lens jobs side by side as
the workflow runs them; artefacts kept in ``--work``/results for the stages downstream), and
beside them each job's decode floor (a fresh process per lens that reads every frame the job
reads, those of its lens or of both, once as the stages do: bytes, MD5 and SHA-256, rawpy, and
that lens's region split into R, G, B), so that the floors run under the same load as the jobs
(two jobs and two floors on the 2 cores); then it deletes the
experiment's raw frames before the next one (``--keep`` keeps them), so the disk never holds the
whole dataset. Prints per stage and lens: frames, MB decoded, wall and CPU seconds, peak resident
memory (the child's own, VmHWM: see :func:`peak_mib`), and the ratio of wall time to the floor's
wall time.

``--scaling EXPERIMENT``: the experiment's full-scale frames (simulated as above, or the ones kept
with ``--keep``) cut to the first ``--base-frames`` times each factor frames of each setting
(hard links, no new simulation), its stage run for one lens at each size: wall time should grow
linearly with the frames and peak memory stay flat. For ``rolloff`` (two frames per setting) the cut is
of the rotation angles instead: every dark frame and one angle in ``max(factors) / factor`` of each
medium, so that the signal frames grow with the factor and the dark frames (80) stay.

The stages downstream of geometry (roll-off, spectral, absolute, immersion) read the geometry artefacts
in ``--work``/results: a geometry run's (``--experiments geometry`` first; simulating it takes about
15 minutes) or, with ``--true-geometry``, maps of the simulator's true optics of the same size written
there (no ``theta_deg_sigma``: the roll-off closure then uses ``rolloff.field_angle_sigma_px``).

Each figure is printed beside the machine's load average (``os.getloadavg``): on a shared
machine absolute times move with the load, the ratio to the floor measured in the same run
less, and the ratio of CPU times (stage CPU / floor CPU, the decode thread's included) least.
Results go to ``--work``/bench_full-EXPERIMENTS.csv (or bench_scaling-EXPERIMENT.csv) as well.

``--experiments field --bundle BUNDLE``: the field hour (31 frames of the zenith lens at the full scale)
against a full-resolution calibration bundle, one job (the lens at the zenith) and its floor. The bundle
must be of the simulated camera (``bench_apply.py`` makes one: dark, linearity and absolute fitted at
the full resolution, the true geometry, roll-off and spectral from the small scale); the match-up's
numbers are then not a calibration's, its cost is.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
LENSES = ("far", "close")
#: the stage that reads each experiment's frames (the field stage only with --bundle)
STAGE_OF = {"dark": "dark", "linearity": "linearity", "geometry": "geometry", "rolloff": "rolloff",
            "spectral": "spectral", "absolute": "absolute", "immersion": "immersion", "field": "field"}
EFFECTS = [("dark_current", {}), ("hot_pixels", {})]


def peak_mib() -> float:
    """This process's peak resident memory since its exec, MiB (Linux: VmHWM of /proc/self/status).

    Not ``getrusage``'s ``ru_maxrss``: Linux carries that across exec from the parent that started
    the child, so a child of a large parent reports the parent's peak as its own (a child of a
    600 MiB parent that allocates nothing reports 625 MiB).
    """
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def job_child(stage: str, dataset: str, results: str, lens: str, bundle: str = "") -> None:
    """Run one stage for one lens (one workflow job) in this process; print wall, CPU and peak as JSON.
    ``bundle``: the calibration bundle of a stage that applies it (the field), "" for none."""
    from pipeline.config import load_config
    from pipeline.runner.workflow import STAGES, run_stage

    cfg = load_config(overrides={"dataset": dataset})
    res = Path(results)
    spec = STAGES[stage]
    upstream = {name: {lens: res / f"{name}/{lens}.nc"} for name in spec.upstream + spec.optional_upstream
                if (res / f"{name}/{lens}.nc").exists()}
    t0, c0 = time.perf_counter(), time.process_time()
    # as a workflow job runs it: the workflow's start-up check validated the folder before any job
    run_stage(stage, dataset, cfg, {lens: res / f"{stage}/{lens}.nc"}, upstream, bundle=bundle or None, checked=True)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(json.dumps({"wall_s": wall, "cpu_s": cpu, "peak_rss_mib": peak_mib()}))


def floor_child(dataset: str, experiment: str, lens: str) -> None:
    """Decode every frame the lens's job reads once and split its lens region into bands; print JSON.

    The frames of the lens or of both lenses (the job's view, ``workflow.lens_view``), read as the
    stages read them (bytes, MD5 and SHA-256, LibRaw) and that lens's region split into R, G, B.
    """
    from pipeline.io.bands import cut_region, split_bands
    from pipeline.io.dataset import open_dataset
    from pipeline.io.rawio import read_raw
    from pipeline.runner.workflow import lens_view

    ds = lens_view(open_dataset(dataset), lens)
    frames = ds.frames(experiment)
    rows, cols = ds.lenses[lens]
    t0, c0 = time.perf_counter(), time.process_time()
    for path in frames["path"]:
        raw = read_raw(path)
        split_bands(cut_region(raw.cfa, rows, cols), raw.cfa_pattern)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(json.dumps({"wall_s": wall, "cpu_s": cpu, "peak_rss_mib": peak_mib()}))


def _start(args: list[str]) -> subprocess.Popen:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    return subprocess.Popen([sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)


def _result(proc: subprocess.Popen) -> dict:
    out, err = proc.communicate()
    if proc.returncode != 0:
        sys.exit(f"{' '.join(proc.args[1:4])} failed:\n{err[-3000:]}")
    return json.loads(out.strip().splitlines()[-1])


def stage_job(stage: str, dataset: Path, results: Path, lens: str, bundle: Path | None = None) -> subprocess.Popen:
    """Start one workflow job (stage, lens) in a fresh process (:func:`job_child`: wall, CPU, peak RSS)."""
    return _start([__file__, "--job", stage, str(dataset), str(results), lens, str(bundle or "")])


def decode_floor(dataset: Path, experiment: str, lens: str) -> subprocess.Popen:
    return _start([__file__, "--floor", str(dataset), experiment, lens])


def simulate(out: Path, experiment: str, scale: str, seed: int) -> float | None:
    """Simulate one experiment into ``out`` unless it is there already; the simulator's wall time (None: reused).

    The simulator runs in its own process: a child forked from a parent that had grown to the
    simulator's size would report that size as its own peak (Linux keeps ru_maxrss across exec).
    """
    if out.exists():
        return None
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, __file__, "--simulate", str(out), experiment, scale, str(seed)])
    if proc.returncode != 0:
        sys.exit(f"simulating {experiment} into {out} failed")
    return time.perf_counter() - t0


def scale_spec(name: str, frames_per_setting: int | None = None, rolloff_stride: int | None = None) -> str:
    """The ``--simulate`` child's scale argument: ``name``, or ``name:JSON`` with the scale's fields replaced."""
    overrides = {}
    if frames_per_setting:
        overrides.update(dark_frames=frames_per_setting, linearity_frames=frames_per_setting)
    if rolloff_stride:
        overrides["rolloff_angle_stride"] = rolloff_stride
    return f"{name}:{json.dumps(overrides)}" if overrides else name


def simulate_child(out: str, experiment: str, scale: str, seed: str) -> None:
    """``scale`` is a scale's name, or ``NAME:JSON`` for that scale with the fields of the JSON object
    replaced (e.g. ``full:{"dark_frames": 4, "linearity_frames": 4}``, see :func:`scale_spec`)."""
    from dataclasses import replace

    from pipeline.simulate import simulate_dataset
    from pipeline.simulate.dataset import SCALES

    name, _, overrides = scale.partition(":")
    sc = replace(SCALES[name], **json.loads(overrides)) if overrides else name
    simulate_dataset(Path(out), scale=sc, seed=int(seed), effects=EFFECTS, experiments=(experiment,),
                     progress=False)


def frame_subset(source: Path, out: Path, experiment: str, per_setting: int) -> int:
    """A copy of ``source`` whose ``experiment`` lists the first ``per_setting`` frames of each setting
    (lens, sweep, ISO, exposure from the tags), the raw files hard-linked; returns its frame count."""
    import pandas as pd

    from pipeline.io.rawio import read_tags

    table = pd.read_csv(source / experiment / "frames.csv")
    tags = [read_tags(source / experiment / f) for f in table["file"]]
    table["_key"] = [(r.lens, getattr(r, "sweep", ""), t["iso"], t["exposure_s"]) for r, t in zip(table.itertuples(), tags)]
    return linked_copy(source, out, experiment, table[table.groupby("_key").cumcount() < per_setting].drop(columns="_key"))


def position_subset(source: Path, out: Path, stride: int) -> int:
    """A copy of the roll-off dataset ``source`` with every dark frame and the signal frames of every
    ``stride``-th rotation angle of each lens, medium and azimuth plane (hard links); its frame count."""
    import pandas as pd

    table = pd.read_csv(source / "rolloff" / "frames.csv")
    signal = table["kind"] == "signal"
    angles = {m: sorted(table.loc[signal & (table["medium"] == m), "angle_deg"].unique()) for m in table["medium"].unique()}
    pos = [angles[m].index(a) if k == "signal" else 0 for m, a, k in zip(table["medium"], table["angle_deg"], table["kind"])]
    return linked_copy(source, out, "rolloff", table[~signal | (pd.Series(pos, index=table.index) % stride == 0)])


def linked_copy(source: Path, out: Path, experiment: str, keep) -> int:
    """``source`` copied to ``out`` with ``experiment`` listing only the rows of ``keep`` (its raw files
    hard-linked, the other experiments' files and every sidecar copied, MD5SUMS written anew)."""
    from pipeline.io.dataset import write_md5sums

    if out.exists():
        shutil.rmtree(out)
    for path in source.rglob("*"):
        rel = path.relative_to(source)
        if path.is_file() and rel.parts[0] != experiment and rel.name != "MD5SUMS":
            (out / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(path, out / rel)
    for sidecar in (source / experiment).iterdir():
        if sidecar.is_file() and sidecar.name != "frames.csv":
            (out / experiment).mkdir(parents=True, exist_ok=True)
            shutil.copy(sidecar, out / experiment / sidecar.name)
    (out / experiment / "raw").mkdir(parents=True, exist_ok=True)
    for f in keep["file"]:
        os.link(source / experiment / f, out / experiment / f)
    keep.to_csv(out / experiment / "frames.csv", index=False)
    write_md5sums(out)
    return len(keep)


#: the artefacts a stage needs from the default mode's results (the scaling mode copies them)
STAGE_UPSTREAM = {"linearity": ("dark",), "rolloff": ("geometry",), "spectral": ("geometry",),
                  "absolute": ("spectral", "geometry"), "immersion": ("geometry",)}


def write_true_geometry(results: Path, band_px: int) -> None:
    """Geometry artefacts of the simulator's true optics (as the roll-off tests and ``bench_apply`` make
    them: :func:`pipeline.simulate.rolloff.true_band_models` laid out by ``geometry_maps.maps_dataset``)
    in ``results``/geometry, for the lenses that have none: the maps a geometry run would give, without
    simulating and fitting the geometry experiment (no ``theta_deg_sigma``: the stages then use
    their configured field-angle uncertainty)."""
    from pipeline.io.artefact import write_artefact
    from pipeline.simulate.rolloff import true_band_models
    from pipeline.stages.geometry_maps import maps_dataset

    for lens in LENSES:
        path = results / "geometry" / f"{lens}.nc"
        if not path.exists():
            write_artefact(maps_dataset(true_band_models(lens, band_px), (band_px, band_px)), path, stage="geometry",
                           inputs={}, config_subset={}, effects=[])
            print(f"{path}: the simulator's true geometry ({band_px} x {band_px} band pixels)", flush=True)


def remove_dataset(out: Path) -> None:
    from pipeline.simulate.dataset import truth_dir_for

    shutil.rmtree(out, ignore_errors=True)
    shutil.rmtree(truth_dir_for(out), ignore_errors=True)


def frames_and_mb(dataset: Path, experiment: str, lens: str) -> tuple[int, float]:
    """Frames the lens's job reads (of the lens or of both) and their size."""
    from pipeline.io.dataset import open_dataset
    from pipeline.runner.workflow import lens_view

    frames = lens_view(open_dataset(dataset), lens).frames(experiment)
    return len(frames), sum(Path(p).stat().st_size for p in frames["path"]) / 1e6


def load() -> str:
    return "/".join(f"{v:.1f}" for v in os.getloadavg())


HEADER = (f"{'stage':<10} {'lens':<6} {'frames':>6} {'MB':>7} {'wall s':>8} {'CPU s':>8} {'peak MiB':>9} "
          f"{'floor s':>8} {'ratio':>6} {'floor CPU':>9} {'CPU ratio':>9}  load 1/5/15 min")


def row_line(r: dict) -> str:
    return (f"{r['stage']:<10} {r['lens']:<6} {r['frames']:>6} {r['mb_decoded']:>7.0f} {r['wall_s']:>8.1f} "
            f"{r['cpu_s']:>8.1f} {r['peak_rss_mib']:>9.0f} {r['floor_wall_s']:>8.1f} {r['ratio_to_floor']:>6.2f} "
            f"{r['floor_cpu_s']:>9.1f} {r['cpu_ratio_to_floor']:>9.2f}  {r['load']}")


def stage_lenses(dataset: Path, experiment: str) -> tuple[str, ...]:
    """The lenses whose jobs the workflow runs for ``experiment``: both, or those its frames.csv names (the
    field: the lens at the zenith)."""
    import pandas as pd

    from pipeline.runner.workflow import STAGES

    if not STAGES[STAGE_OF[experiment]].lenses_from_frames:
        return LENSES
    named = set(pd.read_csv(dataset / experiment / "frames.csv")["lens"])
    return tuple(lens for lens in LENSES if lens in named)


def measure(stage: str, experiment: str, dataset: Path, results: Path, lenses, extra: dict,
            bundle: Path | None = None) -> list[dict]:
    """The stage's job of each lens and each job's decode floor, all side by side (the workflow runs the
    two lens jobs of a stage at once on 2 cores): the floors then decode under the same load as the jobs."""
    sizes = {lens: frames_and_mb(dataset, experiment, lens) for lens in lenses}
    load_start = load()
    procs = {lens: stage_job(stage, dataset, results, lens, bundle) for lens in lenses}
    floor_procs = {lens: decode_floor(dataset, experiment, lens) for lens in lenses}
    jobs = {lens: _result(p) for lens, p in procs.items()}
    floors = {lens: _result(p) for lens, p in floor_procs.items()}
    for lens, floor in floors.items():
        n, mb = sizes[lens]
        print(f"decode floor of {experiment}, {lens} lens: {n} frames, {mb:.0f} MB, {floor['wall_s']:.1f} s wall, "
              f"{floor['cpu_s']:.1f} s CPU, peak {floor['peak_rss_mib']:.0f} MiB (load at start {load_start})",
              flush=True)
    print(HEADER)
    rows = []
    for lens, m in jobs.items():
        n, mb = sizes[lens]
        floor = floors[lens]
        r = {**extra, "stage": stage, "lens": lens, "frames": n, "mb_decoded": mb, **m,
             "floor_wall_s": floor["wall_s"], "floor_cpu_s": floor["cpu_s"], "floor_peak_rss_mib": floor["peak_rss_mib"],
             "ratio_to_floor": m["wall_s"] / floor["wall_s"], "cpu_ratio_to_floor": m["cpu_s"] / floor["cpu_s"],
             "load": load()}
        print(row_line(r), flush=True)
        rows.append(r)
    return rows


def write_csv(path: Path, rows: list[dict]) -> None:
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {path}")


def main() -> None:
    from record import append_rows

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--experiments", default="dark,linearity,geometry,rolloff,spectral,absolute,immersion")
    ap.add_argument("--work", default=str(HERE / "out" / "full"), help="datasets, artefacts and the CSV go here")
    ap.add_argument("--keep", action="store_true", help="keep each experiment's raw frames")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--scale", default="full", help="a scale of the simulator (default full; tiny to try the script)")
    ap.add_argument("--frames-per-setting", type=int, metavar="K",
                    help="simulate K frames per dark and linearity setting instead of the scale's (15 and 4 at full)")
    ap.add_argument("--rolloff-stride", type=int, metavar="K",
                    help="simulate every K-th rotation angle of the roll-off experiment in each medium (its 80 "
                         "dark frames all); with --scaling rolloff the factors cut these positions further")
    ap.add_argument("--true-geometry", action="store_true",
                    help="where --work/results has no geometry artefacts, write those of the simulator's true "
                         "optics instead of running the geometry experiment (for the stages that read them)")
    ap.add_argument("--bundle", metavar="BUNDLE",
                    help="the calibration bundle the field stage applies (a full-resolution one: "
                         "benchmarks/bench_apply.py makes it in its --work, results/calibration/bundle.nc); "
                         "--experiments field needs it")
    ap.add_argument("--scaling", metavar="EXPERIMENT", help="scaling mode: this experiment at 1x, 2x, 4x its frames")
    ap.add_argument("--factors", default="1,2,4")
    ap.add_argument("--base-frames", type=int, default=3, help="frames per setting at factor 1 (scaling mode)")
    ap.add_argument("--lens", default="far", help="the lens of the scaling mode's job")
    ap.add_argument("--floor", nargs=3, metavar=("DATASET", "EXPERIMENT", "LENS"), help=argparse.SUPPRESS)
    ap.add_argument("--job", nargs=5, metavar=("STAGE", "DATASET", "RESULTS", "LENS", "BUNDLE"), help=argparse.SUPPRESS)
    ap.add_argument("--simulate", nargs=4, metavar=("OUT", "EXPERIMENT", "SCALE", "SEED"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.floor:
        floor_child(*args.floor)
        return
    if args.job:
        job_child(*args.job)
        return
    if args.simulate:
        simulate_child(*args.simulate)
        return
    from pipeline.simulate.dataset import SCALES

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    if args.scale not in SCALES:
        sys.exit(f"unknown scale {args.scale}; choose one of {', '.join(SCALES)}")
    scale = scale_spec(args.scale, args.frames_per_setting, args.rolloff_stride)
    rows = []
    if args.true_geometry:
        write_true_geometry(work / "results", SCALES[args.scale].lens_px // 2)
    if args.scaling:
        exp = args.scaling
        if exp not in STAGE_OF:
            sys.exit(f"unknown experiment {exp}; choose among {', '.join(STAGE_OF)}")
        source = work / f"dataset-{exp}"
        sim = simulate(source, exp, scale, args.seed)
        print(f"{exp}: " + (f"simulated in {sim:.0f} s" if sim is not None else "reused") + f" (load {load()})",
              flush=True)
        factors = [int(f) for f in args.factors.split(",")]
        for factor in factors:
            dataset = work / f"scaling-{exp}-x{factor}"
            if exp == "rolloff":     # one frame count per setting: cut the rotation angles instead
                k = max(factors) // factor
                n = position_subset(source, dataset, k)
                print(f"{exp} x{factor}: every dark frame and one rotation angle in {k} ({n} frames, hard links)",
                      flush=True)
            else:
                k = args.base_frames * factor
                n = frame_subset(source, dataset, exp, k)
                print(f"{exp} x{factor}: the first {k} frames of each setting ({n} frames, hard links)", flush=True)
            results = work / f"results-scaling-{exp}-x{factor}"
            for upstream in STAGE_UPSTREAM.get(exp, ()):     # e.g. linearity needs the dark artefact
                art = work / "results" / upstream / f"{args.lens}.nc"
                if not art.exists():
                    sys.exit(f"{art}: run the default mode for {upstream} first ({exp} needs its artefact)")
                (results / upstream).mkdir(parents=True, exist_ok=True)
                shutil.copy(art, results / upstream / art.name)
            rows += measure(STAGE_OF[exp], exp, dataset, results, [args.lens],
                            {"factor": factor, ("angle_stride" if exp == "rolloff" else "frames_per_setting"): k})
            shutil.rmtree(dataset)
        if not args.keep:
            remove_dataset(source)
        write_csv(work / f"bench_scaling-{exp}.csv", rows)
        append_rows("bench_scaling", rows)
        return
    results = work / "results"
    for exp in args.experiments.split(","):
        if exp not in STAGE_OF:
            sys.exit(f"unknown experiment {exp}; choose among {', '.join(STAGE_OF)}")
        if exp == "field" and not args.bundle:
            sys.exit("--experiments field: the field stage applies a calibration bundle; give --bundle")
        dataset = work / f"dataset-{exp}"
        sim = simulate(dataset, exp, scale, args.seed)
        print(f"{exp}: " + (f"simulated in {sim:.0f} s" if sim is not None else "reused") + f" (load {load()})",
              flush=True)
        rows += measure(STAGE_OF[exp], exp, dataset, results, stage_lenses(dataset, exp), {},
                        Path(args.bundle) if exp == "field" else None)
        if not args.keep:
            remove_dataset(dataset)
        write_csv(work / f"bench_full-{args.experiments.replace(',', '-')}.csv", rows)
    append_rows("bench_full", rows)


if __name__ == "__main__":
    main()
