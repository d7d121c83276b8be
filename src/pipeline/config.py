"""Configuration: the JSON schema ``schema.yaml`` of this package validates and fills defaults."""

from __future__ import annotations

import copy
from functools import lru_cache
from importlib.resources import files
from pathlib import Path

import yaml
from jsonschema import Draft202012Validator, validators

from pipeline.errors import InputError
from pipeline.yamlio import DuplicateKey, load_yaml

#: the configuration's JSON schema: package data (src/pipeline/schema.yaml), so that an installed package
#: has it too; a package installed from a wheel lies in files on disk, for which importlib.resources gives
#: a pathlib.Path (its modification time keys the cached defaults, its path names the schema in errors)
SCHEMA_PATH: Path = files(__package__).joinpath("schema.yaml")


def _source_checkout() -> Path | None:
    """The source checkout this package is imported from (its ``src/pipeline``), None for an installed package."""
    package = Path(__file__).resolve().parent
    root = package.parents[1]
    return root if package.parent.name == "src" and (root / "pyproject.toml").is_file() else None


REPO_ROOT = _source_checkout()
#: the workflow's configuration, which the commands that read settings (compare, store, publish, the
#: report) use too; None for an installed package, which has no checkout: the schema's defaults then
CONFIG_PATH = REPO_ROOT / "config" / "config.yaml" if REPO_ROOT is not None else None
#: the configuration of no dataset (the one key the schema requires): what the schema's defaults fill
_NO_DATASET = {"dataset": "unused"}


def _with_defaults(cls):
    validate_properties = cls.VALIDATORS["properties"]

    def set_defaults(validator, properties, instance, schema):
        if isinstance(instance, dict):
            for name, sub in properties.items():
                if "default" in sub and name not in instance:
                    instance[name] = _copy(sub["default"])
        yield from validate_properties(validator, properties, instance, schema)

    return validators.extend(cls, {"properties": set_defaults})


def _copy(value):
    # the schema's defaults are plain YAML data (dicts, lists, numbers, strings)
    return copy.deepcopy(value)


def unknown_keys(config, schema: dict, where: str = "") -> list[tuple[str, list[str]]]:
    """Keys of ``config`` that the schema does not know, as (dotted path, the known keys there).

    Only where the schema lists an object's ``properties`` (and does not allow others with
    ``additionalProperties`` or ``patternProperties``); lists are followed through ``items``. A
    misspelt key would otherwise be ignored and its default used without a word.

    Parameters
    ----------
    config : object
        A configuration or a part of it (dict, list or value).
    schema : dict
        The JSON schema of that part.
    where : str, optional
        The dotted path of ``config`` in the whole configuration (prefix of the paths returned); default ''.

    Returns
    -------
    list of tuple of (str, list of str)
        For each unknown key, its dotted path (list items as ``[i]``) and the sorted keys the schema knows there.
    """
    found = []
    if isinstance(config, dict) and isinstance(schema.get("properties"), dict):
        props = schema["properties"]
        open_ended = schema.get("additionalProperties", False) not in (False, None) or "patternProperties" in schema
        for key, value in config.items():
            path = f"{where}.{key}" if where else str(key)
            if key in props:
                found += unknown_keys(value, props[key], path)
            elif not open_ended:
                found.append((path, sorted(props)))
    elif isinstance(config, list) and isinstance(schema.get("items"), dict):
        for i, value in enumerate(config):
            found += unknown_keys(value, schema["items"], f"{where}[{i}]")
    return found


#: the YAML safe loader, in C (libyaml) where PyYAML has it: the same documents, about ten times faster
#: (the schema's parse was most of apply's start-up)
_SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _read_yaml(path: str | Path):
    return yaml.load(Path(path).read_text(), Loader=_SAFE_LOADER)  # noqa: S506 (a safe loader)


def read_config_file(path: str | Path):
    """A config file (config/config.yaml, a ``--configfile``) as parsed.

    A key written twice in one mapping is refused: YAML, and Snakemake's reader of it, keep the last without a
    word, so a threshold edited below an old copy of its section would be ignored.

    Parameters
    ----------
    path : str or pathlib.Path
        The config file (UTF-8, with or without a byte-order mark).

    Returns
    -------
    object
        The parsed document (a dict for a configuration; None for an empty file).

    Raises
    ------
    InputError
        Naming the file, when it cannot be read, when it does not parse (with the line) or when a key appears
        twice in one mapping (with both lines).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read the config file ({getattr(exc, 'strerror', None) or exc})") from None
    try:
        return load_yaml(text)
    except DuplicateKey as dup:
        raise InputError(path, f"line {dup.line}: key {dup.key!r} appears twice (first on line {dup.first_line}); "
                               "keep one of the two (YAML would silently use the last)") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        raise InputError(path, f"{where}not valid YAML ({getattr(exc, 'problem', None) or 'invalid YAML'})") from None


_TEXT_TYPES = {"integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
               "number": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
               "boolean": lambda v: isinstance(v, bool), "null": lambda v: v is None}


def values_from_text(config, schema: dict):
    """``config`` with the text of a number, boolean or null read as one where the schema wants one.

    Snakemake reads a ``--config key={a: 0, b: 0.5}`` override's nested values as text (its YAML base
    loader), so ``performance={decode_ahead_frames: 0}`` would arrive as the string '0' and be refused;
    the text is read with YAML where the schema's type for that key is not a string and the reading has
    that type (anything else is left for the validator to name).

    Parameters
    ----------
    config : object
        A configuration or a part of it (dict, list or value).
    schema : dict
        The JSON schema of that part.

    Returns
    -------
    object
        A copy of ``config`` (new dicts and lists) with such text replaced by the value it reads as.
    """
    if isinstance(config, dict):
        props = schema.get("properties", {})
        return {k: values_from_text(v, props[k]) if k in props else v for k, v in config.items()}
    if isinstance(config, list) and isinstance(schema.get("items"), dict):
        return [values_from_text(v, schema["items"]) for v in config]
    wanted = schema.get("type")
    wanted = wanted if isinstance(wanted, list) else [wanted]
    if isinstance(config, str) and "string" not in wanted and any(t in _TEXT_TYPES for t in wanted):
        try:
            value = yaml.safe_load(config)
        except yaml.YAMLError:
            return config
        if any(_TEXT_TYPES[t](value) for t in wanted if t in _TEXT_TYPES):
            return value
    return config


_RANGE_KEYWORDS = ("minimum", "exclusiveMinimum", "maximum", "exclusiveMaximum")


def range_text(schema: dict) -> str:
    """A number's range as the schema gives it, in interval notation: ``[1, 100]``, ``(0, 90]``, ``[0, inf)``.

    Parameters
    ----------
    schema : dict
        The schema of one number, with any of ``minimum``, ``exclusiveMinimum``, ``maximum``, ``exclusiveMaximum``.

    Returns
    -------
    str
        The interval; an open side without a bound is ``-inf`` or ``inf``.
    """
    if "exclusiveMinimum" in schema:
        low = f"({schema['exclusiveMinimum']}"
    else:
        low = f"[{schema['minimum']}" if "minimum" in schema else "(-inf"
    if "exclusiveMaximum" in schema:
        high = f"{schema['exclusiveMaximum']})"
    else:
        high = f"{schema['maximum']}]" if "maximum" in schema else "inf)"
    return f"{low}, {high}"


def validate_config(config: dict, schema_path: str | Path = SCHEMA_PATH) -> dict:
    """Validate ``config`` in place, filling defaults.

    A key the schema does not know is an error (see :func:`unknown_keys`). Numbers, booleans and nulls given as
    text where the schema wants them (Snakemake's ``--config`` overrides) are read first
    (:func:`values_from_text`).

    Parameters
    ----------
    config : dict
        The configuration; updated in place.
    schema_path : str or pathlib.Path, optional
        The JSON schema (YAML); default the package's ``schema.yaml`` (:data:`SCHEMA_PATH`).

    Returns
    -------
    dict
        ``config`` itself, validated and with every default the schema gives filled in.

    Raises
    ------
    InputError
        Naming the schema file and the first problem: an unknown key (with the keys known there), a value of the
        wrong type, or a number outside its range (in interval notation, :func:`range_text`).
    """
    schema = _read_yaml(schema_path)
    config.update(values_from_text(config, schema))
    unknown = unknown_keys(config, schema)
    if unknown:
        path, known = unknown[0]
        more = f" ({len(unknown) - 1} more unknown)" if len(unknown) > 1 else ""
        raise InputError(schema_path, f"config {path}: unknown key; known there: {', '.join(known)}{more}")
    validator = _with_defaults(Draft202012Validator)(schema)
    # two passes: defaults of nested objects created by the first pass get filled by the second
    for _ in range(2):
        errors = sorted(validator.iter_errors(config), key=lambda e: list(e.path))
        if errors:
            err = errors[0]
            where = ".".join(str(p) for p in err.path) or "(top level)"
            message = err.message
            if err.validator in _RANGE_KEYWORDS and isinstance(err.schema, dict):
                message = f"{err.instance!r} is outside its range {range_text(err.schema)}"
            raise InputError(schema_path, f"config {where}: {message}")
    return config


def load_config(path: str | Path | None = CONFIG_PATH, overrides: dict | None = None) -> dict:
    """Read a config file, apply ``overrides`` (nested dicts merge), validate, fill defaults.

    Parameters
    ----------
    path : str or pathlib.Path or None, optional
        The config file; default the checkout's ``config/config.yaml`` (:data:`CONFIG_PATH`). None (the default
        of an installed package, which has no config/config.yaml): the schema's defaults alone, with the overrides.
    overrides : dict, optional
        Top-level sections or keys to set: a dict given for a section that is a dict in the file updates that
        section's keys (one level deep), anything else replaces the value. Default none.

    Returns
    -------
    dict
        The validated configuration with defaults filled (:func:`validate_config`).

    Raises
    ------
    InputError
        When the file cannot be read or parsed (:func:`read_config_file`) or the configuration is not valid.
    """
    config = (read_config_file(path) or {}) if path is not None else dict(_NO_DATASET)
    for key, value in (overrides or {}).items():
        if isinstance(value, dict) and isinstance(config.get(key), dict):
            config[key] = {**config[key], **value}
        else:
            config[key] = value
    return validate_config(config)


def defaults() -> dict:
    """The schema's defaults alone (what a stage uses when a config omits a key); a fresh copy each call.

    Returns
    -------
    dict
        The configuration that the schema's defaults make (computed once per version of the schema file).
    """
    return copy.deepcopy(_defaults(SCHEMA_PATH.stat().st_mtime_ns))


@lru_cache(maxsize=1)
def _defaults(schema_mtime_ns: int) -> dict:
    """The validated defaults, once per version of the schema file (its modification time)."""
    return validate_config(dict(_NO_DATASET))


#: config sections each rule depends on (its params rerun trigger); ``performance`` (how many frames are
#: decoded ahead) goes to every stage that decodes frames, since the job reads it from its params
STAGE_SECTIONS = {
    "dark": ("model", "bias", "dark", "performance"),
    "linearity": ("model", "bias", "linearity", "performance"),
    "geometry": ("model", "bias", "geometry", "performance"),
    "rolloff": ("model", "bias", "rolloff", "performance"),
    "spectral": ("model", "bias", "spectral", "performance"),
    "absolute": ("model", "bias", "absolute", "performance"),
    "immersion": ("model", "bias", "immersion", "performance"),
    "diagnostics": ("model", "diagnostics", "plausibility"),
    # apply: the bundle stores every pixel's cell on the default sphere grid (apply.grid_deg)
    "calibration": ("model", "calibration", "apply"),
    "field": ("model", "apply", "field", "performance"),
}


def stage_params(config: dict, stage: str) -> dict:
    """The subset of the configuration a rule uses, so that its params trigger reruns precisely.

    Parameters
    ----------
    config : dict
        The validated configuration.
    stage : str
        A rule's name, a key of :data:`STAGE_SECTIONS` (``dark``, ``linearity``, ..., ``field``).

    Returns
    -------
    dict
        The configuration's sections that this rule reads (those of ``STAGE_SECTIONS[stage]`` present).
    """
    return {key: config[key] for key in STAGE_SECTIONS[stage] if key in config}
