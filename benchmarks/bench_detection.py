"""How well the diagnostics find a missing effect: top-1 accuracy, false alarms, detectable amplitude.

    python benchmarks/bench_detection.py [--effects dark_current,nonlinearity_tanh,...] [--magnitudes clear,limit]
                                         [--pairs dark_current+shutter_offset,...] [--clean N] [--work DIR]

On the tiny simulated camera (the dark and linearity experiments, the foundation stages; the roll-off
experiment, on the simulator's true geometry with exact field angles, for the roll-off's effects), for:

* each catalogue effect of those stages, simulated in the simulator's own form at two magnitudes: a
  clear one (the hidden-effect tests' values) and one near the tiny dataset's detection limit;
* the alternative forms of ``tests/support/effect_forms.py`` (forms the package does not use), injected into
  the raw files of a clean dataset, at their two magnitudes;
* pairs of effects, which the diagnostics' forward selection must find one after the other;
* ``--clean N`` clean datasets (default 20) with the simulator's realistic lab noise (source flicker and
  drift, bias jitter, room-temperature drift), with ``bias_drift`` in the model as the README says a lab
  with that noise should have it.

For every case it runs the dark and linearity stages with the base model, ranks the missing effects,
then adds the named effect(s) and runs them again. It prints one line per case (top-ranked effect,
significance, p-value, the amplitude found and the smallest detectable one against the injected one,
rms_z before and after adding, the noise floor 1 + 2 sqrt(2/dof); for a pair, the effects forward
selection accepted in turn and the second effect's rank, injected, found and detectable amplitude and
p-value) and a summary: top-1 accuracy (clear and near-limit apart), the false-alarm rate on clean data,
and how often the error falls back to the floor; for the clean datasets also the tables the residual tests
report as structured (false alarms of those tests), the covariate scan's smallest p and how often it names
the signal level. ``--effects`` takes catalogue names and form names; ``--magnitudes clear`` runs one magnitude;
``--pairs ''`` and ``--clean 0`` skip those parts; ``--clean-seeds 311,303`` runs those clean seeds instead of
``--clean N``'s 300 to 300 + N - 1, and ``--lab-noise bias_dn_per_room_c=0`` changes the named sizes of the
lab noise (:class:`pipeline.simulate.lab_noise.LabNoise`) from their defaults. Each case is simulated with its own seed, in a
temporary folder removed after it (``--work`` to keep them elsewhere). A benchmark, not a test: nothing
here is asserted. The run appends its rows to ``benchmarks/results/`` (``benchmarks/record.py``), under one run
name: one per case to ``bench_detection.csv``, the summary to ``bench_detection_summary.csv``, its CPU and wall
time and the load average to ``bench_detection_runs.csv``; ``docs/effects-and-diagnostics.md`` renders them.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import yaml

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests" / "support"))

from effect_forms import FORMS  # noqa: E402
from pipeline.config import load_config  # noqa: E402
from pipeline.io.dataset import open_dataset  # noqa: E402
from pipeline.diagnostics.tables import observations_from_artefacts  # noqa: E402
from pipeline.diagnostics.missing_effects import error_figures, rank_missing_effects  # noqa: E402
from pipeline.simulate import simulate_dataset, truth_dir_for  # noqa: E402
from pipeline.simulate.lab_noise import LabNoise  # noqa: E402
from pipeline.stages.dark import analyse_dark, reduce_dark  # noqa: E402
from pipeline.stages.linearity import analyse_linearity, reduce_linearity  # noqa: E402
from pipeline.stages.rolloff import analyse_rolloff, reduce_rolloff  # noqa: E402

#: the simulator's own forms: (clear, near the tiny dataset's detection limit). The clear values are the
#: hidden-effect tests'; the near-limit ones sit at one to two times the detectable amplitude the
#: diagnostics report for that effect on a clean tiny dataset.
MAGNITUDES = {
    "dark_current": ({"rate_e_per_s": 1.3}, {"rate_e_per_s": 0.06}),
    "hot_pixels": ({"fraction": 8e-4, "median_rate_e_per_s": 300.0}, {"fraction": 1e-4, "median_rate_e_per_s": 100.0}),
    "shutter_offset": ({"offset_s": 6e-4}, {"offset_s": 3e-4}),
    "nonlinearity": ({"beta": 0.04}, {"beta": 0.015}),
    "iso_gain": ({"rel_sigma": 0.025}, {"rel_sigma": 0.012}),
    "prnu": ({"sigma_rel": 0.015}, {"sigma_rel": 0.004}),
    "temperature": ({"bias_dn_per_c": 0.4, "dark_doubling_c": 6.0}, {"bias_dn_per_c": 0.04, "dark_doubling_c": 6.0}),
    "bias_drift": ({"sigma_dn": 2.5}, {"sigma_dn": 0.3}),
    "stray_light": ({"fraction": 0.01}, {"fraction": 1e-4}),
    "rolloff_azimuth": ({"amplitude": 0.02, "phi0_deg": 50.0}, {"amplitude": 0.003, "phi0_deg": 50.0}),
}
#: effects seen in the roll-off experiment (the others in dark and linearity)
ROLLOFF_EFFECTS = ("stray_light", "rolloff_azimuth")
DEFAULT_PAIRS = ("dark_current+shutter_offset", "nonlinearity+prnu", "hot_pixels+iso_gain",
                 "temperature+shutter_offset")
LEVELS = {"clear": 0, "limit": 1}


def injected_amplitude(effect: str, params: dict, truth: dict) -> float:
    """The injected size in the diagnostics' amplitude units (missing_effects.csv ``units``)."""
    k100 = truth["derived"]["conversion_gain_dn_per_e_iso100"]
    t = truth["effects"][effect]
    if effect == "dark_current":
        return params["rate_e_per_s"] * k100
    if effect == "iso_gain":
        errors = [v - 1.0 for v in t["factors"].values()]
        return float(errors[int(np.argmax(np.abs(errors)))])
    key = {"hot_pixels": "fraction", "shutter_offset": "offset_s", "nonlinearity": "beta", "prnu": "sigma_rel",
           "temperature": "bias_dn_per_c", "bias_drift": "sigma_dn", "stray_light": "fraction",
           "rolloff_azimuth": "amplitude"}[effect]
    return float(params[key])


def analyse(root: Path, config: dict, model: list[str], experiments=("dark", "linearity")):
    ds = open_dataset(root)
    if experiments == ("rolloff",):
        from helpers import true_geometry_dataset

        config = {**config, "rolloff": {**config["rolloff"], "field_angle_sigma_px": 0.0}}
        band_px = int(np.diff(ds.meta["lenses"]["far"]["rows"])[0]) // 2
        geo = {lens: true_geometry_dataset(lens, band_px) for lens in ("far", "close")}
        arts = analyse_rolloff(reduce_rolloff(ds, geo, config), config, model)
        obs = observations_from_artefacts({"rolloff": list(arts.values())})
        ranked, unexplained, tests = rank_missing_effects(obs, model, config, with_tests=True)
        return ranked, unexplained, error_figures(obs, model), tests
    dark = analyse_dark(reduce_dark(ds, config), config, model)
    lin = analyse_linearity(reduce_linearity(ds, dark, config, model), dark, config, model)
    obs = observations_from_artefacts({"dark": list(dark.values()), "linearity": list(lin.values())})
    ranked, unexplained, tests = rank_missing_effects(obs, model, config, with_tests=True)
    return ranked, unexplained, error_figures(obs, model), tests


def shared_tables(tests) -> list[str]:
    """The tables above their stated noise whose excess the block-robust test leaves to the blocks' shared
    noise: said by the diagnostics (``shared_excess``), not reported as structure."""
    return [f"{t.experiment}/{t.level}" for t in tests[tests["shared_excess"].astype(bool)].itertuples()]


def floor_of(figures) -> np.ndarray:
    return 1.0 + 2.0 * np.sqrt(2.0 / figures["dof"].to_numpy())


def run_case(work: Path, config: dict, seed: int, expected: list[str], sim_effects=(), form=None,
             amplitude=None, lab_noise=False, base_model=(), experiments=("dark", "linearity")) -> dict:
    """Simulate (and rewrite), diagnose with the base model, add the expected effects, diagnose again."""
    root = work / f"case{seed}" / "dataset"
    root.parent.mkdir(parents=True)
    try:
        simulate_dataset(root, scale="tiny", seed=seed, effects=list(sim_effects), experiments=experiments,
                         progress=False, lab_noise=lab_noise)
        truth = yaml.safe_load((truth_dir_for(root) / "truth.yaml").read_text())
        if form is not None:
            form.inject(root, amplitude, truth["derived"]["conversion_gain_dn_per_e_iso100"], seed)
        model = list(base_model)
        ranked, unexplained, before, tests = analyse(root, config, model, experiments)
        found = ranked[ranked["significant"]]["effect"].tolist() if len(ranked) else []
        row = {"top": ranked.iloc[0]["effect"] if len(ranked) else "", "found": found,
               "significant": bool(ranked.iloc[0]["significant"]) if len(ranked) else False,
               "p": float(ranked.iloc[0]["p_value"]) if len(ranked) else float("nan"),
               "rms_before": float(before["rms_z"].max()), "truth": truth, "unexplained": unexplained}
        if expected:
            first = ranked.set_index("effect").loc[expected[0]] if expected[0] in set(ranked["effect"]) else None
            row.update(amplitude=float(first["amplitude"]) if first is not None else float("nan"),
                       detectable=float(first["detectable_amplitude"]) if first is not None else float("nan"),
                       units=str(first["units"]) if first is not None else "")
            if len(expected) == 2 and expected[1] in set(ranked["effect"]):
                second = ranked.set_index("effect").loc[expected[1]]
                row.update(second=(expected[1], int(second["rank"]), float(second["amplitude"]),
                                   float(second["detectable_amplitude"]), float(second["p_value"])))
            ranked_after, unexplained_after, after, tests_after = analyse(root, config, model + expected, experiments)
            row.update(rms_after=float(after["rms_z"].max()),
                       floor=bool((after["rms_z"].to_numpy() < floor_of(after)).all()),
                       still=ranked_after[ranked_after["significant"]]["effect"].tolist() if len(ranked_after) else [],
                       reported=unexplained_after["experiment"].tolist(), noted=shared_tables(tests_after))
        else:
            # clean data: any table reported as structured is a false alarm of the residual tests; the
            # covariate scan's smallest p over the tables, and the table's own smallest p
            best = tests.loc[tests["covariate_p_value"].idxmin()]
            row.update(floor=bool((before["rms_z"].to_numpy() < floor_of(before)).all()),
                       reported=[f"{t.experiment}/{t.level}" for t in unexplained.itertuples()],
                       noted=shared_tables(tests),
                       scan=(str(best["covariate"]), f"{best['experiment']}/{best['level']}",
                             float(best["covariate_p_value"]), float(tests["p_value"].min())),
                       signal_level=tests.loc[tests["covariate"] == "signal_fraction", "covariate_p_value"].tolist())
        return row
    finally:
        shutil.rmtree(root.parent, ignore_errors=True)


def _count(flags) -> str:
    flags = [bool(f) for f in flags]
    return f"{sum(flags)} of {len(flags)}" + (f" ({100 * sum(flags) / len(flags):.0f} %)" if flags else "")


def summary_rows(rows: list[dict], clean: list[dict]) -> list[dict]:
    """The run's summary, one row per kind of case and magnitude, the single-effect cases pooled, and the clean
    datasets.

    Parameters
    ----------
    rows : list of dict
        The effect cases and pairs, as :func:`run_case` returns them with their case, kind, level, top1,
        ranked_first and (single effects) above_limit.
    clean : list of dict
        The clean datasets' cases.

    Returns
    -------
    list of dict
        Column name to text: cases, top1_significant, above_limit_top1, ranked_first, back_to_floor,
        reported (of those not back to the floor, reported as residual structure or as an excess shared by
        blocks), and for the clean datasets false_alarms and note.
    """
    out = []
    for kind, label in (("catalogue", "catalogue"), ("form", "other forms"), ("pair", "pairs")):
        for level in ("clear", "limit"):
            sub = [r for r in rows if r["kind"] == kind and r["level"] == level]
            if not sub:
                continue
            back = [r for r in sub if "rms_after" in r]
            missed = [r for r in back if not r["floor"]]
            row = {"cases": f"{label}, {'clear' if level == 'clear' else 'near the limit'} ({len(sub)})",
                   "top1_significant": _count(r["top1"] for r in sub) + (" found in turn" if kind == "pair" else ""),
                   "ranked_first": _count(r["ranked_first"] for r in sub),
                   "back_to_floor": _count(r["floor"] for r in back),
                   "reported": (f"{sum(bool(r['reported']) for r in missed)} of {len(missed)} as residual structure, "
                                f"{sum(bool(r['noted']) for r in missed if not r['reported'])} as an excess shared "
                                f"by blocks")}
            if kind != "pair":
                row["above_limit_top1"] = _count(r["top1"] for r in sub if r["above_limit"])
            out.append(row)
    single = [r for r in rows if r["kind"] != "pair" and r["above_limit"]]
    if single:
        out.append({"cases": "all single-effect cases pooled", "above_limit_top1": _count(r["top1"] for r in single)})
    if clean:
        out.append({"cases": f"clean with lab noise ({len(clean)})",
                    "false_alarms": _count(r["found"] for r in clean),
                    "back_to_floor": "rms_z within the floor " + _count(r["floor"] for r in clean),
                    "reported": (f"{sum(bool(r['reported']) for r in clean)} as residual structure, "
                                 f"{sum(bool(r['noted']) for r in clean)} as an excess shared by blocks"),
                    "note": f"covariate scan's smallest p {min(r['scan'][2] for r in clean):.2g}; " + _signal_level(clean)})
    return out


def _signal_level(clean: list[dict]) -> str:
    named = [p for r in clean for p in r["signal_level"]]
    return (f"the signal level (signal_fraction) named in {len(named)} tables"
            + (f", smallest p {min(named):.2g}" if named else ""))


def record(rows: list[dict], clean: list[dict], parts: str, t0: float, c0: float, load0: float) -> None:
    """Print the summary and append the run to benchmarks/results: its cases (``bench_detection.csv``), its
    summary (``bench_detection_summary.csv``) and its cost (``bench_detection_runs.csv``), all under one run name.

    Parameters
    ----------
    rows, clean : list of dict
        The effect cases and pairs, and the clean datasets' cases.
    parts : str
        What the run ran (effects, magnitudes, pairs, clean datasets).
    t0, c0, load0 : float
        Wall clock, CPU time and the one-minute load average at the start.
    """
    from datetime import datetime, timezone

    from record import append_rows, commit

    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    summary = summary_rows(rows, clean)
    print()
    print("summary (tiny scale; dark and linearity experiments, roll-off for its effects)")
    for s in summary:
        print(f"  {s['cases']}: " + ", ".join(f"{k} {v}" for k, v in s.items() if k != "cases"))
    print(f"  {wall:.0f} s wall, {cpu:.0f} s CPU")
    run = f"{datetime.now(timezone.utc):%Y-%m-%d %H:%M} {commit()}"
    append_rows("bench_detection", [
        {"case": r["case"], "kind": r["kind"], "level": r["level"], "top_ranked": r["top"],
         "significant": bool(r["significant"]), "p": f"{r['p']:.2g}", "injected": r.get("injected", ""),
         "amplitude": r.get("amplitude", ""), "detectable": r.get("detectable", ""), "units": r.get("units", ""),
         "above_limit": r.get("above_limit", ""), "rms_z_before": round(r["rms_before"], 2),
         "rms_z_after": round(r["rms_after"], 2) if "rms_after" in r else "", "at_noise_floor": bool(r["floor"]),
         "top1": bool(r["top1"])} for r in rows + clean], run=run)
    append_rows("bench_detection_summary", summary, run=run)
    append_rows("bench_detection_runs", [{"parts": parts, "load": f"{load0:.1f} at the start, "
                                          f"{os.getloadavg()[0]:.1f} at the end", "cpu_s": round(cpu),
                                          "wall_s": round(wall)}], run=run)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--effects", default=",".join(list(MAGNITUDES) + list(FORMS)),
                    help="catalogue effects and forms of tests/support/effect_forms.py, comma-separated ('' for none)")
    ap.add_argument("--magnitudes", default="clear,limit", help="clear, limit or both")
    ap.add_argument("--pairs", default=",".join(DEFAULT_PAIRS), help="a+b pairs, comma-separated ('' for none)")
    ap.add_argument("--clean", type=int, default=20, help="clean datasets with the realistic lab noise")
    ap.add_argument("--clean-seeds", default=None,
                    help="seeds of the clean datasets, comma-separated (instead of --clean's 300 on)")
    ap.add_argument("--lab-noise", default="",
                    help="lab-noise sizes of the clean datasets, name=value comma-separated (default: LabNoise's)")
    ap.add_argument("--seed", type=int, default=500, help="first seed of the effect cases (clean: 300 on)")
    ap.add_argument("--work", default=None, help="folder for the simulated datasets (default: a temporary one)")
    args = ap.parse_args()

    names = [n for n in args.effects.split(",") if n]
    unknown = [n for n in names if n not in MAGNITUDES and n not in FORMS]
    if unknown:
        sys.exit(f"error: unknown effect or form {', '.join(unknown)}; known: {', '.join(list(MAGNITUDES) + list(FORMS))}")
    levels = [m for m in args.magnitudes.split(",") if m]
    if any(m not in LEVELS for m in levels):
        sys.exit(f"error: --magnitudes takes clear and/or limit, got {args.magnitudes!r}")
    pairs = [p.split("+") for p in args.pairs.split(",") if p]
    lab = [e for e in MAGNITUDES if e not in ROLLOFF_EFFECTS]
    if any(len(p) != 2 or any(e not in lab for e in p) for p in pairs):
        sys.exit(f"error: --pairs takes a+b with names of {', '.join(lab)}")

    try:
        sizes = {k.strip(): float(v) for k, v in (item.split("=") for item in args.lab_noise.split(",") if item)}
        lab_noise = replace(LabNoise(), **sizes)
    except (ValueError, TypeError) as exc:
        sys.exit(f"error: --lab-noise takes name=value pairs of {', '.join(f.name for f in fields(LabNoise))}: {exc}")
    try:
        clean_seeds = ([int(s) for s in args.clean_seeds.split(",") if s] if args.clean_seeds is not None
                       else list(range(300, 300 + args.clean)))
    except ValueError:
        sys.exit(f"error: --clean-seeds takes comma-separated integers, got {args.clean_seeds!r}")

    config = load_config()
    tmp = None
    if args.work:
        work = Path(args.work)
        work.mkdir(parents=True, exist_ok=True)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="bench-detection-")
        work = Path(tmp.name)
    t0, c0, load0 = time.perf_counter(), time.process_time(), os.getloadavg()[0]
    seed = args.seed
    rows = []
    header = (f"{'case':42s} {'level':5s} {'injected':>10s} {'found':>10s} {'detect.':>10s} {'units':14s} "
              f"{'top-ranked':16s} {'sig':3s} {'p':>8s} {'rms_z':>6s} {'after':>6s} {'floor':5s}")
    print(header)

    def show(label, level, row, injected):
        after = f"{row['rms_after']:6.2f}" if "rms_after" in row else "     -"
        print(f"{label:42s} {level:5s} {injected:10.3g} {row.get('amplitude', np.nan):10.3g} "
              f"{row.get('detectable', np.nan):10.3g} {row.get('units', ''):14s} {row['top']:16s} "
              f"{'yes' if row['significant'] else 'no':3s} {row['p']:8.1e} {row['rms_before']:6.2f} {after} "
              f"{'yes' if row['floor'] else 'no':5s}" + (f"  still significant: {' '.join(row['still'])}"
                                                       if row.get("still") else "")
              + (f"  reported: {' '.join(row['reported'])}" if row.get("reported") else "")
              + (f"  excess shared by blocks: {' '.join(row['noted'])}" if row.get("noted") else "")
              + (f"  significant in turn: {' '.join(row['found']) or '-'}" if row.get("kind") == "pair" else "")
              + ("  covariate scan: smallest p {2:.2g} ({0}, {1}); smallest table p {3:.2g}".format(*row["scan"])
                 if "scan" in row else "")
              + ("  second ({}): rank {}, injected {:.3g}, found {:.3g}, detect. {:.3g}, p {:.1e}".format(*row["second"])
                 if row.get("kind") == "pair" and "second" in row else ""),
              flush=True)

    for name in names:
        for level in levels:
            seed += 1
            i = LEVELS[level]
            if name in MAGNITUDES:
                params = MAGNITUDES[name][i]
                row = run_case(work, config, seed, [name], sim_effects=[(name, params)],
                               experiments=("rolloff",) if name in ROLLOFF_EFFECTS else ("dark", "linearity"))
                injected = injected_amplitude(name, params, row["truth"])
                label, kind, effect = name, "catalogue", name
            else:
                form = FORMS[name]
                exps = ("rolloff",) if "rolloff" in form.experiments else ("dark", "linearity")
                row = run_case(work, config, seed, [form.effect], form=form, amplitude=form.amplitudes[i],
                               experiments=exps)
                injected, label, kind, effect = form.amplitudes[i], f"{name} ({form.effect})", "form", form.effect
            # above the detection limit: the injected amplitude (for a form, whose units may differ, the one
            # found) beyond the detectable amplitude the diagnostics report
            size = injected if kind == "catalogue" else row.get("amplitude", np.nan)
            row.update(case=label, kind=kind, level=level, top1=row["top"] == effect and row["significant"],
                       ranked_first=row["top"] == effect, injected=injected,
                       above_limit=bool(abs(size) > row.get("detectable", np.nan)))
            rows.append(row)
            show(label, level, row, injected)
    for a, b in pairs:
        seed += 1
        row = run_case(work, config, seed, [a, b], sim_effects=[(a, MAGNITUDES[a][0]), (b, MAGNITUDES[b][0])])
        row.update(case=f"{a}+{b}", kind="pair", level="clear", top1=set(row["found"][:2]) == {a, b},
                   ranked_first=row["top"] in (a, b))
        if "second" in row:
            name_b, rank_b, *rest = row["second"]
            row["second"] = (name_b, rank_b, injected_amplitude(b, MAGNITUDES[b][0], row["truth"]), *rest)
        rows.append(row)
        show(f"{a}+{b}", "clear", row, injected_amplitude(a, MAGNITUDES[a][0], row["truth"]))
    clean = []
    for clean_seed in clean_seeds:
        row = run_case(work, config, clean_seed, [], lab_noise=lab_noise, base_model=("bias_drift",))
        row.update(case=f"clean seed {clean_seed}", kind="clean", level="-", top1=False, ranked_first=False)
        clean.append(row)
        show(f"clean seed {clean_seed} (lab noise)", "-", row, np.nan)

    parts = (f"{len(names)} effects or forms at {' and '.join(levels) or 'no'} magnitudes, {len(pairs)} pairs, "
             f"{len(clean_seeds)} clean datasets")
    record(rows, clean, parts, t0, c0, load0)
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
