"""The ``lightfield`` sub-command's arguments.

A module of its own, without the light field's computation: ``python -m pipeline`` builds every
sub-command's parser at each start, and importing :mod:`pipeline.lightfield.command` for it (the bundle's
apply, the diagnostics, scipy) cost about a second of every command's start-up, ``--help`` included.
"""

from __future__ import annotations

import argparse


def _site(text: str) -> tuple:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--site {text!r}: needs LAT,LON[,ALT_M] in degrees and metres") from None
    if len(values) not in (2, 3) or not (-90 <= values[0] <= 90 and -180 <= values[1] <= 360):
        raise argparse.ArgumentTypeError(f"--site {text!r}: needs LAT,LON[,ALT_M], latitude within +-90 degrees")
    return values


def add_lightfield_parser(subparsers) -> argparse.ArgumentParser:
    """``lightfield [--calibration BUNDLE] [--medium air|water] [--attitude FILE] [--site LAT,LON] GRID.nc... -o OUT.nc``.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The command line's sub-commands, to which ``lightfield`` is added.

    Returns
    -------
    argparse.ArgumentParser
        The ``lightfield`` sub-command's parser.
    """
    p = subparsers.add_parser(
        "lightfield", help="radiance sphere grids to irradiances, average cosines and radiances",
        description="E_d, E_u, E_0d, E_0u, E_0, mu_d, mu_u, mu, L_d, L_u and Q per frame and band, with their "
                    "random, systematic, fill-model, attitude and quadrature uncertainty, from radiance sphere "
                    "grids (apply's output, or any grid in the format of docs/light-field.md).")
    p.add_argument("grids", nargs="+", metavar="GRID.nc", help="radiance sphere grid files (with --calibration: "
                                                                "raw DNG frames)")
    p.add_argument("--calibration", metavar="BUNDLE", default=None,
                   help="calibration bundle: the inputs are raw frames, which apply turns into a sphere grid first")
    p.add_argument("--grid-deg", type=float, default=None,
                   help="with --calibration: zenith/azimuth cell size of the grid (default: apply.grid_deg)")
    p.add_argument("-o", "--out", required=True, help="NetCDF file to write")
    p.add_argument("--medium", choices=("air", "water"), default=None,
                   help="medium of the grids (default: their 'medium' attribute, else air)")
    p.add_argument("--attitude", metavar="FILE", default=None,
                   help="CSV log of roll, pitch, heading and their sigmas (docs/light-field.md); without it the "
                        "grid's zenith is the zenith")
    p.add_argument("--site", type=_site, default=None, metavar="LAT,LON[,ALT_M]",
                   help="where the frames were taken: adds the solar position (pvlib) and azimuths from the sun")
    p.add_argument("--camera-utc-offset-h", type=float, default=0.0, metavar="HOURS",
                   help="camera clock minus UTC for frame times without an offset (default 0)")
    p.add_argument("--frames", metavar="FRAMES.csv", default=None,
                   help="with --calibration: exposure brackets, a CSV with the columns file and bracket; the "
                        "frames of each bracket are merged into one HDR map")
    p.add_argument("--hdr", action="store_true",
                   help="with --calibration: merge exposure brackets grouped by time (lightfield.bracket_window_s) "
                        "when no --frames table is given")
    p.add_argument("--attitude-from-sun", choices=("heading", "heading_tilt"), default=None,
                   help="with --frames/--hdr and --site, no --attitude: fit the attitude from the sun's centroid "
                        "(heading: the horizon level assumed; heading_tilt: also the tilt towards the sun)")
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    return p
