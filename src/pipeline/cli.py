"""Command line: ``python -m pipeline COMMAND`` (init-dataset, validate, simulate, apply, lightfield, publish, verify-store,
store history, compare, diagnose).

It only parses arguments and calls the package; the workflow itself runs with
``snakemake``.
"""

from __future__ import annotations

import argparse
import sys

from pipeline import __version__
from pipeline.errors import InputError

#: exit codes (documented in --help and docs/running-your-data.md)
EXIT_OK = 0
EXIT_BAD_INPUT = 1       # the dataset has problems, a file cannot be read, OUT already exists
EXIT_USAGE = 2           # unknown command or option, missing argument (argparse's own code)
EXIT_INTERRUPTED = 130   # Ctrl-C (128 + SIGINT, as shells report it)
#: column where --help starts the one-line descriptions (room for 'init-dataset')
HELP_COLUMN = 28

DESCRIPTION = """\
Calibrate a RAW camera as a radiometer. These commands lay out a lab's raw
files as a calibration dataset (docs/dataset-format.md), check it, simulate one,
turn raw frames into radiance with a calibration bundle, integrate radiance
sphere grids into the light field (irradiances, average cosines), publish bundles
into an append-only calibration store, compare two calibrations, or say what a
run's diagnostics found;
the calibration itself runs with snakemake."""

EXAMPLES = f"""\
examples:
  python -m pipeline init-dataset /data/raw /data/calib2024 --lab-log /data/lab_log.csv
  python -m pipeline validate /data/calib2024
  snakemake --cores 2 --config dataset=/data/calib2024
  python -m pipeline apply --calibration results/calibration/SIM-0001.nc sky.dng -o sky.nc
  python -m pipeline publish results/calibration/SIM-0001.nc --dataset /data/calib2024 --store /archive/calibrations
  python -m pipeline apply --store /archive/calibrations sky.dng -o sky.nc
  python -m pipeline lightfield --medium water --attitude imu.csv sky.nc -o lightfield.nc
  python -m pipeline compare old/SIM-0001.nc results/calibration/SIM-0001.nc -o compare.nc --html compare.html
  python -m pipeline store history SIM-0001 --store /archive/calibrations -o history.csv
  python -m pipeline simulate --out data/sim-tiny --scale tiny --seed 1
  python -m pipeline diagnose --results results --explain shutter_offset

exit codes:
  {EXIT_OK}    ok
  {EXIT_BAD_INPUT}    bad input: the dataset has problems, a file cannot be read, OUT already exists
  {EXIT_USAGE}    usage error: unknown command or option, missing argument
  {EXIT_INTERRUPTED}  interrupted (Ctrl-C)

Run 'python -m pipeline COMMAND --help' for the options of one command."""

INIT_EXAMPLES = """\
RAW_DIR holds either one sub-folder per experiment (dark/, linearity/,
geometry/, rolloff/, spectral/, absolute/, immersion/, field/), or raw files
plus a lab log whose 'experiment' column names the experiment of each file.
The lab log is a CSV file with a 'file' column (path relative to RAW_DIR, or
the file name) and any of the columns only the lab knows (lens, kind, sweep,
medium, azimuth_deg, angle_deg, wavelength_nm, condition, water_height_cm,
temperature_c). The raw files are linked (or copied with --copy), never
modified; OUT must not exist.

examples:
  python -m pipeline init-dataset /data/raw /data/calib2024
  python -m pipeline init-dataset /data/raw /data/calib2024 --lab-log /data/lab_log.csv --copy"""

VALIDATE_EXAMPLES = """\
Lists every problem at once, grouped by file (line, column, what is wrong,
how to fix it), and exits 1 when there is any; prints one 'ok: ...' line and
exits 0 otherwise. The parts are checked against each other too (every frame's
camera, CFA pattern and levels against the others and dataset.yaml, the lens
regions, the field sidecars); what can only be suspected (a time stamp in the
future or out of order, the sun below the horizon at the field site) is a
'warning: ...' line. The workflow runs the same checks before any stage.

examples:
  python -m pipeline validate /data/calib2024
  python -m pipeline validate /data/calib2024 --checksums"""

SIMULATE_EXAMPLES = """\
examples:
  python -m pipeline simulate --out data/sim-tiny --scale tiny --seed 1
  python -m pipeline simulate --out data/sim --effect shutter_offset:offset_s=0.0004 --experiments dark,linearity
  python -m pipeline simulate --out data/phone --camera smartphone --scale tiny --effect dark_current"""

PUBLISH_EXAMPLES = """\
The store is append-only: STORE/<serial>/<valid_from>_<sha256[:16]>.nc, read-only
copies listed in STORE/index.csv. A bundle is valid from the latest DateTimeOriginal
of the lab frames it was made from (--dataset, the dataset the calibration ran on)
or from --valid-from; 'apply --store' gives each frame the calibration with the
newest validity start not after the frame's DateTimeOriginal. Publishing the same
file again writes nothing.

examples:
  python -m pipeline publish results/calibration/SIM-0001.nc --dataset /data/calib2024
  python -m pipeline publish results/calibration/SIM-0001.nc --valid-from 2024-05-01 --store /archive/calibrations
  python -m pipeline verify-store /archive/calibrations"""


COMPARE_EXAMPLES = """\
Both bundles must be of one camera model and lens layout: the same camera at
two dates (drift) or two units of the model (unit-to-unit). The difference's
sigma combines both budgets; a term that comes from a lab input both bundles
share (same sha256: the reference reading, the source spectrum, the frames) is
common and cancels. Thresholds: the compare section of src/pipeline/schema.yaml.
See docs/compare.md.

examples:
  python -m pipeline compare calibration-store/SIM-0001/20210310T093000_0123456789abcdef.nc \\
      results/calibration/SIM-0001.nc -o compare.nc --html compare.html"""

STORE_EXAMPLES = """\
examples:
  python -m pipeline store history SIM-0001 --store /archive/calibrations
  python -m pipeline store history SIM-0001 -o history.csv --figure history.png"""

DIAGNOSE_EXAMPLES = """\
Reads what the workflow's diagnostics rule wrote (RESULTS/diagnostics/*.csv and the closure
table RESULTS/closure/residuals.nc) and recomputes nothing: run the workflow first.

examples:
  python -m pipeline diagnose
  python -m pipeline diagnose --results /scratch/run1/results --explain dark_current"""


def simulate_from_config(out, simulation: dict) -> None:
    """Simulate the default dataset from the ``simulate_if_missing`` config section.

    Parameters
    ----------
    out : str or pathlib.Path
        The dataset folder to write.
    simulation : dict
        The ``simulate_if_missing`` section, defaults filled: ``scale`` (tiny, small, medium or full), ``seed``
        (int), ``effects`` (effect specifications such as ``shutter_offset:offset_s=0.0004``) and optionally
        ``lab_noise`` (bool, default False).
    """
    from pipeline.effects.base import parse_effect_spec
    from pipeline.simulate import simulate_dataset

    effects = [parse_effect_spec(s) for s in simulation["effects"]]
    simulate_dataset(out, scale=simulation["scale"], seed=simulation["seed"], effects=effects,
                     lab_noise=bool(simulation.get("lab_noise", False)))


class _HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keeps the epilog's layout; leaves room for the indented command names before their help."""

    def add_argument(self, action):
        super().add_argument(action)
        if isinstance(action, argparse._SubParsersAction):
            # the command names are listed one indent deeper than the width argparse measured
            self._action_max_length = max(self._action_max_length,
                                          max(len(name) for name in action.choices) + 2 * self._indent_increment + 2)


def _scale(name: str) -> str:
    """--scale NAME, checked against the simulator's scales (imported only when the option is used)."""
    from pipeline.simulate import SCALES

    if name not in SCALES:
        raise argparse.ArgumentTypeError(f"unknown scale {name!r}; choose one of {', '.join(SCALES)}")
    return name


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m pipeline`` with one sub-command per command.

    Returns
    -------
    argparse.ArgumentParser
        The parser; the chosen command's name is in the parsed namespace's ``command``.
    """
    def fmt(prog):
        return _HelpFormatter(prog, max_help_position=HELP_COLUMN)
    parser = argparse.ArgumentParser(prog="python -m pipeline", description=DESCRIPTION, epilog=EXAMPLES,
                                     formatter_class=fmt)
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, title="commands", metavar="COMMAND")

    init = sub.add_parser("init-dataset", help="lay out a folder of raw files as a calibration dataset",
                          description="Write dataset.yaml, a frames.csv per experiment and MD5SUMS from a "
                                      "folder of raw files (and a lab log).",
                          epilog=INIT_EXAMPLES, formatter_class=fmt)
    init.add_argument("raw_dir", metavar="RAW_DIR", help="folder of raw files (read only)")
    init.add_argument("out", metavar="OUT", help="dataset folder to create (must not exist)")
    init.add_argument("--lab-log", metavar="LOG.csv", default=None,
                      help="CSV lab log: file, experiment and the columns only the lab knows")
    init.add_argument("--copy", action="store_true",
                      help="copy the raw files instead of linking to them (for a dataset to move or upload)")

    val = sub.add_parser("validate", help="list every problem of a dataset at once (exit 1 if any)",
                         description="Check dataset.yaml, MD5SUMS, every frames.csv, the tags of every frame "
                                     "and the sidecar files.",
                         epilog=VALIDATE_EXAMPLES, formatter_class=fmt)
    val.add_argument("dataset", metavar="DATASET", help="dataset folder")
    val.add_argument("--checksums", action="store_true",
                     help="also read every file and compare its MD5 with MD5SUMS (slow)")

    sim = sub.add_parser("simulate", help="write a simulated calibration dataset and its truth folder",
                         description="Simulate the calibration experiments of the default dual-fisheye camera.",
                         epilog=SIMULATE_EXAMPLES, formatter_class=fmt)
    sim.add_argument("--out", required=True, help="dataset folder to create (must not exist)")
    sim.add_argument("--scale", type=_scale, default="small", metavar="NAME",
                     help="size of the simulated dataset (default: small; an unknown name lists the scales)")
    sim.add_argument("--seed", type=int, default=0)
    sim.add_argument("--effect", action="append", default=[], metavar="NAME[:param=value,...]",
                     help="switch on a true effect of the simulated camera (repeatable)")
    sim.add_argument("--experiments", default=None,
                     help="comma-separated experiments to simulate (default: all the simulator writes)")
    sim.add_argument("--full-well-e", type=float, default=None, metavar="ELECTRONS",
                     help="full-well capacity of the simulated sensor (default: none; the ADC clips first)")
    sim.add_argument("--lab-errors", action="store_true",
                     help="draw the lab's systematic errors from the seed (calibration lamp, reference radiometer, "
                          "photodiode; written to the truth); default: a perfect lab")
    sim.add_argument("--lab-noise", action="store_true",
                     help="add the lab's frame-to-frame noise (source flicker and drift, bias jitter, "
                          "room-temperature drift; sizes written to the truth); default: none")
    sim.add_argument("--camera", choices=("dual-fisheye", "smartphone"), default="dual-fisheye",
                     help="the simulated camera: the default dual-fisheye 360 camera, or a rectilinear smartphone "
                          "(one region, 12-bit, GRBG, optically black margins, a gain table not proportional to "
                          "ISO; dark and linearity experiments; scales tiny, small, medium)")
    sim.add_argument("--no-progress", action="store_true", help="no progress bar")
    from pipeline.bundle.apply_parser import add_apply_parser

    add_apply_parser(sub)
    from pipeline.lightfield.parser import add_lightfield_parser

    add_lightfield_parser(sub)
    pub = sub.add_parser("publish", help="file a calibration bundle into the append-only store",
                         description="Copy a calibration bundle into the store, dated and content-hashed, and "
                                     "append it to the store's index; nothing is ever overwritten.",
                         epilog=PUBLISH_EXAMPLES, formatter_class=fmt)
    pub.add_argument("bundle", metavar="BUNDLE", help="calibration bundle (results/calibration/<serial>.nc)")
    pub.add_argument("--store", metavar="DIR", default=None,
                     help="store folder (default: store.path of config/config.yaml, calibration-store)")
    start = pub.add_mutually_exclusive_group(required=True)
    start.add_argument("--dataset", metavar="DATASET",
                       help="the dataset the bundle was made from: valid from its latest lab frame's DateTimeOriginal")
    start.add_argument("--valid-from", metavar="DATE", help="validity start on the camera clock (2024-05-01 or 2024-05-01T08:30:00)")
    diag = sub.add_parser("diagnose", help="what the diagnostics found, a plain sentence per finding",
                          description="Print the error per experiment and level and, per finding, the missing "
                                      "effect (its signature, amplitude and the config line that adds it) or the "
                                      "structure no candidate explains (where it sits).",
                          epilog=DIAGNOSE_EXAMPLES, formatter_class=fmt)
    diag.add_argument("--results", metavar="DIR", default="results",
                      help="the workflow's results folder (default: results)")
    diag.add_argument("--explain", metavar="EFFECT", default=None,
                      help="also explain one effect: physics, signature, how it fared in this run")
    ver = sub.add_parser("verify-store", help="check every file of a calibration store against its index",
                         description="List every published file that is missing or changed (sha256) and every "
                                     "file the index does not list; exit 1 if any.", formatter_class=fmt)
    ver.add_argument("store", metavar="STORE", help="store folder")
    cmp = sub.add_parser("compare", help="compare two calibration bundles parameter by parameter",
                         description="Every calibrated parameter of bundle B against bundle A: both values, the "
                                     "difference, its combined standard uncertainty (terms of shared inputs cancel), "
                                     "z and a verdict per group.", epilog=COMPARE_EXAMPLES, formatter_class=fmt)
    cmp.add_argument("bundle_a", metavar="BUNDLE_A", help="calibration bundle A (the reference)")
    cmp.add_argument("bundle_b", metavar="BUNDLE_B", help="calibration bundle B (compared with A)")
    cmp.add_argument("-o", "--out", metavar="OUT.nc", default=None, help="write the comparison table as NetCDF")
    cmp.add_argument("--html", metavar="OUT.html", default=None, help="write the comparison as an HTML page")
    sto = sub.add_parser("store", help="look into a calibration store (store history)",
                         description="Look into a calibration store.", epilog=STORE_EXAMPLES, formatter_class=fmt)
    store_sub = sto.add_subparsers(dest="store_command", required=True, title="store commands", metavar="STORE_COMMAND")
    hist = store_sub.add_parser("history", help="a camera's calibrations in validity order with the drift of R^-1",
                                description="List the calibrations of camera SERIAL in validity order with R^-1 per "
                                            "lens and band and its change from the one before (percent, sigma, z).",
                                epilog=STORE_EXAMPLES, formatter_class=fmt)
    hist.add_argument("serial", metavar="SERIAL", help="camera serial number (the store's folder name)")
    hist.add_argument("--store", metavar="DIR", default=None,
                      help="store folder (default: store.path of config/config.yaml, calibration-store)")
    hist.add_argument("-o", "--out", metavar="OUT.csv", default=None, help="write the table as CSV")
    hist.add_argument("--figure", metavar="OUT.png", default=None, help="draw R^-1 against the validity start (PNG)")
    return parser


def _init_dataset(args) -> int:
    from pipeline.scaffold import describe_result, init_dataset

    result = init_dataset(args.raw_dir, args.out, lab_log=args.lab_log, copy=args.copy)
    print(describe_result(result))
    return EXIT_OK


def _validate(args) -> int:
    from pipeline.io.validation import (format_problems, grouped_warning_lines, inspect_dataset, ok_line,
                                     unlisted_files, warning_lines)

    warnings = []
    dataset, problems = inspect_dataset(args.dataset, checksums=args.checksums, warnings=warnings)
    for line in grouped_warning_lines(warnings, args.dataset):
        print(line)
    if problems:
        print(format_problems(problems, args.dataset))
        print(f"\nfix them and run: python -m pipeline validate {args.dataset}")
        return EXIT_BAD_INPUT
    for line in warning_lines(unlisted_files(dataset)):
        print(line)
    print(ok_line(dataset))
    return EXIT_OK


def _simulate(args) -> int:
    from pipeline.effects.base import parse_effect_spec
    from pipeline.simulate import simulate_dataset
    from pipeline.simulate.dataset import EXPERIMENTS, truth_dir_for

    effects = [parse_effect_spec(s) for s in args.effect]
    if args.camera == "smartphone":
        from pipeline.simulate.smartphone import PHONE_EXPERIMENTS, simulate_smartphone_dataset

        experiments = tuple(e for e in args.experiments.split(",") if e) if args.experiments else PHONE_EXPERIMENTS
        out = simulate_smartphone_dataset(args.out, scale=args.scale, seed=args.seed, effects=effects,
                                          experiments=experiments)
        print(f"dataset: {out}\ntruth:   {truth_dir_for(out)}")
        return EXIT_OK
    experiments = tuple(e for e in args.experiments.split(",") if e) if args.experiments else EXPERIMENTS
    sensor = {"full_well_e": args.full_well_e} if args.full_well_e is not None else None
    out = simulate_dataset(args.out, scale=args.scale, seed=args.seed, effects=effects,
                           experiments=experiments, progress=not args.no_progress, sensor=sensor,
                           lab_errors=args.lab_errors, lab_noise=args.lab_noise)
    print(f"dataset: {out}\ntruth:   {truth_dir_for(out)}")
    return EXIT_OK


def _apply(args) -> int:
    from pipeline.bundle.apply import apply_command

    if args.store is None:
        return apply_command(args)
    from pipeline.bundle.store import calibrations_for_frames, output_for

    groups = calibrations_for_frames(args.store, args.raw)
    for bundle, row, frames in groups:
        print(f"calibration: {bundle} (valid from {row['valid_from']}) for {len(frames)} frame(s)")
        one = argparse.Namespace(**{**vars(args), "calibration": str(bundle), "raw": frames,
                                    "out": str(output_for(args.out, row, len(groups)))})
        code = apply_command(one)
        if code != EXIT_OK:
            return code
    return EXIT_OK


def _lightfield(args) -> int:
    from pipeline.lightfield.command import lightfield_command

    return lightfield_command(args)


def _publish(args) -> int:
    from pipeline.config import load_config
    from pipeline.bundle.store import parse_valid_from, publish

    store = args.store if args.store is not None else load_config()["store"]["path"]
    valid_from = parse_valid_from(args.valid_from) if args.valid_from is not None else None
    row, written = publish(args.bundle, store, valid_from=valid_from, dataset=args.dataset)
    if written:
        print(f"published: {store}/{row['file']} (camera {row['serial']}, valid from {row['valid_from']}, "
              f"{row['valid_from_source']})")
    else:
        print(f"already published: {store}/{row['file']} (camera {row['serial']}, valid from {row['valid_from']}, "
              f"published {row['published_utc']}); nothing written")
    return EXIT_OK


def _verify_store(args) -> int:
    from pipeline.bundle.store import read_index, verify_store

    problems = verify_store(args.store)
    for line in problems:
        print(f"error: {line}", file=sys.stderr)
    if problems:
        return EXIT_BAD_INPUT
    print(f"ok: {len(read_index(args.store))} calibration(s) in {args.store}, every file as published")
    return EXIT_OK


def _compare(args) -> int:
    from pipeline.bundle.compare import compare_bundles, render_html, summary_lines, write_comparison
    from pipeline.config import load_config

    table = compare_bundles(args.bundle_a, args.bundle_b, load_config())
    print("\n".join(summary_lines(table)))
    if args.out:
        print(f"table: {write_comparison(table, args.out)}")
    if args.html:
        print(f"page:  {render_html(table, args.html)}")
    return EXIT_OK


def _store(args) -> int:
    from pipeline.bundle.compare import history, history_lines, write_history_csv, write_history_figure
    from pipeline.config import load_config

    config = load_config()
    store = args.store if args.store is not None else config["store"]["path"]
    entries = history(store, args.serial, config)
    print("\n".join(history_lines(entries, args.serial)))
    if args.out:
        print(f"table:  {write_history_csv(entries, args.out)}")
    if args.figure:
        print(f"figure: {write_history_figure(entries, args.figure, args.serial)}")
    return EXIT_OK


def _diagnose(args) -> int:
    from pipeline.diagnostics.findings import diagnosis_lines, explain_lines, read_diagnostics

    found = read_diagnostics(args.results)
    lines = diagnosis_lines(found, args.results)
    if args.explain:
        lines += ["", *explain_lines(found, args.explain)]
    print("\n".join(lines))
    return EXIT_OK


COMMANDS = {"diagnose": _diagnose, "init-dataset": _init_dataset, "validate": _validate, "simulate": _simulate, "apply": _apply,
            "lightfield": _lightfield,
            "publish": _publish, "verify-store": _verify_store, "compare": _compare, "store": _store}


def main(argv: list[str] | None = None) -> int:
    """Run one command of ``python -m pipeline`` and return its exit code.

    A bad input (:class:`~pipeline.errors.InputError`) is printed on stderr (every problem when a validator found
    several) rather than raised; a usage error exits from argparse with ``EXIT_USAGE``.

    Parameters
    ----------
    argv : list of str, optional
        The command line without the program name; None (default) reads ``sys.argv``.

    Returns
    -------
    int
        The exit code: ``EXIT_OK`` (0), ``EXIT_BAD_INPUT`` (1) or ``EXIT_INTERRUPTED`` (130), or the command's own.
    """
    args = build_parser().parse_args(argv)   # exits with EXIT_USAGE on a usage error
    try:
        return COMMANDS[args.command](args)
    except InputError as exc:
        if len(exc.problems) > 1:
            from pipeline.io.validation import format_problems

            print(format_problems(exc.problems), file=sys.stderr)
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
