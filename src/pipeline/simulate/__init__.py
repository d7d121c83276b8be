"""Physically based simulator of the dual-fisheye camera and its lab experiments.

It writes calibration datasets laid out exactly as docs/dataset-format.md says, with what
only a simulator knows (true parameters, effects switched on) in a truth
folder beside the dataset.
"""

from pipeline.simulate.dataset import SCALES, simulate_dataset, truth_dir_for

__all__ = ["SCALES", "simulate_dataset", "truth_dir_for"]
