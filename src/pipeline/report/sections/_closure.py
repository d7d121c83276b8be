"""Where the model fails, measurement by measurement: the residual tests per experiment and level
(``residual_tests.csv``) as a table, and from the closure table (``results/closure/residuals.nc``) per
experiment z against the covariate its structure follows and, where the measurements have pixel
positions, the mean z per image-plane cell (no section of its own; used by the diagnostics section)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import xarray as xr  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

from pipeline.diagnostics.missing_effects import SOURCE_EXPERIMENT  # noqa: E402
from pipeline.report.content import Figure, Table, draw  # noqa: E402
from pipeline.report.formatting import finite, fmt_value, units_text  # noqa: E402
from pipeline.report.palette import DIVERGING_MAP, OKABE_ITO  # noqa: E402
from pipeline.diagnostics.residual_structure import (  # noqa: E402
    IMAGE_PLANE_COLUMNS,
    LOG_SCALE_COVARIATES,
    covariate_label,
    covariate_tests,
    image_plane_pattern,
    scan_values,
)

__all__ = ["is_structured", "lens_tests_table", "residual_tests_table", "closure_frame", "plotted_covariate", "z_covariate_figure",
           "image_plane_figure", "closure_figures"]

#: |z| beyond this is piled at the edge of the z-against-covariate plots
Z_PLOT_LIMIT = 6.0
#: the text covariates of the closure table (categorical axes)
TEXT_COVARIATES = ("lens", "band", "sweep", "medium", "kind", SOURCE_EXPERIMENT)
#: the closure table's column of a covariate a residual test names, where the two differ: ``experiment``, the
#: stage whose frames a row of a pooling closure table measures, is the table's ``source_experiment``
CLOSURE_COLUMN_OF = {"experiment": SOURCE_EXPERIMENT}


def _flag(row, column: str) -> bool:
    """A residual test's yes/no column, as written (bool) or read back from its CSV (text)."""
    v = row.get(column)
    if isinstance(v, str):
        return v.strip().lower() in ("true", "1", "yes")
    return bool(v) and not (isinstance(v, float) and np.isnan(v))


def is_structured(row) -> bool:
    """A residual test's row is structured when its ``significant`` column says so.

    Parameters
    ----------
    row : pandas.Series or dict
        One row of ``residual_tests.csv``.

    Returns
    -------
    bool
        True when ``significant`` is true (as a bool, a number or its text).
    """
    return _flag(row, "significant")


def _shared(row) -> bool:
    """Whether a residual test's row is above its stated noise with the excess shared by its blocks."""
    return _flag(row, "shared_excess")


def _text(v) -> str:
    return "" if v is None or (isinstance(v, float) and np.isnan(v)) else str(v)


def residual_tests_table(tests: pd.DataFrame) -> Table:
    """One row per experiment and level; the structured rows marked (and listed first in their experiment).

    Parameters
    ----------
    tests : pandas.DataFrame
        The diagnostics' ``residual_tests.csv``.

    Returns
    -------
    pipeline.report.content.Table
        n, dof, chi-square over dof, the p-values, whether structured, the covariate and image-plane cell.
    """
    rows, marked = [], []
    for _, r in tests.iterrows():
        dof = r.get("dof")
        ratio = float(r["chi2"]) / float(dof) if finite(r.get("chi2")) and finite(dof) and float(dof) > 0 else np.nan
        structured = is_structured(r)
        cov = _text(r.get("covariate"))
        if cov and finite(r.get("covariate_p_value")):
            cov = f"{covariate_label(cov)} (p {fmt_value(r['covariate_p_value'], 2)})"
        rows.append([_text(r.get("experiment")), _text(r.get("level")), fmt_value(r.get("n_obs"), 6),
                     fmt_value(dof, 6), fmt_value(ratio, 3), fmt_value(r.get("p_chi2"), 2),
                     fmt_value(r.get("p_block"), 2),
                     "yes" if structured else "no, excess shared by blocks" if _shared(r) else "no", cov,
                     _text(r.get("image_plane")) or "—"])
        marked.append(structured)
    return Table(["experiment", "level", "n", "dof", "χ²/dof", "p", "block p", "structured",
                  "covariate it follows", "image-plane cell"], rows,
                 "Residual tests per experiment and level: the sum of z² against its degrees of freedom (p of the "
                 "χ² distribution), the same with the residuals of one frame or setting taken together (block p, "
                 "robust to correlation within a block), whether the table is structured (highlighted rows), the "
                 "covariate whose grouping of the residuals is most significant and, for measurements with pixel "
                 "positions, the image-plane cell whose mean z departs most.", left=2, marked=marked)


def lens_tests_table(tests: pd.DataFrame) -> Table:
    """One row per effect and table tested for one value shared by the two lenses against one per lens.

    Parameters
    ----------
    tests : pandas.DataFrame
        The diagnostics' ``lens_tests.csv``.

    Returns
    -------
    pipeline.report.content.Table
        Per lens the value and its 95 % interval, the two chi-squares, the dof and p, and whether the lenses
        differ (highlighted).
    """
    rows, marked = [], []
    for _, r in tests.iterrows():
        units = "" if _text(r.get("units")) in ("", "1") else f" {_text(r.get('units'))}"
        each = "; ".join(f"{lens} {fmt_value(float(v), 3)} ({fmt_value(float(lo), 3)} to {fmt_value(float(hi), 3)})"
                         for lens, v, lo, hi in zip(_text(r.get("lenses")).split(), _text(r.get("values")).split(),
                                                    _text(r.get("lows")).split(), _text(r.get("highs")).split()))
        differ = str(r.get("significant")).strip().lower() in ("true", "1")
        rows.append([_text(r.get("effect")), f"{_text(r.get('experiment'))}/{_text(r.get('level'))}",
                     each + units, fmt_value(r.get("chi2_shared"), 4), fmt_value(r.get("chi2_split"), 4),
                     fmt_value(r.get("dof_split"), 6), fmt_value(r.get("p_value"), 2), "yes" if differ else "no"])
        marked.append(differ)
    return Table(["effect", "table", "per lens (95 % interval)", "χ² shared", "χ² per lens", "dof", "p",
                  "lenses differ"], rows,
                 "Per-lens parameters: the two lenses are two sensors; each effect whose value may differ between "
                 "them is fitted once shared by both and once per lens (the rest of the model as it is); p is the "
                 "larger of the F test of the drop in χ² and its block-robust Wald test, and the lenses differ "
                 "(highlighted) below the diagnostics' significance level over the tests made. Every stage fits "
                 "each lens on its own, so an effect of the model has each lens's value in its artefact.", left=3, marked=marked)


def closure_frame(ds: xr.Dataset) -> tuple[pd.DataFrame, dict[str, str]]:
    """The closure table as a data frame (one row per measurement) and the units of each numeric covariate.

    Parameters
    ----------
    ds : xarray.Dataset
        The closure table (``residuals.nc``), variables along ``measurement``.

    Returns
    -------
    frame : pandas.DataFrame
        Its variables along ``measurement`` as columns (text as ``str``).
    units : dict[str, str]
        Variable -> its units attribute ("" when absent).
    """
    frame = pd.DataFrame({name: ds[name].values for name in ds.data_vars if ds[name].dims == ("measurement",)})
    for name in frame.columns:
        if frame[name].dtype == object or frame[name].dtype.kind in "SU":
            frame[name] = frame[name].astype(str)
    units = {name: str(ds[name].attrs.get("units", "")) for name in ds.data_vars}
    return frame, units


def _numeric_covariates(frame: pd.DataFrame) -> list[str]:
    skip = {"value", "prediction", "residual", "sigma", "z"}
    return [c for c in frame.columns if c not in skip and c not in TEXT_COVARIATES and frame[c].dtype.kind == "f"]


def plotted_covariate(rows: pd.DataFrame, tests: pd.DataFrame, bins: int) -> str | None:
    """The covariate to plot one experiment's z against: the one its structured test names (its first test
    when none is structured) when the closure table has it, else the numeric covariate whose grouping of z
    is most significant; None when no covariate varies.

    Parameters
    ----------
    rows : pandas.DataFrame
        One experiment's rows of the closure table (finite ``z``).
    tests : pandas.DataFrame
        That experiment's rows of ``residual_tests.csv`` (may be empty).
    bins : int
        The quantile bins of the covariate test (``diagnostics.covariate_bins``).

    Returns
    -------
    str or None
        The covariate's column.
    """
    for structured_first in (True, False):
        for _, r in tests.iterrows():
            if structured_first and not is_structured(r):
                continue
            name = _text(r.get("covariate"))
            name = CLOSURE_COLUMN_OF.get(name, name)
            if name in rows and rows[name].nunique(dropna=True) > 1:
                return name
    best, best_p = None, np.inf
    z = rows["z"].to_numpy(float)
    for name in _numeric_covariates(rows):
        values = rows[name]
        if values.notna().sum() < 3 or values.nunique(dropna=True) < 2:
            continue
        ok = values.notna().to_numpy()
        p, _ = covariate_tests(z[ok], scan_values(name, values[ok].reset_index(drop=True)), bins)
        if p < best_p:
            best, best_p = name, p
    return best


def _structured_levels(tests: pd.DataFrame) -> set[str]:
    return {str(r["level"]) for _, r in tests.iterrows() if is_structured(r)}


def z_covariate_figure(experiment: str, rows: pd.DataFrame, covariate: str, units: dict[str, str],
                       structured: set[str], bins: int) -> Figure:
    """z of one experiment's measurements against ``covariate``, one colour per level, the structured
    levels in vermillion, the ±2 band shaded and the mean z in quantile bins of the covariate.

    Parameters
    ----------
    experiment : str
        The experiment, for the title and caption.
    rows : pandas.DataFrame
        Its rows of the closure table.
    covariate : str
        The column to plot against (text covariates spread as categories).
    units : dict[str, str]
        Column -> units, for the axis label.
    structured : set[str]
        The levels (tables) the residual tests call structured.
    bins : int
        The number of quantile bins of the binned mean.

    Returns
    -------
    pipeline.report.content.Figure
        The figure (z clipped at the plot's limit).
    """
    fig, ax = plt.subplots(figsize=(7.5, 2.9))
    ax.axhspan(-2, 2, color=OKABE_ITO[2], alpha=0.15, lw=0, label="±2 (95 % of a unit normal)")
    ax.axhline(0, color=OKABE_ITO[0], lw=0.8)
    categorical = covariate in TEXT_COVARIATES or rows[covariate].dtype.kind not in "fiu"
    if categorical:
        cats = sorted(rows[covariate].astype(str).unique())
        pos = {c: i for i, c in enumerate(cats)}
        x_all = rows[covariate].astype(str).map(pos).to_numpy(float)
        x_all = x_all + np.random.default_rng(0).uniform(-0.25, 0.25, len(x_all))
    else:
        x_all = rows[covariate].to_numpy(float)
    z_all = np.clip(rows["z"].to_numpy(float), -Z_PLOT_LIMIT, Z_PLOT_LIMIT)
    levels = list(dict.fromkeys(rows["level"].astype(str)))
    others = [OKABE_ITO[4], OKABE_ITO[3], OKABE_ITO[6], OKABE_ITO[1]]
    for k, level in enumerate(levels):
        sel = (rows["level"].astype(str) == level).to_numpy()
        flagged = level in structured
        ax.scatter(x_all[sel], z_all[sel], s=6 if sel.sum() > 300 else 12, alpha=0.6, lw=0, rasterized=True,
                   color=OKABE_ITO[5] if flagged else others[k % len(others)],
                   label=f"{level} (structured)" if flagged else level)
    if not categorical:
        x, z = rows[covariate].to_numpy(float), rows["z"].to_numpy(float)
        ok = np.isfinite(x) & np.isfinite(z)
        if np.unique(x[ok]).size > 1:
            edges = np.unique(np.quantile(x[ok], np.linspace(0, 1, bins + 1)))
            idx = np.clip(np.searchsorted(edges, x[ok], side="right") - 1, 0, len(edges) - 2)
            centres = [x[ok][idx == i].mean() for i in range(len(edges) - 1) if (idx == i).any()]
            means = [z[ok][idx == i].mean() for i in range(len(edges) - 1) if (idx == i).any()]
            ax.plot(centres, means, "-o", color=OKABE_ITO[0], ms=3, lw=1.2, label="mean z per quantile bin")
    else:
        ax.set_xticks(range(len(cats)))
        ax.set_xticklabels(cats, fontsize=8)
    unit = units_text(units.get(covariate, ""))
    label = covariate_label(covariate)
    ax.set_xlabel(f"{label} [{unit or '1'}]" if not categorical else label)
    log_x = (not categorical and covariate in LOG_SCALE_COVARIATES
             and bool((rows[covariate].dropna() > 0).all()) and rows[covariate].notna().any())
    if log_x:
        ax.set_xscale("log")
    ax.set_ylabel("normalised residual z [1]")
    ax.set_ylim(-Z_PLOT_LIMIT - 0.3, Z_PLOT_LIMIT + 0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    flagged = sorted(set(levels) & structured)
    marked = (f" The structured table{'s' if len(flagged) > 1 else ''} ({', '.join(flagged)}) in vermillion."
              if flagged else " No table of this experiment is structured.")
    return draw(fig, f"closure_z_{experiment}",
                f"Where the {experiment} model fails: the normalised residual z = (value − prediction)/σ of each "
                f"of its {len(rows)} measurements in the closure table against {label}"
                f"{' (log scale)' if log_x else ''}, the covariate its "
                f"residual test names (or, when it names none the table has, the numeric covariate whose grouping "
                f"of z is most significant); one colour per table (level), the shaded band ±2, black the mean z "
                f"per quantile bin; |z| beyond {Z_PLOT_LIMIT:g} piled at the edge.{marked}",
                alt=f"z of the {experiment} measurements against {label}")


def image_plane_figure(experiment: str, rows: pd.DataFrame, cells: int) -> Figure | None:
    """Mean z per cell of a ``cells`` x ``cells`` grid over the measured span of the pixel positions (the
    grid of the residual tests: per table, over all lenses), one panel per table (level) and lens, the
    cell that departs most in each table outlined; None without pixel positions.

    Parameters
    ----------
    experiment : str
        The experiment, for the title and caption.
    rows : pandas.DataFrame
        Its rows of the closure table (pixel position columns, ``z``, ``level``, ``lens``).
    cells : int
        The grid's cells per side (``diagnostics.image_plane_cells``).

    Returns
    -------
    pipeline.report.content.Figure or None
        The figure; None when no table has pixel positions and enough measurements (two per cell).
    """
    if not all(c in rows for c in IMAGE_PLANE_COLUMNS):
        return None
    panels, patterns = [], []
    for level in dict.fromkeys(rows["level"].astype(str)):
        part = rows[rows["level"].astype(str) == level]
        x, y, z = (part[c].to_numpy(float) for c in (*IMAGE_PLANE_COLUMNS, "z"))
        ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
        if ok.sum() < 2 * cells * cells:
            continue
        part, x, y, z = part[ok].reset_index(drop=True), x[ok], y[ok], z[ok]
        lens = part["lens"].astype(str).to_numpy() if "lens" in part else np.full(len(part), "")
        edges_x = np.linspace(x.min(), x.max(), cells + 1)
        edges_y = np.linspace(y.min(), y.max(), cells + 1)
        ix = np.clip(np.searchsorted(edges_x, x, side="right") - 1, 0, cells - 1)
        iy = np.clip(np.searchsorted(edges_y, y, side="right") - 1, 0, cells - 1)
        pattern = image_plane_pattern(part, z, cells)
        patterns.append((level, pattern))
        for name in sorted(set(lens)):
            sums = np.zeros((cells, cells))
            counts = np.zeros((cells, cells))
            sel = lens == name
            np.add.at(sums, (iy[sel], ix[sel]), z[sel])
            np.add.at(counts, (iy[sel], ix[sel]), 1)
            with np.errstate(invalid="ignore", divide="ignore"):
                grid = np.where(counts > 0, sums / counts, np.nan)
            outline = pattern if pattern is not None and pattern["lens"] == name else None
            panels.append((level, name, edges_x, edges_y, grid, outline))
    if not panels:
        return None
    vmax = max(float(np.nanmax([np.nanmax(np.abs(p[4])) for p in panels])), 0.5)
    ncols = min(len(panels), 4)
    nrows = -(-len(panels) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(2.5 * ncols + 0.8, 2.5 * nrows), squeeze=False)
    for k, (ax, (level, name, edges_x, edges_y, grid, outline)) in enumerate(zip(axes.ravel(), panels)):
        ax.set_facecolor("#d9d9d9")
        mesh = ax.pcolormesh(edges_x, edges_y, grid, cmap=DIVERGING_MAP, vmin=-vmax, vmax=vmax)
        if outline is not None:
            (x0, x1), (y0, y1) = outline["x_px"], outline["y_px"]
            ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec=OKABE_ITO[0], lw=2))
        ax.set_title(f"{level}, lens {name}" if name else level, fontsize=8)
        ax.set_xlabel("x [px]")
        if k % ncols == 0:
            ax.set_ylabel("y [px]")
        ax.invert_yaxis()
        ax.set_aspect("equal", adjustable="box")
    for ax in axes.ravel()[len(panels):]:
        ax.set_visible(False)
    fig.colorbar(mesh, ax=list(axes.ravel()), label="mean z [1]", shrink=0.9)
    where = "; ".join(f"{level}: mean z {p['mean_z']:+.2f} over {p['n']} measurements, F test of the cell means "
                      f"p {p['p_value']:.2g}" for level, p in patterns if p is not None)
    return draw(fig, f"closure_image_plane_{experiment}",
                f"Where on the image plane the {experiment} model fails: mean normalised residual z per cell of a "
                f"{cells}×{cells} grid over the measured span of each table's pixel positions (full-resolution "
                f"pixels, y down), per table and lens; white is zero, red the data above the model, blue below, "
                f"grey no measurements. Outlined: the cell that departs most in each table, from the closure "
                f"table's z of the model's fit ({where}); the residual tests' table gives each test's own cell.",
                alt=f"image-plane map of the mean z of the {experiment} measurements")


def closure_figures(closure: xr.Dataset | None, tests: pd.DataFrame, bins: int, cells: int) -> list[Figure]:
    """Per experiment of the closure table: z against its covariate and, with pixel positions, the image-plane map.

    Parameters
    ----------
    closure : xarray.Dataset or None
        The closure table, or None when the diagnostics did not write it.
    tests : pandas.DataFrame
        ``residual_tests.csv`` (may be empty).
    bins : int
        The quantile bins of the covariate test.
    cells : int
        The image-plane grid's cells per side.

    Returns
    -------
    list[pipeline.report.content.Figure]
        The figures in the closure table's order of experiments; empty without a closure table with ``z``.
    """
    if closure is None or "z" not in closure:
        return []
    frame, units = closure_frame(closure)
    out = []
    for experiment in dict.fromkeys(frame["experiment"].astype(str)):
        rows = frame[frame["experiment"] == experiment]
        rows = rows[np.isfinite(rows["z"].to_numpy(float))]
        if rows.empty:
            continue
        mine = (tests[tests["experiment"].astype(str) == experiment]
                if not tests.empty and "experiment" in tests else pd.DataFrame())
        covariate = plotted_covariate(rows, mine, bins)
        if covariate is not None:
            out.append(z_covariate_figure(experiment, rows, covariate, units, _structured_levels(mine), bins))
        image = image_plane_figure(experiment, rows, cells)
        if image is not None:
            out.append(image)
    return out
