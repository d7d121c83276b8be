"""The one stage runner: from dataset files and upstream artefacts to one artefact per lens.

Every stage module in :mod:`pipeline.stages` provides ``compute(ctx)``: it
reduces the frames of its experiment for one lens (streaming, each frame
decoded once) and returns that lens's artefact Dataset. Everything else a
stage needs is done here, once, in the same way for every stage:

* the effects of the model are read and their plugins loaded once;
* the dataset is opened (validated) and restricted to the lens of the job, so
  that the two lenses of the camera run as independent jobs;
* upstream artefacts are read and their stage and version checked;
* every input that was read is hashed (raw frames from the decoded bytes,
  ``dataset.yaml``, ``MD5SUMS``, the experiment's sidecars and the upstream
  artefacts), by path relative to the dataset or the results folder;
* the artefact is written with its provenance, atomically.

The registry :data:`STAGES` says what each stage reads; the Snakemake rules
and the command line use it to declare their inputs.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import json
import logging
import os
import signal
import sys
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import xarray as xr

from pipeline.io.artefact import BUNDLE_REQUIRED_STAGES, read_artefact, read_artefact_mapped, sha256_file, write_artefact
from pipeline.config import defaults, read_config_file, stage_params, validate_config
from pipeline.io.dataset import Dataset, open_dataset
from pipeline.effects import available, load_plugins
from pipeline.entry import exit_on_input_error, setup_log
from pipeline.errors import InputError
from pipeline.io.frames import decode_ahead
from pipeline.io.validation import (format_problems, grouped_warning_lines, inspect_dataset, unlisted_files,
                                 warning_lines)

log = logging.getLogger("pipeline.runner.workflow")

#: files at the dataset's root that every stage reads
DATASET_FILES = ("dataset.yaml", "MD5SUMS")


@dataclass(frozen=True)
class StageSpec:
    """What one stage reads: its experiment folder, sidecar files and upstream artefacts."""

    name: str
    experiment: str
    sidecars: tuple[str, ...] = ()
    upstream: tuple[str, ...] = ()
    optional_upstream: tuple[str, ...] = ()
    #: top-level keys of dataset.yaml the stage reads besides ``camera`` and its lens's region
    reads_meta: tuple[str, ...] = ()
    #: the stage applies the calibration bundle (every lab stage of both lenses) to its frames
    bundle: bool = False
    #: the stage runs only for the lenses its frames.csv names (the field: the lens at the zenith)
    lenses_from_frames: bool = False

    @property
    def experiments(self) -> tuple[str, ...]:
        """Experiment folders the stage needs, its own and those of its required upstream stages."""
        out = [self.experiment]
        needs = self.upstream + (BUNDLE_REQUIRED_STAGES if self.bundle else ())
        for name in needs:
            out += [e for e in STAGES[name].experiments if e not in out]
        return tuple(out)

    def module(self):
        """The stage's module in :mod:`pipeline.stages` (imported on first use).

        Returns
        -------
        module
            ``pipeline.stages.<name>``, which provides ``compute(ctx)``.
        """
        return importlib.import_module(f"pipeline.stages.{self.name}")


#: the stages in the order of the calibration chain (Larouche et al. 2024, Section 2)
STAGES: dict[str, StageSpec] = {spec.name: spec for spec in (
    StageSpec("dark", "dark"),
    StageSpec("linearity", "linearity", upstream=("dark",), optional_upstream=("geometry",)),
    StageSpec("geometry", "geometry", reads_meta=("chessboard",)),
    StageSpec("rolloff", "rolloff", upstream=("geometry",), optional_upstream=("dark", "linearity")),
    StageSpec("spectral", "spectral", sidecars=("photodiode.csv",), upstream=("geometry",),
              optional_upstream=("dark", "linearity")),
    StageSpec("absolute", "absolute", sidecars=("source_spectrum.csv", "source_reference.csv"),
              upstream=("spectral", "geometry"), optional_upstream=("dark", "linearity")),
    StageSpec("immersion", "immersion", sidecars=("water.yaml",), upstream=("geometry",),
              optional_upstream=("spectral", "linearity", "dark")),
    StageSpec("field", "field", sidecars=("reference_radiometer.csv", "site.yaml"), bundle=True,
              lenses_from_frames=True),
)}

#: Peak memory of one lens job: a fixed part (the interpreter and libraries, measured as the
#: diagnostics job's peak, which holds no image) plus bytes per band pixel of the lens region,
#: from the peak of each job in results/benchmarks/ of the small simulated dataset (288 x 288
#: band pixels per lens, 2026-12-01): (peak - fixed) / pixels. A scheduler is asked for
#: JOB_MEMORY_HEADROOM times that, and more on each retry. The dark stage's figure is from its peak at
#: the full scale (1728 x 1728 band pixels per lens; 1,455 to 1,553 MiB for 26 to 104 frames,
#: benchmarks/bench_full.py --scaling dark, 2026-12-02), which the small dataset's peak is too close
#: to the fixed part to show: it reduces one setting at a time, so the figure no longer grows with
#: the number of settings (it was 700, for the running sums of every setting at once).
JOB_MEMORY_FIXED_MIB = 230.0
JOB_MEMORY_BYTES_PER_BAND_PIXEL = {"dark": 500.0, "linearity": 400.0, "geometry": 2000.0, "rolloff": 350.0,
                                   "spectral": 50.0, "absolute": 50.0, "immersion": 50.0,
                                   # the field applies the bundle (every per-pixel map of both lenses) to one frame at a time
                                   "field": 400.0}
JOB_MEMORY_HEADROOM = 1.5

#: experiments each stage reads (a stage runs only when all are present)
STAGE_EXPERIMENTS = {name: spec.experiments for name, spec in STAGES.items()}


# --------------------------------------------------------------------------- the model
def load_model(config: dict) -> list[str]:
    """The effects of ``model.effects``, after importing the plugin modules that define user effects.

    Parameters
    ----------
    config : dict
        The run's configuration, with the section ``model`` (``effects``, optional ``plugins``).

    Returns
    -------
    list of str
        The names of the effects in the model, in the configuration's order.

    Raises
    ------
    pipeline.errors.InputError
        When a plugin module fails to import.
    """
    load_plugins(config["model"].get("plugins", []))
    return list(config["model"]["effects"])


def check_config(config: dict, config_file: str | Path, config_files=()) -> dict:
    """The workflow's start-up check of its configuration, before any job.

    Every file of ``config_files`` is read again by the
    strict reader, which refuses a key written twice (Snakemake keeps the last without a word); then the
    schema (filling its defaults, as ``pipeline.config.validate_config``), the plugin modules of
    ``model.plugins`` and the effect names of ``model.effects`` are checked.

    Parameters
    ----------
    config : dict
        The configuration as Snakemake merged it; its defaults are filled in place.
    config_file : str or pathlib.Path
        The config file the run read (the --config options extend it), named in the error.
    config_files : iterable of str or pathlib.Path, default ()
        The config files Snakemake read: config/config.yaml and each ``--configfile``.

    Returns
    -------
    dict
        ``config``, validated and with the schema's defaults.

    Raises
    ------
    pipeline.errors.InputError
        One, naming ``config_file`` (or the file with the duplicate key) and the first problem.
    """
    for path in dict.fromkeys(str(p) for p in config_files):
        read_config_file(path)
    try:
        validate_config(config)
        load_model(config)
    except InputError as exc:
        raise InputError(config_file, exc.problem) from None
    unknown = [name for name in config["model"]["effects"] if name not in available()]
    if unknown:
        raise InputError(config_file, f"model.effects: unknown effect '{unknown[0]}'; implemented: "
                                      f"{', '.join(available())} (a user effect needs its module in model.plugins)")
    return config


# --------------------------------------------------------------------------- one lens
@dataclass
class LensDataset(Dataset):
    """A dataset seen by the job of one lens: only that lens's region, only frames of it or of both."""

    lens: str = ""

    def frames(self, experiment: str) -> pd.DataFrame:
        """The frames table of an experiment, restricted to frames of this lens or of both.

        Parameters
        ----------
        experiment : str
            Name of the experiment folder.

        Returns
        -------
        pandas.DataFrame
            The rows of the experiment's frames.csv whose ``lens`` is this lens or ``both`` (all rows when the
            table has no ``lens`` column).
        """
        frames = super().frames(experiment)
        if "lens" in frames:
            frames = frames[frames["lens"].isin([self.lens, "both"])]
        return frames


def lens_view(dataset: Dataset, lens: str) -> LensDataset:
    """The dataset as the job of one lens sees it: only that lens's region, only frames of it or of both.

    Parameters
    ----------
    dataset : pipeline.io.dataset.Dataset
        The opened dataset.
    lens : str
        Name of a lens of ``dataset.yaml``.

    Returns
    -------
    LensDataset
        A view with only ``lens`` in ``lenses``.

    Raises
    ------
    pipeline.errors.InputError
        When the dataset has no such lens.
    """
    if lens not in dataset.lenses:
        raise InputError(dataset.root / "dataset.yaml", f"has no lens '{lens}' (lenses: {', '.join(dataset.lenses)})")
    fields = {f.name: getattr(dataset, f.name) for f in dataclasses.fields(Dataset)}
    fields["lenses"] = {lens: dataset.lenses[lens]}
    return LensDataset(**fields, lens=lens)


@dataclass
class StageContext:
    """What ``compute`` receives: the lens's dataset, the config, the model, the upstream artefacts."""

    stage: str
    lens: str
    dataset: LensDataset
    config: dict
    effects: list[str]
    upstream: dict[str, xr.Dataset]
    progress: bool = False
    #: the calibration bundle (stages with ``bundle``), opened as the ``calibration`` artefact
    bundle: xr.Dataset | None = None
    #: input path relative to the dataset root -> sha256, filled as frames are decoded
    inputs: dict[str, str] = field(default_factory=dict)

    def record_frames(self, hashes: dict[str, str], experiment: str | None = None) -> None:
        """Record the sha256 of decoded frames, given by their path relative to the experiment folder.

        Parameters
        ----------
        hashes : dict[str, str]
            Frame path relative to the experiment folder -> hex sha256 of its bytes.
        experiment : str, optional
            The experiment folder of the frames; the stage's own when None.
        """
        experiment = experiment or STAGES[self.stage].experiment
        for name, sha in hashes.items():
            self.inputs[f"{experiment}/{name}"] = sha

    @property
    def params(self) -> dict:
        """This stage's section of the configuration."""
        return self.config[self.stage]


def _relative(path: Path, root: Path) -> str:
    try:
        return str(Path(os.path.relpath(Path(path).resolve(), root.resolve())))
    except ValueError:      # another drive
        return str(path)


def decode_ahead_frames(config: dict) -> int:
    """The job's ``performance.decode_ahead_frames`` (the schema's default where the config lacks the section).

    Parameters
    ----------
    config : dict
        The run's configuration.

    Returns
    -------
    int
        How many frames are decoded ahead of the one a stage reduces.
    """
    return (config.get("performance") or defaults()["performance"])["decode_ahead_frames"]


#: upstream variables up to this size are read when a stage opens the artefact (the model parameters and the
#: tables, which a stage may read at every frame); larger ones, the per-pixel maps, stay on disk until read
UPSTREAM_IN_MEMORY_BYTES = 4 * 2**20


#: upstream artefacts of at most this many bytes on disk that :func:`run_stage` read whole and keeps in this
#: process, (resolved path, stage) -> ((inode, size, mtime in ns), the loaded artefact): a process that runs a
#: stage many times on the same upstream (an absolute stage per simulated lab session of one calibrated camera)
#: opens and decodes each of them once. The stages replace an artefact by renaming a new file into place (a new
#: inode); the workflow's jobs, one stage per process, never read one twice. At most ``_UPSTREAM_KEPT_ENTRIES``
#: artefacts of at most ``_UPSTREAM_KEPT_MEMORY_BYTES`` each in memory are kept.
UPSTREAM_KEPT_FILE_BYTES = 8 * 2**20
_UPSTREAM_KEPT: dict[tuple[str, str], tuple[tuple[int, int, int], xr.Dataset]] = {}
_UPSTREAM_KEPT_ENTRIES, _UPSTREAM_KEPT_MEMORY_BYTES = 16, 32 * 2**20


def _upstream_artefact(path: str | Path, name: str, opened: ExitStack) -> xr.Dataset:
    """The ``name`` artefact at ``path`` for a stage: a small one loaded whole (kept for the next run on the same
    file; the stage gets its own deep copy), a larger one opened lazily with its small variables read (closed
    by ``opened``)."""
    try:
        stat = os.stat(path)
    except OSError:
        stat = None                         # read_artefact says what is wrong with the path
    if stat is None or stat.st_size > UPSTREAM_KEPT_FILE_BYTES:
        return opened.enter_context(read_artefact(path, name, load=False, load_below_bytes=UPSTREAM_IN_MEMORY_BYTES))
    key = (str(Path(path).resolve()), name)
    identity = (stat.st_ino, stat.st_size, stat.st_mtime_ns)
    hit = _UPSTREAM_KEPT.get(key)
    if hit is None or hit[0] != identity:
        hit = (identity, read_artefact(path, name))
        _UPSTREAM_KEPT.pop(key, None)
        if hit[1].nbytes > _UPSTREAM_KEPT_MEMORY_BYTES:
            return hit[1]                   # read whole, not kept: the stage's own
        while len(_UPSTREAM_KEPT) >= _UPSTREAM_KEPT_ENTRIES:
            _UPSTREAM_KEPT.pop(next(iter(_UPSTREAM_KEPT)))          # the oldest first
        _UPSTREAM_KEPT[key] = hit
    return hit[1].copy(deep=True)


#: dataset folder -> (its files' fingerprint, the dataset) of the last check in this process that found no
#: problem: a stage run again on the unchanged folder (the stages of one calibration in a script) is not
#: checked again
_CHECKED: dict[tuple, tuple[tuple, Dataset]] = {}


def _fingerprint(root: Path, experiments=None) -> tuple:
    """(path, size, modification time) of every file the check reads: those at the dataset's top
    (dataset.yaml, MD5SUMS), every frames.csv, and every file of the checked experiments' folders (all
    folders when ``experiments`` is None): any edit of them changes it."""
    out = []
    for path in sorted(root.iterdir()):
        if path.is_dir() and (experiments is None or path.name in experiments):
            files = sorted(p for p in path.rglob("*") if p.is_file())
        else:
            files = [path / "frames.csv"] if path.is_dir() else [path]
        for file in files:
            try:
                stat = file.stat()
            except OSError:          # no frames.csv: the layout check names it
                continue
            out.append((file.relative_to(root).as_posix(), stat.st_size, stat.st_mtime_ns))
    return tuple(out)


def check_experiments(stage: str) -> tuple[str, ...]:
    """The experiments whose frames a stage run on its own is checked with.

    Its own and those of the stages it needs (their artefacts are made from them); the field's calibration
    bundle was checked with the lab's frames when it was made, so the field checks its own.

    Parameters
    ----------
    stage : str
        Name of a stage of :data:`STAGES`.

    Returns
    -------
    tuple of str
        Experiment folder names, the stage's own first.
    """
    spec = STAGES[stage]
    out = [spec.experiment]
    for name in spec.upstream:
        out += [e for e in check_experiments(name) if e not in out]
    return tuple(out)


def checked_dataset(root: str | Path, experiments=None, field_settings: dict | None = None) -> Dataset:
    """The dataset at ``root`` after the checks ``python -m pipeline validate`` makes.

    The checks are the layout, the tags of every frame, the sidecars and their consistency
    (``pipeline.io.validation.inspect_dataset``); the suspicions are logged as warnings. The result is kept
    while no file of the folder changes.

    Parameters
    ----------
    root : str or pathlib.Path
        The dataset folder.
    experiments : iterable of str, optional
        Check the frames and sidecars of these experiments only; all when None.
    field_settings : dict, optional
        The run's ``field`` section (the reference's match-up window and clock search the check uses).

    Returns
    -------
    pipeline.io.dataset.Dataset
        The opened, checked dataset.

    Raises
    ------
    pipeline.errors.InputError
        Naming the first problem (and counting the others) when there is one.
    """
    root = Path(root)
    key = (root.resolve(), None if experiments is None else tuple(sorted(experiments)),
           json.dumps(field_settings, sort_keys=True, default=str))
    fingerprint = _fingerprint(key[0], experiments) if key[0].is_dir() else ()
    kept = _CHECKED.get(key)
    if kept is not None and kept[0] == fingerprint:
        return kept[1]
    warnings: list = []
    dataset, problems = inspect_dataset(root, warnings=warnings, experiments=experiments,
                                        field_settings=field_settings)
    for line in grouped_warning_lines(warnings, root):
        log.warning("%s", line.removeprefix("warning: "))
    if problems:
        raise InputError.from_problems(problems, f"python -m pipeline validate {root} lists them all")
    _CHECKED[key] = (fingerprint, dataset)
    return dataset


def run_stage(stage: str, dataset: str | Path | Dataset, config: dict, outputs: dict[str, str | Path],
              upstream: dict[str, dict[str, str | Path]] | None = None,
              progress: bool = False, bundle: str | Path | None = None,
              checked: bool = False) -> dict[str, xr.Dataset]:
    """Run ``stage`` for each lens of ``outputs`` (lens -> artefact path); returns the artefacts.

    A required upstream artefact that is missing stops the stage with a clear message.
    A dataset folder is first checked as ``validate`` checks it (:func:`checked_dataset`: the frames' tags
    against each other and dataset.yaml, the sidecars against each other and the frames), on the
    experiments of :func:`check_experiments`, so a stage run directly never uses what validate refuses.

    Parameters
    ----------
    stage : str
        Name of a stage of :data:`STAGES`.
    dataset : str, pathlib.Path or pipeline.io.dataset.Dataset
        The dataset folder, or the dataset already opened.
    config : dict
        The run's validated configuration.
    outputs : dict[str, str or pathlib.Path]
        Lens -> path of the artefact to write (``results/<stage>/<lens>.nc``).
    upstream : dict[str, dict[str, str or pathlib.Path]], optional
        Upstream stage -> its artefacts per lens.
    progress : bool, default False
        Show the stage's progress.
    bundle : str or pathlib.Path, optional
        The calibration bundle that a stage with ``bundle`` applies.
    checked : bool, default False
        The dataset folder was checked already (the workflow's jobs: its start-up check ran it on the whole
        folder before any job); then only the layout is read.

    Returns
    -------
    dict[str, xarray.Dataset]
        Lens -> the artefact written, loaded in memory.

    Raises
    ------
    pipeline.errors.InputError
        When the experiment folder, a sidecar, a required upstream artefact or the bundle is missing, or the
        dataset fails its checks.
    """
    spec = STAGES[stage]
    module = spec.module()
    effects = load_model(config)
    if isinstance(dataset, Dataset):
        ds = dataset
        if not checked:
            checked_dataset(dataset.root, check_experiments(stage), config.get("field"))
    else:
        ds = open_dataset(dataset) if checked else checked_dataset(dataset, check_experiments(stage),
                                                                   config.get("field"))
    if spec.experiment not in ds.experiments():
        raise InputError(ds.root / spec.experiment, "experiment folder is absent")
    upstream = {name: dict(paths) for name, paths in (upstream or {}).items() if paths}
    fixed = {name: sha256_file(ds.root / name) for name in DATASET_FILES}
    for name in spec.sidecars:
        path = ds.root / spec.experiment / name
        if not path.is_file():
            raise InputError(path, "sidecar file is missing")
        fixed[f"{spec.experiment}/{name}"] = sha256_file(path)
    calibration = None
    if spec.bundle:
        if bundle is None:
            raise InputError(None, f"{stage} stage needs the calibration bundle; run the 'calibration' rule first")
        # only the lenses of this call (the field: the one at the zenith), their per-pixel maps memory-mapped:
        # the stage reads a crop of one medium's maps at each frame (the bundle is about 1 GB at the full scale)
        calibration = read_artefact_mapped(bundle, "calibration", lenses=list(outputs))
    out = {}
    # the upstream artefacts' hashes (the bundle's 1 GB about 1 s at the full scale) taken in a thread beside
    # the stage's work, which leaves a core to it while it waits for the next frame's decode
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="hash") as hashing:
        bundle_hash = hashing.submit(sha256_file, bundle) if calibration is not None else None
        for lens, out_path in outputs.items():
            out_path = Path(out_path)
            results_root = out_path.parent.parent
            artefacts, hashes = {}, {}
            with ExitStack() as opened:
                for name in spec.upstream + spec.optional_upstream:
                    path = upstream.get(name, {}).get(lens)
                    if path is None:
                        if name in spec.upstream:
                            raise InputError(None, f"{stage} stage of lens '{lens}' needs the {name} artefact; "
                                                   f"run the '{name}' stage first")
                        continue
                    # a large one opened lazily, closed once this lens's artefact is written: a stage reads of
                    # its upstream only what it uses (at the full resolution the geometry artefact is 128 MB, of
                    # which the absolute and spectral stages read the theta map in air); a small one kept
                    artefacts[name] = _upstream_artefact(path, name, opened)
                    hashes[_relative(path, results_root)] = hashing.submit(sha256_file, path)
                if bundle_hash is not None:
                    hashes[_relative(bundle, results_root)] = bundle_hash
                ctx = StageContext(stage=stage, lens=lens, dataset=lens_view(ds, lens), config=config,
                                   effects=effects, upstream=artefacts, progress=progress, bundle=calibration)
                with decode_ahead(decode_ahead_frames(config)):
                    art = module.compute(ctx)
                inputs = dict(fixed) | {name: h.result() for name, h in hashes.items()} | ctx.inputs
                write_artefact(art, out_path, stage=stage, inputs=inputs, config_subset=stage_params(config, stage),
                               effects=effects)
                art = art.load()
                log.info("%s %s: wrote %s (%d inputs hashed)", stage, lens, out_path, len(inputs))
            out[lens] = art
    return out


# --------------------------------------------------------------------------- the code a stage runs
PACKAGE_ROOT = Path(__file__).resolve().parent.parent


def _module_path(name: str) -> Path | None:
    parts = name.split(".")[1:]
    if not parts:
        return PACKAGE_ROOT / "__init__.py"
    rel = Path(*parts)
    for path in (PACKAGE_ROOT / rel.with_suffix(".py"), PACKAGE_ROOT / rel / "__init__.py"):
        if path.is_file():
            return path
    return None


#: (path, mtime_ns, size) -> the file's pipeline imports: every rule's code param walks the same modules,
#: so each file is parsed once per workflow process (an edited file has a new key)
_IMPORTS_CACHE: dict[tuple[str, int, int], frozenset[str]] = {}


def _package_imports(path: Path) -> frozenset[str]:
    """The ``pipeline.*`` modules a source file imports (at any depth of the file)."""
    stat = path.stat()
    key = (str(path), stat.st_mtime_ns, stat.st_size)
    if key not in _IMPORTS_CACHE:
        _IMPORTS_CACHE[key] = frozenset(_parse_package_imports(path))
    return _IMPORTS_CACHE[key]


#: instructions that may stand between an import's IMPORT_NAME and its IMPORT_FROMs (binding each name)
_BETWEEN_IMPORTS = frozenset({"STORE_NAME", "STORE_FAST", "STORE_GLOBAL", "STORE_DEREF", "POP_TOP", "IMPORT_STAR",
                              "EXTENDED_ARG", "CACHE"})


def _parse_package_imports(path: Path) -> set[str]:
    # From the compiled code, which the interpreter keeps in __pycache__ (read in about 2 ms, against 5 to 7 ms
    # to parse the source into a syntax tree; every Snakemake start walks 70 modules): each IMPORT_NAME of a
    # pipeline module, at any depth of the file, and after it the names its IMPORT_FROMs take from it
    # ("from pipeline.x import module"). The same names as the syntax tree's Import and ImportFrom nodes give,
    # checked on every module of the package.
    import dis
    import importlib.machinery

    code = importlib.machinery.SourceFileLoader("pipeline._scanned", str(path)).get_code("pipeline._scanned")
    out, todo = set(), [code]
    while todo:
        co = todo.pop()
        todo += [c for c in co.co_consts if hasattr(c, "co_code")]
        if not any(n.split(".")[0] == "pipeline" for n in co.co_names):
            continue
        module = None
        for ins in dis.get_instructions(co):
            if ins.opname == "IMPORT_NAME":
                module = ins.argval if ins.argval.split(".")[0] == "pipeline" else None
                if module:
                    out.add(module)
            elif ins.opname == "IMPORT_FROM" and module:
                out.add(f"{module}.{ins.argval}")
            elif ins.opname not in _BETWEEN_IMPORTS:
                module = None
    return out


def stage_code_modules(stage: str) -> list[str]:
    """The package's modules whose code a stage's job runs: its module and all it imports, transitively.

    Parameters
    ----------
    stage : str
        Name of a stage (its module ``pipeline.stages.<stage>``).

    Returns
    -------
    list of str
        Dotted module names, sorted, with this runner and the packages' ``__init__`` modules.
    """
    seen, todo = set(), [f"pipeline.stages.{stage}", "pipeline.runner.workflow"]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        path = _module_path(name)
        if path is None:
            continue
        seen.add(name)
        parts = name.split(".")
        # a module also runs its packages' __init__ (e.g. pipeline.effects registers the built-in effects)
        todo += [".".join(parts[:k]) for k in range(2, len(parts))]
        todo += sorted(_package_imports(path))
    return sorted(seen)


def stage_code_sha256(stage: str) -> str:
    """sha256 of the source of every module a stage runs: a rule's param, so a code change reruns it.

    Parameters
    ----------
    stage : str
        Name of a stage.

    Returns
    -------
    str
        Hex sha256 of the names and sources of :func:`stage_code_modules`.
    """
    h = hashlib.sha256()
    for name in stage_code_modules(stage):
        h.update(name.encode())
        h.update(_module_path(name).read_bytes())
    return h.hexdigest()


# --------------------------------------------------------------------------- the dataset index
class DatasetIndex:
    """A dataset validated once per workflow run: layout, checksums list, frames.csv and tags."""

    def __init__(self, root: str | Path, config: dict | None = None):
        self.root = Path(root)
        self.dataset: Dataset | None = None
        #: the run's field section (the reference's match-up window and clock search the check uses)
        self.field_settings = (config or {}).get("field")

    def load(self) -> "DatasetIndex":
        """Validate once (``pipeline.io.validation``); on problems print them grouped and raise InputError.

        Returns
        -------
        DatasetIndex
            ``self``, its ``dataset`` set.

        Raises
        ------
        pipeline.errors.InputError
            When the dataset has problems (listed on standard error).
        """
        if self.dataset is None:
            warnings = []
            dataset, problems = inspect_dataset(self.root, warnings=warnings, field_settings=self.field_settings)
            for line in grouped_warning_lines(warnings, self.root):
                print(line, file=sys.stderr)
            if problems:
                print(format_problems(problems, self.root), file=sys.stderr)
                raise InputError.from_problems(problems, "listed above")
            for line in warning_lines(unlisted_files(dataset)):
                print(line, file=sys.stderr)
            self.dataset = dataset
        return self

    def lenses(self) -> list[str]:
        """The lenses of the dataset.

        Returns
        -------
        list of str
            Lens names in the order of dataset.yaml.
        """
        return list(self.load().dataset.lenses)

    def stage_lenses(self, stage: str) -> list[str]:
        """The lenses a stage runs for: every lens, or those its frames.csv names (``lenses_from_frames``).

        Parameters
        ----------
        stage : str
            Name of a stage of :data:`STAGES`.

        Returns
        -------
        list of str
            Lens names.
        """
        lenses = self.lenses()
        spec = STAGES[stage]
        if not spec.lenses_from_frames or spec.experiment not in self.dataset.experiments():
            return lenses
        named = set(self.dataset.frames(spec.experiment)["lens"].astype(str))
        return lenses if "both" in named else [lens for lens in lenses if lens in named]

    def stage_runnable(self, stage: str) -> bool:
        """Whether the dataset has every experiment folder the stage reads.

        Parameters
        ----------
        stage : str
            Name of a stage of :data:`STAGES`.

        Returns
        -------
        bool
            True when all of :data:`STAGE_EXPERIMENTS` of the stage are present.
        """
        present = set(self.load().dataset.experiments())
        return all(exp in present for exp in STAGE_EXPERIMENTS[stage])

    def skipped(self) -> dict[str, str]:
        """The stages the dataset cannot run and why.

        Returns
        -------
        dict[str, str]
            Stage -> the reason (the experiment folders it lacks).
        """
        present = set(self.load().dataset.experiments())
        out = {}
        for stage, needs in STAGE_EXPERIMENTS.items():
            missing = [e for e in needs if e not in present]
            if missing:
                out[stage] = f"the dataset has no {', '.join(m + '/' for m in missing)} folder"
        return out

    def stage_files(self, stage: str) -> list[str]:
        """The experiment's files a stage reads: frames.csv, raw frames, sidecars (and DATASET_FILES at the root).

        Parameters
        ----------
        stage : str
            Name of a stage of :data:`STAGES`.

        Returns
        -------
        list of str
            Paths of the experiment's files (the root's DATASET_FILES are :meth:`layout_files`); empty when the
            dataset has no folder for the stage's experiment.
        """
        dataset = self.load().dataset
        spec = STAGES[stage]
        if spec.experiment not in dataset.experiments():
            return []
        folder = dataset.root / spec.experiment
        return ([str(folder / "frames.csv")]
                + [str(p) for p in dataset.raw_files(spec.experiment)]
                + [str(folder / name) for name in spec.sidecars])

    def dataset_subset(self, stage: str, lens: str) -> dict:
        """The part of dataset.yaml that the job of one lens reads (its rerun trigger).

        Parameters
        ----------
        stage : str
            Name of a stage of :data:`STAGES`.
        lens : str
            Name of the lens.

        Returns
        -------
        dict
            ``camera``, the lens's region under ``lens`` and the keys of the stage's ``reads_meta``, as plain JSON
            values with sorted keys.
        """
        meta = self.load().dataset.meta
        out = {"camera": meta.get("camera"), "lens": meta.get("lenses", {}).get(lens)}
        for key in STAGES[stage].reads_meta:
            out[key] = meta.get(key)
        return json.loads(json.dumps(out, sort_keys=True, default=str))   # key order of the file does not matter

    def job_memory_mb(self, stage: str, lens: str, attempt: int = 1) -> int:
        """Memory to ask a scheduler for, for the job of one stage and lens (see JOB_MEMORY_*).

        Parameters
        ----------
        stage : str
            Name of a stage of :data:`STAGES`.
        lens : str
            Name of the lens (its region's size sets the band pixels).
        attempt : int, default 1
            The job's attempt; each retry asks for that many times more.

        Returns
        -------
        int
            Memory in MB (10^6 bytes), rounded up.
        """
        (r0, r1), (c0, c1) = self.load().dataset.lenses[lens]
        band_pixels = (r1 - r0) * (c1 - c0) / 4
        mib = JOB_MEMORY_FIXED_MIB + JOB_MEMORY_BYTES_PER_BAND_PIXEL[stage] * band_pixels / 2**20
        return int(np.ceil(JOB_MEMORY_HEADROOM * attempt * mib * 1.048576))

    def layout_files(self) -> list[str]:
        """dataset.yaml and MD5SUMS: read by every stage.

        Returns
        -------
        list of str
            Their paths.
        """
        return [str(self.load().dataset.root / name) for name in DATASET_FILES]

    def lens_files(self, stage: str, lens: str) -> list[str]:
        """The files of :meth:`stage_files` that the job of one lens reads.

        Parameters
        ----------
        stage : str
            Name of a stage of :data:`STAGES`.
        lens : str
            Name of the lens.

        Returns
        -------
        list of str
            Paths: frames.csv, the sidecars and the raw frames of that lens or of both.
        """
        dataset = self.load().dataset
        spec = STAGES[stage]
        if spec.experiment not in dataset.experiments():
            return []
        raws = set(str(p) for p in lens_view(dataset, lens).raw_files(spec.experiment))
        every = set(str(p) for p in dataset.raw_files(spec.experiment))
        return [f for f in self.stage_files(stage) if f not in every or f in raws]


# --------------------------------------------------------------------------- the scripts' entry point
def artefacts_by_lens(paths) -> dict[str, str]:
    """Artefact paths of one stage (``results/<stage>/<lens>.nc``) keyed by lens.

    Parameters
    ----------
    paths : str, pathlib.Path or iterable of them
        One artefact path or several.

    Returns
    -------
    dict[str, str]
        Lens (the file's stem) -> path.
    """
    paths = [paths] if isinstance(paths, (str, Path)) else list(paths)
    return {Path(p).stem: str(p) for p in paths}


def run_stage_script(smk, stage: str) -> None:
    """Entry point of the thin stage scripts: one stage, one lens (the rule's ``{lens}`` wildcard).

    Exits with the message of an InputError (:func:`pipeline.entry.exit_on_input_error`).

    Parameters
    ----------
    smk : snakemake.script.Snakemake
        The ``snakemake`` object of the rule's script: ``input`` (upstream artefacts by stage name,
        ``calibration``), ``output.artefact``, ``params.dataset``, ``params.config``, ``wildcards.lens`` and
        ``log``.
    stage : str
        Name of a stage of :data:`STAGES`.
    """
    setup_log(smk.log[0] if smk.log else None)
    lens = smk.wildcards.lens
    upstream = {name: {lens: smk.input[name]} for name in STAGES[stage].upstream + STAGES[stage].optional_upstream
                if name in smk.input.keys()}
    bundle = smk.input["calibration"] if "calibration" in smk.input.keys() else None
    # the workflow's start-up check (common.smk: DatasetIndex.load) ran validate's checks on this folder
    # before it scheduled any job
    exit_on_input_error(run_stage, stage, smk.params.dataset, smk.params.config, {lens: smk.output.artefact},
                        upstream, bundle=bundle, checked=True)


# --------------------------------------------------------------------------- what to simulate
def dataset_to_simulate(config: dict) -> bool:
    """Whether the workflow must simulate the dataset folder first.

    Only the configured default simulated dataset (``simulate_if_missing.path``)
    is simulated when absent, or any folder with ``simulate: true``. A folder a
    user named that does not exist is an error before any job runs, so a
    mistyped or unmounted path never yields a report of a simulated camera.

    Parameters
    ----------
    config : dict
        The run's configuration (``dataset``, ``simulate_if_missing``, optional ``simulate``).

    Returns
    -------
    bool
        True when the dataset folder is absent and is to be simulated; False when it exists.

    Raises
    ------
    pipeline.errors.InputError
        When the folder does not exist and is not to be simulated.
    """
    path = Path(config["dataset"])
    if path.exists():
        return False
    default = config["simulate_if_missing"]
    asked = str(config.get("simulate", False)).lower() == "true"     # --config simulate=true gives a string
    if asked or (default["enabled"] and path.resolve() == Path(default["path"]).resolve()):
        return True
    raise InputError(path, "dataset folder not found (check the path; to simulate a dataset into it, "
                           "add --config simulate=true)")


# --------------------------------------------------------------------------- an interrupted run
class SignalWatch:
    """Notes the signal that interrupts a run (Ctrl-C's SIGINT, a scheduler's SIGTERM), then lets the
    handler that was there act on it: Snakemake's own (a KeyboardInterrupt for SIGINT that cancels the
    running jobs; for SIGTERM, the scheduler's "exit after finishing the running jobs").

    Snakemake calls the workflow's ``onerror`` for an interrupted run as for one whose job failed; the
    handler asks :meth:`exit_if_interrupted` first, so that an interrupt ends the run with 128 + the
    signal's number and one line, without the failed-run report or an entry in the error history.
    """

    def __init__(self):
        self.signals: list[int] = []

    def watch(self, *signums: int) -> None:
        """Note each of ``signums`` from now on, before the handler installed so far acts.

        Snakemake's scheduler installs its SIGTERM handler when it starts: watch SIGTERM from ``onstart``.
        Outside the main thread nothing is installed.

        Parameters
        ----------
        *signums : int
            Signal numbers (``signal.SIGINT``, ``signal.SIGTERM``).
        """
        for signum in signums:
            previous = signal.getsignal(signum)

            def handler(number, frame, previous=previous):
                self.signals.append(number)
                if callable(previous):
                    return previous(number, frame)
                if previous == signal.SIG_IGN:
                    return None
                raise SystemExit(128 + number)      # SIG_DFL: end as the signal would

            try:
                signal.signal(signum, handler)
            except ValueError:      # not the main thread (a job run inside the scheduler's process)
                pass

    def exit_if_interrupted(self) -> None:
        """After a failed run: when a watched signal came, one line and exit 128 + its number."""
        if not self.signals:
            return
        number = self.signals[0]
        print(f"interrupted ({signal.Signals(number).name}): the run stopped; the jobs that did not finish left "
              "no artefact; the same command resumes the run", file=sys.stderr)
        sys.exit(128 + number)
