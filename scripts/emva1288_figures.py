"""The EMVA1288 Reference Set 001 through the dark and linearity stages: its figures against the reference, as CSV.

    PYTHONPATH=src python scripts/emva1288_figures.py $PIPELINE_REALDATA/emva1288-set001/EMVA1288_Data.txt \\
        docs/figures-data/emva1288_set001.csv

Lays the set out in a temporary folder (pipeline.scaffold.init_emva1288_dataset), runs the dark stage with the
default model and with bias_drift added, and the linearity stage with bias_drift (and once more with the bend of
the response, a shutter offset and the pixel response pattern modelled: nonlinearity, shutter_offset, prnu), takes
DSNU1288 and PRNU1288 from the 50-frame stacks (pipeline.radiometry.emva1288.spatial_nonuniformity on the DNGs, and
the stages' own),
and writes one row per figure (reference values of the set's SOURCES.md) with the machine, date, commit and
command. Per-band figures are averaged over the raw sites (R, G, G, B), as the temporal dark noise is.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from collections import Counter
from datetime import date
from pathlib import Path

import numpy as np
import pandas as pd
import xarray as xr

from pipeline.config import load_config
from pipeline.radiometry.emva1288 import spatial_nonuniformity
from pipeline.io.rawio import read_raw
from pipeline.scaffold import init_emva1288_dataset, read_emva1288_descriptor
from pipeline.runner.workflow import run_stage

LENS = "main"
CAMERA = {"make": "Basler", "model": "EMVA1288 Reference Set 001", "serial": "EMVA1288-SET001"}
MODEL = ["dark_current", "hot_pixels"]
#: the linearity residuals' structure modelled: the bend of the response, a shutter offset, the pixel response pattern
BEND = ["nonlinearity", "shutter_offset", "prnu"]
REF_K = 0.280769


def _machine() -> str:
    mem_gb = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return f"{os.cpu_count()} cores, {mem_gb:.0f} GB"


def _stages(descriptor: Path, work: Path) -> dict[str, xr.Dataset]:
    result = init_emva1288_dataset(descriptor, work / "raw", work / "dataset", **CAMERA)
    config, out = load_config(), {}
    for name, effects in (("dark", MODEL), ("dark_drift", MODEL + ["bias_drift"])):
        cfg = {**config, "model": {**config["model"], "effects": effects}}
        out[name] = run_stage("dark", result.out, cfg, {LENS: work / f"{name}.nc"})[LENS]
    out["linearity"] = run_stage("linearity", result.out, cfg, {LENS: work / "linearity.nc"},
                                 {"dark": {LENS: work / "dark_drift.nc"}})[LENS]
    cfg_bend = {**config, "model": {**config["model"], "effects": MODEL + ["bias_drift"] + BEND}}
    out["linearity_bend"] = run_stage("linearity", result.out, cfg_bend, {LENS: work / "linearity_bend.nc"},
                                      {"dark": {LENS: work / "dark_drift.nc"}})[LENS]
    stacks = {}
    frames = read_emva1288_descriptor(descriptor)[2]
    for kind, folder in (("signal", "linearity"), ("dark", "dark")):
        step = max(f.step for f in frames if f.kind == kind)
        stack = np.stack([read_raw(result.out / folder / "raw" / f"{f.image.stem}.dng", checksums=False).cfa
                          for f in frames if f.kind == kind and f.step == step]).astype(np.float64)
        stacks[kind] = (stack.mean(axis=0), stack.var(axis=0, ddof=1), len(stack))
    out["spatial"] = spatial_nonuniformity(*stacks["signal"], *stacks["dark"])
    return out


def _sites(values) -> float:
    """A per-band figure (R, G, B) averaged over the raw sites R, G, G, B."""
    r, g, b = (float(v) for v in values)
    return (r + 2 * g + b) / 4


def figures(descriptor: Path) -> list[dict]:
    with tempfile.TemporaryDirectory() as tmp:
        a = _stages(descriptor, Path(tmp))
        lin, dark, drift = a["linearity"], a["dark"], a["dark_drift"]
        read = drift["read_noise_dn"].sel(band=["R", "G", "B"]).values[:, 0]
        per_site = float(np.sqrt((read[0] ** 2 + 2 * read[1] ** 2 + read[2] ** 2) / 4))
        st = lin["obs_setting__exposure_s"].values[lin["obs_setting__saturated"].values == 1]
        # the bright steps' exposures (blocks of two frames; the 50-frame stack is not a step)
        blocks = Counter((f.step, round(f.exposure_s, 9)) for f in read_emva1288_descriptor(descriptor)[2]
                         if f.kind == "signal")
        steps = np.array(sorted(t for (_, t), n in blocks.items() if n == 2))
        first_saturated = int(np.searchsorted(steps, round(float(st.min()), 9))) if st.size else -1
        effects = " ".join(MODEL + ["bias_drift"])
        rows = [
            ("conversion gain", "DN/e-", REF_K, float(lin["conversion_gain_dn_per_e"]),
             float(lin["conversion_gain_dn_per_e_sigma"]), 3.0, effects),
            ("read noise", "e-", 10.9, float(lin["read_noise_e"]), float(lin["read_noise_e_sigma"]), 5.0, effects),
            ("temporal dark noise (raw sites of R, G, G, B)", "DN", 3.07342, per_site, np.nan, 5.0, effects),
            ("last unsaturated step (counted from 0)", "step", 36, first_saturated - 1, np.nan, 0.0, effects),
            ("dark current", "DN/s", 28.41 * REF_K, float(drift["dark_current_dn_per_s"]),
             float(drift["dark_current_dn_per_s_sigma"]), np.nan, effects),
            ("dark current", "DN/s", 28.41 * REF_K, float(dark["dark_current_dn_per_s"]),
             float(dark["dark_current_dn_per_s_sigma"]), np.nan, " ".join(MODEL)),
            ("bias drift (frame-to-frame black-level spread per band)", "DN", np.nan, float(drift["bias_drift_dn"]),
             np.nan, np.nan, effects),
            ("dark table rms z", "1", 1.0, float(drift["rms_z"]), np.nan, np.nan, effects),
            ("dark table rms z", "1", 1.0, float(dark["rms_z"]), np.nan, np.nan, " ".join(MODEL)),
            ("linearity table rms z", "1", 1.0, float(lin["rms_z"]), np.nan, np.nan, effects),
        ]
        bend = a["linearity_bend"]
        bend_effects = " ".join(MODEL + ["bias_drift"] + BEND)
        for ds, model in ((lin, effects), (bend, bend_effects)):
            rows += [(f"linearity rms z, {what} table", "1", 1.0, float(ds["rms_z"].attrs[f"{what}_table"]), np.nan,
                      np.nan, model) for what in ("setting", "frame", "flat")]
        rows += [
            ("linearity table rms z", "1", 1.0, float(bend["rms_z"]), np.nan, np.nan, bend_effects),
            ("conversion gain", "DN/e-", REF_K, float(bend["conversion_gain_dn_per_e"]),
             float(bend["conversion_gain_dn_per_e_sigma"]), np.nan, bend_effects),
            ("nonlinearity beta (relative bend at full scale)", "1", np.nan,
             float(bend["effect_nonlinearity"].values[0]), float(bend["effect_nonlinearity_sigma"].values[0]),
             np.nan, bend_effects),
            ("flat-field prnu (pattern left after the smooth surface)", "%", np.nan,
             100 * float(np.sqrt(bend["effect_prnu"].values[0])), np.nan, np.nan, bend_effects),
        ]
        band = {name: _sites(lin[name].sel(band=["R", "G", "B"]).values) for name in (
            "responsivity_dn_per_photon", "quantum_efficiency", "saturation_capacity_e", "dynamic_range",
            "dynamic_range_db", "snr_max", "linearity_error_min_pct", "linearity_error_max_pct")}
        rows += [
            ("responsivity (mean of the raw sites' bands)", "DN/photon", 0.126727, band["responsivity_dn_per_photon"],
             np.nan, 1.0, effects),
            ("quantum efficiency (mean of the raw sites' bands)", "1", 0.4514, band["quantum_efficiency"], np.nan, 4.0,
             effects),
            ("saturation capacity (mean of the raw sites' bands)", "e-", 13972.6, band["saturation_capacity_e"],
             np.nan, 4.0, effects),
            ("dynamic range (mean of the raw sites' bands)", "1", 1220.7, band["dynamic_range"], np.nan, 6.1,
             effects),
            ("dynamic range (mean of the raw sites' bands)", "dB", float(20 * np.log10(1220.7)),
             band["dynamic_range_db"], np.nan, np.nan, effects),
            ("SNR_max (mean of the raw sites' bands)", "1", 118.2, band["snr_max"], np.nan, 2.0, effects),
            ("linearity error LE_min (mean of the raw sites' bands; tolerance 0.2 percentage point)", "%", -0.616,
             band["linearity_error_min_pct"], np.nan, np.nan, effects),
            ("linearity error LE_max (mean of the raw sites' bands; tolerance 0.2 percentage point)", "%", 0.480,
             band["linearity_error_max_pct"], np.nan, np.nan, effects),
            ("DSNU1288 (50-frame dark stack, radiometry function)", "DN", 0.155, a["spatial"].dsnu_dn, np.nan, 1.0,
             "none (the stacks' raw values)"),
            ("DSNU1288 (dark stage, mean of the raw sites' bands)", "DN", 0.155,
             _sites(drift["dsnu1288_dn"].sel(band=["R", "G", "B"]).values), np.nan, 15.0, effects),
            ("PRNU1288 (linearity stage, photon-transfer region, R and B bands' mean)", "%", 0.433,
             float(lin["prnu1288_pct"].sel(band=["R", "B"]).mean()), np.nan, np.nan, effects),
            ("PRNU1288 (50-frame stacks, radiometry function)", "%", 0.433, a["spatial"].prnu_pct, np.nan, 1.0,
             "none (the stacks' raw values)"),
        ]
    out = []
    for quantity, unit, ref, value, sigma, tol, model in rows:
        relative = unit not in ("step", "1") or not quantity.startswith(("linearity", "dark table"))
        if quantity.startswith("linearity error"):
            relative = False    # a percentage's difference is read in percentage points, not relative
        diff = 100.0 * (value / ref - 1.0) if relative and unit != "step" and np.isfinite(ref) else np.nan
        out.append({"quantity": quantity, "unit": unit, "reference": ref, "measured": value, "measured_sigma": sigma,
                    "difference_percent": diff, "tolerance_percent": tol, "model_effects": model})
    return out


def main(descriptor: str, csv_path: str) -> None:
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    command = "PYTHONPATH=src python scripts/emva1288_figures.py " + " ".join(sys.argv[1:])
    meta = {"machine": _machine(), "date": date.today().isoformat(), "commit": commit, "command": command}
    # the descriptor may be given as written in the docs, with $PIPELINE_REALDATA unexpanded
    rows = figures(Path(os.path.expandvars(descriptor)))
    pd.DataFrame([{**meta, **row} for row in rows]).to_csv(csv_path, index=False)


if __name__ == "__main__":
    main(*sys.argv[1:3])
