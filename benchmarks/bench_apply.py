"""Time ``apply`` on one full-resolution frame against the decode of the same frame, in the same run.

    python benchmarks/bench_apply.py [--repeat 5] [--warmup 1] [--work /tmp/bench-apply] [--seed 1] [--time-bundle]

The decode floor is what every stage pays per frame: ``pipeline.io.rawio.read_raw``
(rawpy decode and tags) of the DNG plus ``pipeline.io.bands.split_bands`` of each
lens region. ``apply`` is ``pipeline.bundle.apply.apply_calibration(bundle, [frame],
"air", out)``: decode, the measurement chain on every band pixel of both
lenses, the sphere grid and the NetCDF write; ``apply-grid`` the same with
``pixels=False`` (``--no-pixels``: the sphere grid only, no per-pixel maps
written); ``apply-maps`` the pixel maps with ``pixel_geometry=False``
(``--no-pixel-geometry``: no theta, phi, solid angle, zenith and azimuth
maps, which stay in the bundle). Each is run ``--repeat`` times, each run in a fresh Python process,
alternating, after ``--warmup`` untimed rounds (1: the bundle and the frame
into the page cache); before each run the output of the one before is deleted
and the file system synced, untimed (so that no run pays for freeing the
455 MB written by the run before, or shares the cores with its writeback);
the script prints the minimum and median wall time,
the median CPU time (all threads, user and system, and each apart: the
system time is mostly the kernel's page faults and page-cache copies; on a virtual machine that hands
freed memory back to its host, free page reporting, a page not recently used costs about ten times a
reused one, README "Performance"), the peak
resident memory of each process (``VmHWM``) and the ratios apply / decode
of the medians.

The calibration bundle (made once, kept in ``--work``; several GB, keep it
out of the repository) has the real camera's 6912 x 3456 frame and
1728 x 1728 band images, but is not the full simulated dataset: simulating
the experiments the bundle needs at the full scale takes about 1,300 frames
at 2 to 6 s each (over an hour on 2 cores). So:

* dark, linearity and absolute are simulated at the full lens region
  (3456 px) with 3 dark frames and 2 linearity frames per setting instead of
  15 and 4 (a :class:`pipeline.simulate.dataset.Scale` of this script) and the
  absolute experiment's own counts; their stages run on those frames at full
  resolution (hot-pixel mask, read noise, dark model, gain, R^-1);
* geometry is not fitted: its artefact holds the simulator's true per-band
  maps at the full resolution (what the tests hand later stages; the
  geometry stage itself costs about 5 min per lens at this scale);
* roll-off and spectral (per-band coefficients only, no pixel maps) are
  simulated and fitted at the small scale with their full frame counts.

When the bundle's layout changes (a new calibration artefact version), delete
only ``results/calibration/bundle.nc`` in ``--work``: the script then gathers
it again from the stage artefacts kept in ``results/`` (the simulated datasets
and the fitted stages are reused). After a change of a stage's artefact version
delete that stage's folder in ``results/`` as well (``dark-full``, ...): the
stage then runs again on the kept datasets (dark, linearity and absolute at
the full resolution with the geometry: 470 s here, the machine shared).

``apply`` reads only the bundle's values, so its cost is that of a bundle made
from the whole dataset; its radiances are not a truth test (tests/bundle/test_apply.py
is). The frame timed is the first signal frame of the full-scale absolute
experiment (ISO 100, calibrated exposure).
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
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

HERE = Path(__file__).resolve().parent
LENSES = ("far", "close")
EFFECTS = [("dark_current", {}), ("hot_pixels", {})]
FULL_EXPERIMENTS = ("dark", "linearity", "absolute")
SMALL_EXPERIMENTS = ("rolloff", "spectral")


def _simulate(folder: str, scale, seed: int, experiments) -> float:
    from pipeline.simulate import simulate_dataset

    t0 = time.perf_counter()
    simulate_dataset(folder, scale=scale, seed=seed, effects=EFFECTS, experiments=experiments, progress=False)
    return time.perf_counter() - t0


def _true_geometry(folder: Path, band_px: int, effects) -> dict:
    from pipeline.io.artefact import write_artefact
    from pipeline.simulate.rolloff import true_band_models
    from pipeline.stages.geometry_maps import maps_dataset

    import numpy as np

    from pipeline.io.bands import BANDS

    paths = {}
    for lens in LENSES:
        models = true_band_models(lens, band_px)
        ds = maps_dataset(models, (band_px, band_px))
        for name, value in (("circle_xc_px", lambda m: m.xc), ("circle_yc_px", lambda m: m.yc),
                            ("circle_radius_px", lambda m: m.image_circle_radius())):
            ds[name] = (("medium", "band"), np.array([[value(models[(m, b)]) for b in BANDS]
                                                      for m in ds["medium"].values]), {"units": "pixel"})
        paths[lens] = write_artefact(ds, folder / f"{lens}.nc", stage="geometry", inputs={}, config_subset={},
                                     effects=effects)
    return paths


def build(work: Path, seed: int) -> tuple[Path, Path]:
    """The full-resolution bundle and the frame to time (made once; see the module docstring)."""
    import yaml

    from pipeline.bundle.calibration import build_bundle
    from pipeline.config import load_config
    from pipeline.simulate.dataset import SCALES, Scale
    from pipeline.runner.workflow import STAGES, load_model, run_stage

    full, small = work / "dataset-full-reduced", work / "dataset-small"
    results = work / "results"
    bundle = results / "calibration" / "bundle.nc"
    if not bundle.exists():
        reduced = Scale("full", lens_px=SCALES["full"].lens_px, dark_frames=3, linearity_frames=2)
        jobs = [(str(full), reduced, seed, FULL_EXPERIMENTS), (str(small), "small", seed, SMALL_EXPERIMENTS)]
        jobs = [j for j in jobs if not Path(j[0]).exists()]
        with ProcessPoolExecutor(max_workers=2) as pool:
            for job, took in zip(jobs, pool.map(_simulate, *zip(*jobs))):
                print(f"simulated {job[0]} ({', '.join(job[3])}) in {took:.0f} s", flush=True)
        cfg = load_config()
        effects = load_model(cfg)
        t0 = time.perf_counter()
        art = {}
        for tag, root in (("small", small), ("full", full)):
            meta = yaml.safe_load((root / "dataset.yaml").read_text())
            band_px = (meta["lenses"]["far"]["rows"][1] - meta["lenses"]["far"]["rows"][0]) // 2
            art[tag] = {"geometry": _true_geometry(results / f"geometry-{tag}", band_px, effects)}
        for tag, root, stages in (("small", small, ("rolloff", "spectral")), ("full", full, ("dark", "linearity"))):
            for stage in stages:
                spec = STAGES[stage]
                upstream = {n: art[tag][n] for n in spec.upstream + spec.optional_upstream if n in art[tag]}
                art[tag][stage] = {lens: results / f"{stage}-{tag}" / f"{lens}.nc" for lens in LENSES}
                if not all(p.exists() for p in art[tag][stage].values()):
                    run_stage(stage, root, cfg, art[tag][stage], upstream)
        art["full"]["spectral"] = art["small"]["spectral"]
        spec = STAGES["absolute"]
        art["full"]["absolute"] = {lens: results / "absolute-full" / f"{lens}.nc" for lens in LENSES}
        if not all(p.exists() for p in art["full"]["absolute"].values()):
            run_stage("absolute", full, cfg, art["full"]["absolute"],
                      {n: art["full"][n] for n in spec.upstream + spec.optional_upstream if n in art["full"]})
        art["full"]["rolloff"] = art["small"]["rolloff"]
        artefacts, meta = kept_artefacts(work)
        build_bundle(artefacts, bundle, meta["camera"], meta["lenses"], cfg)
        print(f"stages and bundle in {time.perf_counter() - t0:.0f} s", flush=True)
    frames = [line.split(",") for line in (full / "absolute" / "frames.csv").read_text().splitlines()[1:]]
    frame = full / "absolute" / next(f for f, _, kind in frames if kind == "signal")
    return bundle, frame


def kept_artefacts(work: Path) -> tuple[dict, dict]:
    """The stage artefacts the bundle is gathered from (made by :func:`build` in ``work``/results: dark,
    linearity and absolute of the full-resolution frames, the true geometry at full resolution, roll-off and
    spectral of the small scale) and the full dataset's dataset.yaml."""
    import yaml

    results = work / "results"
    tags = {"geometry": "full", "dark": "full", "linearity": "full", "absolute": "full", "spectral": "small",
            "rolloff": "small"}
    artefacts = {stage: {lens: results / f"{stage}-{tag}" / f"{lens}.nc" for lens in LENSES}
                 for stage, tag in tags.items()}
    return artefacts, yaml.safe_load((work / "dataset-full-reduced" / "dataset.yaml").read_text())


def bundle_child(work: str, out: str) -> None:
    """Gather the bundle from the kept stage artefacts into ``out`` in this fresh process (what the workflow's
    ``calibration`` rule runs); prints wall, CPU and peak RSS as JSON."""
    from pipeline.bundle.calibration import build_bundle
    from pipeline.config import load_config

    artefacts, meta = kept_artefacts(Path(work))
    cfg = load_config()
    t0, c0 = time.perf_counter(), time.process_time()
    build_bundle(artefacts, Path(out), meta["camera"], meta["lenses"], cfg)
    print(json.dumps({"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
                      "peak_rss_mib": _peak_rss_mib(), "size_mb": Path(out).stat().st_size / 1e6}))


def child(what: str, frame: str, bundle: str, out: str) -> None:
    """One timed call in this fresh process; prints wall time and peak RSS as JSON."""
    import yaml

    from pipeline.bundle.apply import apply_calibration
    from pipeline.io.bands import cut_region, split_bands
    from pipeline.io.rawio import read_raw

    meta = yaml.safe_load((Path(frame).parents[2] / "dataset.yaml").read_text())
    t0, c0, r0 = time.perf_counter(), time.process_time(), resource.getrusage(resource.RUSAGE_SELF)
    if what == "decode":
        raw = read_raw(frame)
        for lens in LENSES:
            region = meta["lenses"][lens]
            split_bands(cut_region(raw.cfa, region["rows"], region["cols"]), raw.cfa_pattern)
    else:
        apply_calibration(bundle, [frame], "air", out, overwrite=True, pixels=what != "apply-grid",
                          pixel_geometry=what != "apply-maps")
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    print(json.dumps({"wall_s": wall, "cpu_s": cpu, "user_s": r1.ru_utime - r0.ru_utime,
                      "system_s": r1.ru_stime - r0.ru_stime, "peak_rss_mib": _peak_rss_mib()}))


def _peak_rss_mib() -> float:
    """Peak resident memory of this process since its exec (VmHWM; ``ru_maxrss`` would also count the
    parent's resident size at the fork: the builder's gigabytes in the run that made the bundle)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def time_bundle(work: Path, repeat: int) -> None:
    """The bundle gathered ``repeat`` times from the kept stage artefacts, each in a fresh process."""
    out = work / "bundle-timed.nc"
    for k in range(repeat):
        out.unlink(missing_ok=True)
        os.sync()
        load_start = os.getloadavg()[0]
        proc = subprocess.run([sys.executable, __file__, "--bundle-child", str(work), str(out)], capture_output=True,
                              text=True)
        if proc.returncode != 0:
            sys.exit(f"gathering the bundle failed:\n{proc.stderr[-2000:]}")
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        print(f"bundle gathered (run {k + 1}): {r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s CPU, peak "
              f"{r['peak_rss_mib']:.0f} MiB, {r['size_mb']:.0f} MB written (load {load_start:.1f} -> "
              f"{os.getloadavg()[0]:.1f})", flush=True)
    out.unlink(missing_ok=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--work", default="/tmp/bench-apply", help="folder for the datasets, artefacts and bundle")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--warmup", type=int, default=1, help="untimed rounds first (the bundle and the frame into "
                                                           "the page cache)")
    ap.add_argument("--time-bundle", action="store_true",
                    help="also gather the bundle again from the kept stage artefacts, --repeat times, each in a "
                         "fresh process (the calibration rule's cost at the full resolution), into a temporary "
                         "file in --work")
    ap.add_argument("--bundle-child", nargs=2, metavar=("WORK", "OUT"), help=argparse.SUPPRESS)
    ap.add_argument("--child", nargs=4, metavar=("WHAT", "FRAME", "BUNDLE", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(*args.child)
        return
    if args.bundle_child:
        bundle_child(*args.bundle_child)
        return
    work = Path(args.work)
    bundle, frame = build(work, args.seed)
    if args.time_bundle:
        time_bundle(work, args.repeat)
    out = work / "apply-out.nc"
    print(f"frame {frame} ({frame.stat().st_size / 1e6:.0f} MB), bundle {bundle} ({bundle.stat().st_size / 1e6:.0f} MB)")
    runs = {"decode": [], "apply": [], "apply-maps": [], "apply-grid": []}
    load_before = os.getloadavg()[0]
    for k in range(args.warmup + args.repeat):
        for what in runs:
            # untimed: no earlier output to replace (its pages freed in the child's rename) and no dirty pages
            # of the child before still being written back while this one runs
            out.unlink(missing_ok=True)
            os.sync()
            proc = subprocess.run([sys.executable, __file__, "--child", what, str(frame), str(bundle), str(out)],
                                  capture_output=True, text=True)
            if proc.returncode != 0:
                sys.exit(f"{what} failed:\n{proc.stderr[-2000:]}")
            if k >= args.warmup:
                runs[what].append(json.loads(proc.stdout.strip().splitlines()[-1]))
    print(f"{args.repeat} runs each, each in a fresh process; load average (1 min) {load_before:.1f} before, "
          f"{os.getloadavg()[0]:.1f} after")
    print(f"{'':<10} {'min ms':>8} {'median ms':>10} {'CPU median ms':>14} {'user median ms':>15} "
          f"{'system median ms':>17} {'peak MiB':>9}")
    med, cpu, user = {}, {}, {}
    rows = []
    for what, rs in runs.items():
        walls = [r["wall_s"] * 1e3 for r in rs]
        med[what] = statistics.median(walls)
        cpu[what] = statistics.median(r["cpu_s"] * 1e3 for r in rs)
        user[what] = statistics.median(r["user_s"] * 1e3 for r in rs)
        system = statistics.median(r["system_s"] * 1e3 for r in rs)
        rows.append({"what": what, "runs": len(rs), "min_ms": round(min(walls)), "median_ms": round(med[what]),
                     "cpu_median_ms": round(cpu[what]), "user_median_ms": round(user[what]),
                     "system_median_ms": round(system), "peak_mib": round(max(r["peak_rss_mib"] for r in rs)),
                     "load_before": round(load_before, 1)})
        print(f"{what:<10} {min(walls):8.0f} {med[what]:10.0f} {cpu[what]:14.0f} {user[what]:15.0f} {system:17.0f} "
              f"{max(r['peak_rss_mib'] for r in rs):9.0f}")
    print(f"apply / decode (wall medians): {med['apply'] / med['decode']:.2f} with the pixel maps, "
          f"{med['apply-maps'] / med['decode']:.2f} without the pixel geometry (--no-pixel-geometry), "
          f"{med['apply-grid'] / med['decode']:.2f} the sphere grid only (--no-pixels)")
    print(f"apply / decode (CPU medians, all threads): {cpu['apply'] / cpu['decode']:.2f} with the pixel maps, "
          f"{cpu['apply-grid'] / cpu['decode']:.2f} the sphere grid only")
    print(f"apply / decode (user CPU medians, without the kernel's page-cache and page-fault time): "
          f"{user['apply'] / user['decode']:.2f} with the pixel maps, {user['apply-grid'] / user['decode']:.2f} "
          "the sphere grid only")
    from record import append_rows

    append_rows("bench_apply", rows)


if __name__ == "__main__":
    main()
