"""The ``apply`` sub-command's arguments.

A module of its own, without the radiometry: ``python -m pipeline`` builds every sub-command's parser at
each start, and importing :mod:`pipeline.bundle.apply` for it (scipy, xarray) cost about a second of
every command's start-up, ``--help`` included.
"""

from __future__ import annotations

import argparse


def add_apply_parser(subparsers) -> argparse.ArgumentParser:
    """``apply --calibration BUNDLE | --store DIR [--medium air|water] RAW.dng... -o OUT.nc``.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The command line's sub-commands, to which ``apply`` is added.

    Returns
    -------
    argparse.ArgumentParser
        The ``apply`` sub-command's parser.
    """
    p = subparsers.add_parser("apply", help="raw frames to radiance maps with a calibration bundle")
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--calibration", help="calibration bundle (results/calibration/<serial>.nc)")
    which.add_argument("--store", metavar="DIR", help="calibration store (python -m pipeline publish): each frame "
                                                      "takes the calibration valid at its DateTimeOriginal")
    p.add_argument("--medium", choices=("air", "water"), default="air")
    p.add_argument("raw", nargs="+", help="raw DNG frames of the calibrated camera")
    p.add_argument("-o", "--out", required=True, help="NetCDF file to write")
    p.add_argument("--grid-deg", type=float, default=None, help="zenith/azimuth cell size (default: apply.grid_deg)")
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    p.add_argument("--pixels", action=argparse.BooleanOptionalAction, default=True,
                   help="write the per-pixel maps of both lenses besides the sphere grid (default); "
                        "--no-pixels writes the sphere grid only")
    p.add_argument("--pixel-geometry", action=argparse.BooleanOptionalAction, default=True,
                   help="with the pixel maps also write each band pixel's theta, phi and solid angle (default); "
                        "--no-pixel-geometry leaves them in the calibration bundle and names them there "
                        "(216 MB less per file at the full resolution)")
    return p
