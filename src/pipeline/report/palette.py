"""The report's colours: one definition for every figure, colour-blind safe and legible on white.

Categories (bands, experiments, lenses) use the Okabe-Ito palette (Okabe and Ito 2008) without its
yellow, which is too pale on white. Ordered series (exposure times, ISO steps, runs) take colours from
viridis cut at 80 % of its range, before the pale yellow end. Signed maps use a diverging map whose
middle is white on purpose (zero offset).
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from cycler import cycler  # noqa: E402

__all__ = ["OKABE_ITO", "BAND_COLOURS", "category", "sequence", "SEQUENTIAL_MAP", "DIVERGING_MAP", "apply_style"]

#: Okabe-Ito without yellow (#F0E442): black, orange, sky blue, bluish green, blue, vermillion, reddish purple
OKABE_ITO = ("#000000", "#E69F00", "#56B4E9", "#009E73", "#0072B2", "#D55E00", "#CC79A7")
BAND_COLOURS = {"R": "#D55E00", "G": "#009E73", "B": "#0072B2"}
#: fraction of viridis used for ordered series: its last 20 % runs into pale yellow-green and yellow
SEQUENCE_END = 0.8
SEQUENTIAL_MAP = "viridis"
DIVERGING_MAP = "RdBu_r"


def category(i: int) -> str:
    """The i-th categorical colour (cycling; black first is kept for references, so start at orange).

    Parameters
    ----------
    i : int
        The series' index, from 0.

    Returns
    -------
    str
        A colour of the Okabe-Ito palette as ``"#rrggbb"``.
    """
    return OKABE_ITO[1 + i % (len(OKABE_ITO) - 1)]


def sequence(n: int) -> list:
    """``n`` colours of an ordered series, dark blue to green, never the pale yellow end of viridis.

    Parameters
    ----------
    n : int
        The number of colours (at least one is returned).

    Returns
    -------
    list[tuple[float, float, float, float]]
        RGBA colours, evenly spaced along the cut map.
    """
    cmap = plt.get_cmap(SEQUENTIAL_MAP)
    return [cmap(x) for x in np.linspace(0.0, SEQUENCE_END, max(n, 1))]


def sequential_map():
    """viridis cut at 80 %, before its yellow end, for images whose values are all positive (sky radiance).

    Returns
    -------
    matplotlib.colors.ListedColormap
        The colour map, 256 colours, named ``"viridis_cut"``.
    """
    from matplotlib.colors import ListedColormap

    return ListedColormap(plt.get_cmap(SEQUENTIAL_MAP)(np.linspace(0.0, SEQUENCE_END, 256)), name="viridis_cut")


def apply_style() -> None:
    """Matplotlib defaults for every report figure: the categorical cycle and legible font sizes."""
    plt.rcParams.update({"axes.prop_cycle": cycler(color=[category(i) for i in range(len(OKABE_ITO) - 1)]),
                         "font.size": 9, "legend.fontsize": 7, "axes.titlesize": 9})
