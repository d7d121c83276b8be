"""Command line: ``python -m pipeline simulate --out DIR --scale tiny|small|full --seed N --effect NAME[:p=v,...]``."""

from __future__ import annotations

import argparse
import sys

from pipeline.effects.base import parse_effect_spec
from pipeline.errors import InputError


def simulate_from_config(out, simulation: dict) -> None:
    """Simulate the default dataset from the ``simulate_if_missing`` config section."""
    from pipeline.simulate import simulate_dataset

    effects = [parse_effect_spec(s) for s in simulation["effects"]]
    simulate_dataset(out, scale=simulation["scale"], seed=simulation["seed"], effects=effects)


def main(argv: list[str] | None = None) -> int:
    from pipeline.simulate import SCALES

    parser = argparse.ArgumentParser(prog="python -m pipeline", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sim = sub.add_parser("simulate", help="write a simulated calibration dataset and its truth folder")
    sim.add_argument("--out", required=True, help="dataset folder to create (must not exist)")
    sim.add_argument("--scale", choices=list(SCALES), default="small")
    sim.add_argument("--seed", type=int, default=0)
    sim.add_argument("--effect", action="append", default=[], metavar="NAME[:param=value,...]",
                     help="switch on a true effect of the simulated camera (repeatable)")
    sim.add_argument("--experiments", default=None,
                     help="comma-separated experiments to simulate (default: all the simulator writes)")
    sim.add_argument("--no-progress", action="store_true", help="no progress bar")
    from pipeline.apply import add_apply_parser, apply_command

    add_apply_parser(sub)
    args = parser.parse_args(argv)
    if args.command == "apply":
        return apply_command(args)
    try:
        if args.command == "simulate":
            from pipeline.simulate import simulate_dataset
            from pipeline.simulate.dataset import truth_dir_for

            from pipeline.simulate.dataset import EXPERIMENTS

            effects = [parse_effect_spec(s) for s in args.effect]
            experiments = tuple(e for e in args.experiments.split(",") if e) if args.experiments else EXPERIMENTS
            out = simulate_dataset(args.out, scale=args.scale, seed=args.seed, effects=effects,
                                   experiments=experiments, progress=not args.no_progress)
            print(f"dataset: {out}\ntruth:   {truth_dir_for(out)}")
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
