"""Light-field quantities of one frame and band from its (filled) radiance sphere grid, with their uncertainty.

Conventions (Mobley, Light and Water; Kirk): a direction is where the light
comes from; z is its zenith angle in the earth frame. Per band:

    E_d  = int_upper L |cos z| dOmega      E_u  = int_lower L |cos z| dOmega
    E_0d = int_upper L dOmega              E_0u = int_lower L dOmega        E_0 = E_0d + E_0u
    mu_d = E_d / E_0d    mu_u = E_u / E_0u    mu = (E_d - E_u) / E_0
    L_d  = mean L over a cone about the zenith, L_u about the nadir (solid-angle weighted)
    Q    = E_u / L_u

Each of E_d, E_u, E_0d, E_0u, L_d, L_u is a weighted sum F_k = sum_i W_ki L_i
over the cells (:mod:`pipeline.lightfield.quadrature`, the earth's zenith
expressed in the grid's frame by the attitude), the others functions of them.
A filled cell is (to first order) a linear map of two measured cells
(:mod:`pipeline.lightfield.fill`), so its weight moves onto them (W_eff) and
the uncertainty is propagated through the measured cells:

- random (independent per cell): Cov(F_k, F_l) = sum_i W_eff,ki W_eff,li sigma_r,i^2;
- systematic (common to the band, fully correlated between cells):
  dF_k = sum_i W_eff,ki sigma_s,i, one shared deviation; a derived quantity
  q(F) takes grad(q) . dF, so a term proportional to the radiance (R^-1, the
  immersion factor) cancels exactly in mu_d, mu_u, mu and Q (they are of degree
  zero in L) while it scales every E and L;
- fill model: sum over filled cells of W_ki sigma_model,i, taken fully
  correlated between the filled cells of a band (the largest it can be for
  sums with positive weights);
- attitude: the quantity recomputed with roll and pitch moved by +-delta
  (the grid rotated), variance (dq/dx)^2 sigma_x^2 + (d2q/dx2)^2 sigma_x^4 / 2
  per angle (the second term keeps the effect of a tilt about a level
  attitude, where the first derivative of E_d vanishes); heading turns about
  the vertical and changes no quantity here;
- quadrature: per weighted sum |F - F(half resolution)| plus, for a grid of
  centre samples, the size of the centre-to-mean correction
  (:mod:`pipeline.lightfield.quadrature`); a ratio takes |grad q| . error,
  its terms' errors added in magnitude.

The total is their root sum of squares. ``filled_fraction`` is the share of an
integral's value from filled cells; ``filled_variance_fraction`` the fill
model's share of its total variance.
"""

from __future__ import annotations

import numpy as np

from pipeline.lightfield.attitude import Attitude, earth_up_in_camera
from pipeline.lightfield.fill import FLAG_FILLED, Filled
from pipeline.lightfield.quadrature import GridEdges, cap_weights, cell_means_from_centres, cell_solid_angles, coarsen

__all__ = ["LINEAR", "QUANTITIES", "INTEGRALS", "functional_weights", "derived_values", "derived_gradients",
           "light_field_quantities", "COMPONENTS"]

#: the weighted sums, in this order
LINEAR = ("E_d", "E_u", "E_0d", "E_0u", "E_0", "L_d", "L_u")
#: every quantity reported
QUANTITIES = ("E_d", "E_u", "E_0d", "E_0u", "E_0", "mu_d", "mu_u", "mu", "L_d", "L_u", "Q")
#: the quantities that are integrals of the radiance (a filled fraction of their value is defined)
INTEGRALS = ("E_d", "E_u", "E_0d", "E_0u", "E_0", "L_d", "L_u")
COMPONENTS = ("random", "systematic", "fill_model", "attitude", "quadrature")


def functional_weights(edges: GridEdges, up: np.ndarray, cone_half_angle_deg: float, subcells: int) -> np.ndarray:
    """(7, n_cells) weights of LINEAR for the earth zenith ``up`` (grid components).

    Parameters
    ----------
    edges : GridEdges
        The grid's cell edges, radians.
    up : numpy.ndarray
        The earth's zenith as a unit vector in the grid's components, shape ``(3,)``.
    cone_half_angle_deg : float
        Half angle of the cones about the zenith and nadir over which L_d and L_u are averaged, degree.
    subcells : int
        k of the k x k division of the cells a cap's edge crosses.

    Returns
    -------
    numpy.ndarray
        Shape ``(7, n_cells)``: per sum of ``LINEAR``, the weight of each cell (sr for the irradiances, a
        solid-angle fraction summing to 1 for L_d and L_u).
    """
    cone = float(np.cos(np.radians(cone_half_angle_deg)))
    up_w0, up_w1 = cap_weights(edges, up, 0.0, subcells)
    dn_w0, dn_w1 = cap_weights(edges, -np.asarray(up), 0.0, subcells)
    zc, _ = cap_weights(edges, up, cone, subcells)
    nc, _ = cap_weights(edges, -np.asarray(up), cone, subcells)
    return np.stack([up_w1, dn_w1, up_w0, dn_w0, up_w0 + dn_w0, zc / zc.sum(), nc / nc.sum()]).reshape(7, -1)


def derived_values(F: np.ndarray) -> np.ndarray:
    """(..., 11) QUANTITIES from (..., 7) LINEAR.

    Parameters
    ----------
    F : numpy.ndarray
        The weighted sums of ``LINEAR``, shape ``(..., 7)`` (irradiances in W m-2 nm-1, radiances in
        W m-2 sr-1 nm-1).

    Returns
    -------
    numpy.ndarray
        The quantities of ``QUANTITIES``, shape ``(..., 11)``: irradiances (W m-2 nm-1), average cosines
        (dimensionless), L_d, L_u (W m-2 sr-1 nm-1) and Q (sr).
    """
    Ed, Eu, E0d, E0u, E0, Ld, Lu = np.moveaxis(F, -1, 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.stack([Ed, Eu, E0d, E0u, E0, Ed / E0d, Eu / E0u, (Ed - Eu) / E0, Ld, Lu, Eu / Lu], axis=-1)


def derived_gradients(F: np.ndarray) -> np.ndarray:
    """(11, 7) gradient of each of QUANTITIES with respect to LINEAR at F (7,).

    Parameters
    ----------
    F : numpy.ndarray
        The weighted sums of ``LINEAR``, shape ``(7,)``.

    Returns
    -------
    numpy.ndarray
        d quantity / d sum, shape ``(11, 7)``.
    """
    Ed, Eu, E0d, E0u, E0, Ld, Lu = F
    g = np.zeros((len(QUANTITIES), len(LINEAR)))
    for q, k in ((0, 0), (1, 1), (2, 2), (3, 3), (4, 4), (8, 5), (9, 6)):
        g[q, k] = 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        g[5, 0], g[5, 2] = 1 / E0d, -Ed / E0d ** 2
        g[6, 1], g[6, 3] = 1 / E0u, -Eu / E0u ** 2
        g[7, 0], g[7, 1], g[7, 4] = 1 / E0, -1 / E0, -(Ed - Eu) / E0 ** 2
        g[10, 1], g[10, 6] = 1 / Lu, -Eu / Lu ** 2
    return g


def _sums(W: np.ndarray, values: np.ndarray) -> np.ndarray:
    """W @ values, NaN where a cell with weight is NaN."""
    finite = np.isfinite(values)
    out = W @ np.where(finite, values, 0.0)
    out[(W[:, ~finite] != 0).any(axis=1)] = np.nan
    return out


def _effective(W: np.ndarray, filled: Filled) -> np.ndarray:
    """The weights moved from the filled cells onto the two measured cells each is interpolated from."""
    cells = np.flatnonzero(filled.flag.ravel() == FLAG_FILLED)
    Weff = W.copy()
    if cells.size:
        a = filled.above.ravel()[cells]
        b = filled.below.ravel()[cells]
        moved = W[:, cells]
        Weff[:, cells] = 0.0
        np.add.at(Weff.T, a, (moved * filled.weight_above.ravel()[cells]).T)
        np.add.at(Weff.T, b, (moved * filled.weight_below.ravel()[cells]).T)
    return Weff


class WeightCache:
    """Functional weights per (grid, roll, pitch): frames at the same attitude share them."""

    def __init__(self, cone_half_angle_deg: float, subcells: int):
        self.cone, self.subcells, self._cache = cone_half_angle_deg, subcells, {}

    def __call__(self, edges: GridEdges, roll_deg: float, pitch_deg: float) -> np.ndarray:
        key = (edges.key, round(roll_deg, 12), round(pitch_deg, 12))
        if key not in self._cache:
            if len(self._cache) > 64:
                self._cache.clear()
            self._cache[key] = functional_weights(edges, earth_up_in_camera(roll_deg, pitch_deg), self.cone,
                                                  self.subcells)
        return self._cache[key]


def light_field_quantities(filled: Filled, edges: GridEdges, attitude: Attitude, weights: WeightCache,
                           attitude_step_deg: float, centre_samples: bool = False, exposure_systematic=None,
                           lower_bound=None) -> dict:
    """Every quantity of one frame and band with its uncertainty components.

    Parameters
    ----------
    filled : Filled
        The frame and band's filled camera-frame radiance grid (:func:`pipeline.lightfield.fill.fill_between_lenses`),
        W m-2 sr-1 nm-1.
    edges : GridEdges
        The grid's cell edges, radians.
    attitude : Attitude
        The frame's attitude and its sigmas, degree.
    weights : WeightCache
        The functional weights per grid and attitude.
    attitude_step_deg : float
        The step delta of the attitude's numerical derivatives, degree.
    centre_samples : bool, default False
        The grid's values are samples at the cell centres; they are turned into cell means first
        (:func:`~pipeline.lightfield.quadrature.cell_means_from_centres`) and the size of that correction is part
        of the quadrature error.
    exposure_systematic : numpy.ndarray, optional
        Shape ``(n_exposure, n_zenith, n_azimuth)``: systematic sigmas of the measured cells (W m-2 sr-1 nm-1),
        each fully correlated over the cells and independent of the others (an HDR merge's per-exposure terms);
        each goes through the effective weights (filled cells take their edges') as one shared deviation and
        joins the systematic component in quadrature.
    lower_bound : numpy.ndarray, optional
        Shape ``(n_zenith, n_azimuth)``, bool: cells whose value is a lower bound; their share of each integral's
        value is ``lower_bound_fraction``.

    Returns
    -------
    dict
        ``"value"``: the 11 ``QUANTITIES`` (units as :func:`derived_values`); for each of ``COMPONENTS`` its
        standard uncertainty (11,), same units; ``"total"`` (11,) their root sum of squares;
        ``"filled_fraction"`` (11,) (NaN for the ratios); ``"filled_variance_fraction"`` (11,);
        ``"lower_bound_fraction"`` (11,) (NaN without ``lower_bound``).
    """
    grid = cell_means_from_centres(filled.radiance, edges) if centre_samples else filled.radiance
    L = grid.ravel()
    W = weights(edges, attitude.roll_deg, attitude.pitch_deg)
    F = _sums(W, L)
    value = derived_values(F)
    sampling = np.abs(F - _sums(W, filled.radiance.ravel())) if centre_samples else 0.0
    grad = derived_gradients(F)
    Weff = _effective(W, filled)
    sr2 = np.nan_to_num(filled.random_sigma.ravel()) ** 2
    measured = filled.flag.ravel() == 0
    Cr = (Weff * np.where(measured, sr2, 0.0)) @ Weff.T
    # the systematic deviation is one field over the grid (filled cells: their edges' through the same weights),
    # summed with the weights as the radiance is: W @ fill(sigma_s) = W_eff @ sigma_s
    ss_grid = cell_means_from_centres(filled.systematic_sigma, edges) if centre_samples else filled.systematic_sigma
    s = W @ np.nan_to_num(ss_grid.ravel())
    is_filled = filled.flag.ravel() == FLAG_FILLED
    m = W[:, is_filled] @ np.nan_to_num(filled.model_sigma.ravel()[is_filled])
    sys_var = (grad @ s) ** 2
    if exposure_systematic is not None:
        e = np.where(measured[None, :], np.nan_to_num(np.asarray(exposure_systematic, float).reshape(
            len(exposure_systematic), -1)), 0.0)
        sys_var = sys_var + np.sum((grad @ (Weff @ e.T)) ** 2, axis=1)
    out = {"value": value,
           "random": np.sqrt(np.maximum(np.einsum("qk,kl,ql->q", grad, Cr, grad), 0.0)),
           "systematic": np.sqrt(sys_var),
           "fill_model": np.abs(grad @ m)}
    # attitude: the grid rotated by +-delta in roll and in pitch
    variance = np.zeros(len(QUANTITIES))
    d = float(attitude_step_deg)
    for name, sigma in (("roll", attitude.roll_sigma_deg), ("pitch", attitude.pitch_sigma_deg)):
        if sigma <= 0:
            continue
        shifted = []
        for sign in (1, -1):
            r = attitude.roll_deg + (sign * d if name == "roll" else 0.0)
            p = attitude.pitch_deg + (sign * d if name == "pitch" else 0.0)
            shifted.append(derived_values(_sums(weights(edges, r, p), L)))
        first = (shifted[0] - shifted[1]) / (2 * d)
        second = (shifted[0] - 2 * value + shifted[1]) / d ** 2
        variance += first ** 2 * sigma ** 2 + second ** 2 * sigma ** 4 / 2
    out["attitude"] = np.sqrt(variance)
    # quadrature: the same on the grid of half resolution
    coarse = edges.halved()
    Lc = coarsen(grid, cell_solid_angles(edges)).ravel()
    half = _sums(weights(coarse, attitude.roll_deg, attitude.pitch_deg), Lc)
    # per weighted sum: the half-resolution difference, the centre-to-mean correction and a floor of 1e-12 of
    # the value (the sums' rounding); a ratio takes its terms' errors in magnitude (no cancellation assumed)
    error = np.abs(F - half) + sampling + 1e-12 * np.abs(F)
    out["quadrature"] = np.abs(grad) @ error
    out["total"] = np.sqrt(sum(out[c] ** 2 for c in COMPONENTS))
    Ff = _sums(W[:, is_filled], L[is_filled]) if is_filled.any() else np.zeros(len(LINEAR))
    part = derived_values(Ff)
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = np.where([q in INTEGRALS for q in QUANTITIES], part / value, np.nan)
        # L_d, L_u are means: their filled share is the filled cells' share of the weighted sum (as computed)
        out["filled_fraction"] = fraction
        out["filled_variance_fraction"] = np.where(out["total"] > 0, out["fill_model"] ** 2 / out["total"] ** 2, 0.0)
        out["lower_bound_fraction"] = np.full(len(QUANTITIES), np.nan)
        if lower_bound is not None:
            bound = np.asarray(lower_bound, bool).ravel()
            Fb = _sums(W[:, bound], L[bound]) if bound.any() else np.zeros(len(LINEAR))
            out["lower_bound_fraction"] = np.where([q in INTEGRALS for q in QUANTITIES], derived_values(Fb) / value,
                                                   np.nan)
    return out
