"""Roll-off stage (Larouche et al. 2024, Sections 2.4 and 3.3; Eq. (13), Fig. 5).

Streams the roll-off frames once (dark frames first, then the port images):

* dark subtraction with the per-pixel mean of the experiment's dark frames of
  the same medium;
* the port spot: the brightest pixel of the smoothed G image, the connected
  pixels above ``rolloff.spot_threshold_fraction`` of its level, their flux-weighted centroid, found on the
  setting's first frame; a setting whose
  spot carries no light above the noise in the lit field
  (``rolloff.min_spot_snr``) or whose light rises beyond the field's edge
  (the wing of a port outside it) is dropped with its
  reason (logged, counted in ``n_settings_dropped``), and the stage stops when
  a lens and medium keeps fewer than ``rolloff.min_settings``;
* the mean in a circle of ``rolloff.spot_radius_deg`` around it, in band
  pixels through the angular size of a pixel near the axis (from the geometry
  artefact's theta map), at least 1 px; the
  field angle and azimuth of the point from the geometry artefact's maps
  (Section 3.3: "converted into absolute angles using the angular
  calibration"), averaged over the same pixels so that value and angle pair;
* the noise of each setting mean from the frame-to-frame differences, pooled
  per band into a photon-transfer line var = k S + r (no per-point noisy
  variances);
* the centroid's uncertainty, per axis (``spot_x_sigma_px``, ``spot_y_sigma_px``,
  :func:`_add_centroid_sigma`), the sum in quadrature of three terms: the pixels'
  noise through the flux-weighted centroid (the setting keeps five sums; the noise
  model above is known only after streaming); the cut's flips, pixels that pass
  the threshold in one frame and not the next (the scatter of every frame's
  centroid through the same cut, pooled per lens, medium and azimuth plane, beyond
  the pixel term: with the G band's edge pixels at half the level, one green site
  of two lit, this is 20 times the linear term); and the pixel grid's sampling of
  the sharp-edged spot, 1 / (12 pi n R) for a spot of radius R band pixels and n
  samples a pixel (2 for G). Against the simulator's true port centres (docs/stages.md,
  "Closure and diagnostics", ``closure/field_angle``) the three hold the centroid's
  error at both scales: rms of error over sigma 1.00 (tiny, nine seeds) and 0.96
  (small, two seeds), the noise terms alone 1.05 and 0.99 of the seed-to-seed
  scatter; a constant 0.1 px, 0.96 and 0.76. The spread of the centroid over
  threshold fractions 0.3 to 0.7 was measured and left out: it follows the error
  only on average (rms of error over it 1.1 to 1.8 in its upper quartiles, 800 in
  the lowest, where no edge pixel lies between the fractions);
* the halo: mean excess in an annulus just outside the port's pixels (the
  union over bands of the pixels above ``halo_spot_fraction`` of each band's
  peak: the R and B sites are offset from the G sites), and the model's
  stray-light column, those pixels' flux convolved with the wide kernel;
* per lens, band and medium: the normalised roll-off and the even
  8th-degree polynomial (radiometry.rolloff.fit_rolloff) over both azimuth
  planes, plus the effects of the model (``rolloff_azimuth``,
  ``stray_light``, ``immersion_angle``);
* the field angle's error from the geometric calibration as what it is, an
  error of the fitted model common to every spot of a band image: the
  principal point's share (odd in azimuth, the look-alike of
  ``rolloff_azimuth``) as two whitened nuisance columns per group
  (``x_centre_1``, ``x_centre_2``: the spot's slope times d theta / d centre
  times the square root of the geometry artefact's centre covariance,
  :mod:`pipeline.geometry.centre_shift`) and their prior as two rows of kind
  ``centre_prior`` (0 +/- 1), so that the diagnostics' refits carry it too;
  the radial share is absorbed by the even polynomial. Each spot keeps
  ``rolloff.field_angle_sigma_px`` as independent noise besides (the only
  term without the geometry's covariance);
* observation tables: ``obs_setting`` (one row per setting: the port spot,
  ``kind=spot``, base columns the even polynomial terms; and its halo,
  ``kind=halo``, base prediction 0) and ``obs_water`` (closure: each
  in-water point, normalised by the water fit, against its prediction from
  the in-air fit and the immersion physics, g_w(theta_w) = c g_air(theta_a)
  F(theta_a, theta_w): theta_a the same pixels' field angle in the geometry
  artefact's air model, F the Fresnel transmissions of the outer surface,
  radiometry/immersion_rolloff.py; no shape parameter fitted, only the
  scale c; the prediction's uncertainty from the air fit's covariance and
  the air model's field-angle uncertainty).
"""

from __future__ import annotations

import logging
from collections import defaultdict

import numpy as np
import pandas as pd
import xarray as xr
from scipy import ndimage

from pipeline.io.bands import BANDS
from pipeline.io.dataset import Dataset, read_water
from pipeline.effects import get as get_effect
from pipeline.effects.optics import azimuth_from_coefficients
from pipeline.stats.fitting import base_design, wls
from pipeline.errors import InputError
from pipeline.io.frames import iter_frames
from pipeline.geometry.centre_shift import centre_columns, centre_root, centre_theta_gradient, centre_variance
from pipeline.stats.moments import RunningMoments
from pipeline.stages.observations import table_to_dataset, with_corner_table
from pipeline.radiometry.immersion_rolloff import water_rolloff_factor
from pipeline.radiometry.rolloff import (ROLLOFF_POWERS, evaluate_rolloff, fit_rolloff, normalise_rolloff,
                                         rolloff_design_matrix, rolloff_slope)
from pipeline.radiometry.response import PixelResponse
from pipeline.radiometry.unlit_corners import FrameCorners
from pipeline.radiometry.water import refractive_index_water
from pipeline.stages.geometry_maps import model_from_dataset
from pipeline.stages.immersion import NOMINAL_WAVELENGTH_NM

STAGE = "rolloff"
MEDIA = ("air", "water")
#: scale of theta in the stored base columns (conditioning): u = theta / 90 deg
THETA_SCALE_DEG = 90.0
SETTING_EFFECTS = ("rolloff_azimuth", "stray_light")
#: the nuisance columns of the principal point's error (whitened, one pair per band image) and the kind of the
#: pseudo-measurement rows that hold their prior (:mod:`pipeline.geometry.centre_shift`)
CENTRE_COLUMNS = ("x_centre_1", "x_centre_2")
CENTRE_PRIOR_KIND = "centre_prior"
WATER_EFFECTS = ("rolloff_azimuth", "immersion_angle")
log = logging.getLogger("pipeline.rolloff")


# ----------------------------------------------------------------------------- reduction
#: half-size (band pixels) of the first window in which a spot is searched; doubled until the spot's
#: connected pixels lie inside it, up to the whole image. The result does not depend on it (only the time):
#: the window is searched only where it provably holds what the whole image would give.
SPOT_WINDOW_HALF_PX = 48
#: independent samples of the scene in one G band pixel (the mean of the cell's two green sites,
#: :func:`pipeline.io.bands.band_plane`): the grid term of the centroid's uncertainty (:func:`_add_centroid_sigma`)
G_SITES_PER_BAND_PIXEL = 2


def _window(shape, iy: int, ix: int, half: int) -> tuple[slice, slice]:
    return (slice(max(iy - half, 0), min(iy + half + 1, shape[0])),
            slice(max(ix - half, 0), min(ix + half + 1, shape[1])))


def _bounding_window(shape, ys: np.ndarray, xs: np.ndarray, margin: int) -> tuple[slice, slice]:
    return (slice(max(int(ys.min()) - margin, 0), min(int(ys.max()) + margin + 1, shape[0])),
            slice(max(int(xs.min()) - margin, 0), min(int(xs.max()) + margin + 1, shape[1])))


def _contains(win: tuple[slice, slice], inner: tuple[slice, slice]) -> bool:
    return all(w.start <= i.start and i.stop <= w.stop for w, i in zip(win, inner))


def _lit_image(band: np.ndarray, dark: np.ndarray, lit: np.ndarray) -> np.ndarray:
    """The dark-subtracted band image where ``lit``, 0 elsewhere (float64, one pass)."""
    out = np.zeros(band.shape)
    np.subtract(band, dark, out=out, where=lit)
    return out


def _peak_pixel(a: np.ndarray) -> tuple[int, int]:
    """The pixel of the largest 3 x 3 mean of the lit image ``a`` (:func:`_lit_image`), as
    ``argmax(uniform_filter(a, 3))`` of the whole image, without filtering it all.

    The mean is filtered in a window around the brightest lit pixel; its best value S bounds the answer:
    a pixel whose 3 x 3 mean reaches S has a neighbour (or is one) of at least S, so every candidate lies
    within one pixel of {a >= S}. When that set (grown by one pixel) is inside the window, the
    window's argmax is the whole image's (the first in raster order among equals, as argmax); otherwise
    the window grows to hold it.
    """
    iy, ix = np.unravel_index(int(np.argmax(a)), a.shape)
    win = _window(a.shape, iy, ix, SPOT_WINDOW_HALF_PX)
    while True:
        # the 3 x 3 means of the window's pixels need their neighbours: filter the window grown by one
        # pixel (the image's own edge reflected as uniform_filter does for the whole image)
        ext = (slice(max(win[0].start - 1, 0), min(win[0].stop + 1, a.shape[0])),
               slice(max(win[1].start - 1, 0), min(win[1].stop + 1, a.shape[1])))
        sm = ndimage.uniform_filter(a[ext], 3)[win[0].start - ext[0].start:win[0].stop - ext[0].start,
                                              win[1].start - ext[1].start:win[1].stop - ext[1].start]
        wy, wx = np.unravel_index(int(np.argmax(sm)), sm.shape)
        best = float(sm[wy, wx])
        if win == (slice(0, a.shape[0]), slice(0, a.shape[1])):
            break
        if best <= 0.0:                    # no bound: every pixel is a candidate
            win = (slice(0, a.shape[0]), slice(0, a.shape[1]))
            continue
        # the bound, lowered by far more than the filter's rounding so that no candidate is missed
        ys, xs = np.nonzero(a >= best * (1.0 - 1e-9))
        if not ys.size:                    # best is the filter's rounding of an unlit window: no bound either
            win = (slice(0, a.shape[0]), slice(0, a.shape[1]))
            continue
        need = _bounding_window(a.shape, ys, xs, 1)
        if _contains(win, need):
            break
        win = (slice(min(win[0].start, need[0].start), max(win[0].stop, need[0].stop)),
               slice(min(win[1].start, need[1].start), max(win[1].stop, need[1].stop)))
    return win[0].start + int(wy), win[1].start + int(wx)


def _find_spot(band: np.ndarray, dark: np.ndarray, lit: np.ndarray, level: float, peak_px: tuple[int, int]):
    """Centroid (x, y) and pixels (rows, columns) of the port spot in ``band`` minus ``dark``: the lit
    pixels above ``level`` times its peak (the brightest pixel beside ``peak_px``, the largest 3 x 3 mean
    of the lit image, :func:`_peak_pixel`) connected to that peak, and their flux-weighted centroid.

    Dark-subtracted and labelled in a window around the peak, grown until the spot touches no edge of it
    that is not the image's own: the same pixels and values as in the whole image.
    """
    iy, ix = peak_px
    near = (slice(max(iy - 1, 0), iy + 2), slice(max(ix - 1, 0), ix + 2))
    peak = (band[near].astype(float) - dark[near]).max()
    whole = (slice(0, band.shape[0]), slice(0, band.shape[1]))
    half = SPOT_WINDOW_HALF_PX
    while True:
        win = _window(band.shape, iy, ix, half)
        w_img = band[win].astype(float) - dark[win]
        lab, _ = ndimage.label((w_img > level * peak) & lit[win])
        ly, lx = iy - win[0].start, ix - win[1].start
        k = lab[ly, lx]
        if not k and win != whole:
            # the peak itself below the level: the 3 x 3 fallback's label order is the whole image's
            half = max(band.shape)
            continue
        k = k if k else lab[max(ly - 1, 0):ly + 2, max(lx - 1, 0):lx + 2].max()
        comp = lab == k
        edges = ((comp[0].any() and win[0].start > 0) or (comp[-1].any() and win[0].stop < band.shape[0])
                 or (comp[:, 0].any() and win[1].start > 0) or (comp[:, -1].any() and win[1].stop < band.shape[1]))
        if not edges or win == whole:
            break
        half *= 2
    y, x = np.nonzero(comp)
    w = w_img[comp]
    y, x = y + win[0].start, x + win[1].start
    cx, cy = float(np.sum(w * x) / np.sum(w)), float(np.sum(w * y) / np.sum(w))
    return cx, cy, (y, x)


def _setting_masks(bands: dict[str, np.ndarray], darks: dict[str, np.ndarray], lit: np.ndarray, r_avg: float,
                   sigma_psf: float, cfg: dict, noise_3x3_dn: float):
    """One setting's pixels in its first frame's ``bands`` minus the ``darks``, as flat indices of the
    band image: the averaging circle of radius ``r_avg`` around the G spot's centroid, the halo annulus,
    the port's own pixels in every band, the halo weights of those pixels, and the centroid. Computed in
    a window that holds the circle, the port and the annulus: the same pixels as over the whole image.

    Returns (those, "") or, for a spot that cannot be measured, (None, the reason): no light above the
    noise in the lit field (the brightest 3 x 3 mean of the lit G image at most ``rolloff.min_spot_snr``
    times ``noise_3x3_dn``, the noise of such a mean in one dark-subtracted frame), or a G spot whose light
    rises beyond the lit field's edge (:func:`_peak_beside_field`: the wing of a port outside the field)."""
    shape = bands["G"].shape
    lit_g = _lit_image(bands["G"], darks["G"], lit)
    peak_g = _peak_pixel(lit_g)
    light = _window_mean(lit_g, peak_g)
    if not light > cfg["min_spot_snr"] * noise_3x3_dn:
        return None, (f"no light above the noise in the lit field (best 3 x 3 mean {light:.3g} DN above dark, "
                      f"rolloff.min_spot_snr {cfg['min_spot_snr']:g} x {noise_3x3_dn:.3g} DN)")
    peaks = {b: _peak_pixel(_lit_image(bands[b], darks[b], lit)) if b != "G" else peak_g for b in BANDS}
    cx, cy, (gy, gx) = _find_spot(bands["G"], darks["G"], lit, cfg["spot_threshold_fraction"], peaks["G"])
    centroid = _centroid_sums(bands["G"], darks["G"], gy, gx, cx, cy)
    centroid["peak_px"] = peaks["G"]
    inside, outside = _peak_beside_field(bands["G"], darks["G"], lit, gy, gx)
    if outside > inside:
        return None, (f"port beyond the edge of the lit field (near x {cx:.1f}, y {cy:.1f} its light rises outside "
                      f"the field, to {outside:.3g} DN against {inside:.3g} DN inside): is the geometry's image "
                      f"circle short?")
    # the port's own pixels in every band: the R and B sites sit a quarter band pixel off the
    # G sites, so at the disc's edge R or B pixels are lit where G is not; the halo column must
    # convolve all of each band's flux, not only the part inside the G spot
    parts = [_find_spot(bands[b], darks[b], lit, cfg["halo_spot_fraction"], peaks[b])[2] for b in BANDS]
    sy, sx = np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    r_in = float(np.max(np.hypot(sx - cx, sy - cy))) + cfg["halo_gap_px"]
    reach = int(np.ceil(max(r_in + cfg["halo_width_px"], r_avg))) + 2
    win = _bounding_window(shape, np.array([int(round(cy)), sy.min(), sy.max()]),
                           np.array([int(round(cx)), sx.min(), sx.max()]), reach)
    yy = np.arange(win[0].start, win[0].stop)[:, None]
    xx = np.arange(win[1].start, win[1].stop)[None, :]
    dist = np.hypot(xx - cx, yy - cy)
    circle = dist <= r_avg
    if not circle.any():
        circle = dist <= dist.min() + 1e-9
    annulus = (dist > r_in) & (dist <= r_in + cfg["halo_width_px"]) & lit[win]
    spot = np.zeros(dist.shape, bool)
    spot[sy - win[0].start, sx - win[1].start] = True

    def flat(mask):
        my, mx = np.nonzero(mask)
        return (my + win[0].start) * shape[1] + (mx + win[1].start)

    # pixel indices, not images: a setting keeps a few hundred numbers, never a frame
    return (flat(circle), flat(annulus), flat(spot), _halo_weights(spot, annulus, sigma_psf), (cx, cy), centroid), ""


def _centroid_sums(band: np.ndarray, dark: np.ndarray, ys: np.ndarray, xs: np.ndarray, cx: float,
                   cy: float) -> dict[str, float]:
    """The sums over the spot's pixels (``ys``, ``xs``; weights w = ``band`` - ``dark``) that the pixel noise's
    share of the flux-weighted centroid's variance needs once the noise model is known (:func:`centroid_sigma`):
    W = sum w, sum dx^2 w, sum dx^2 (and the same in y), dx = x - cx. Five numbers, never an image: the noise
    model var = k S + r is fitted only after the frames have streamed."""
    w = band[ys, xs].astype(float) - dark[ys, xs]
    dx2, dy2 = (xs - cx) ** 2, (ys - cy) ** 2
    return {"w_sum": float(w.sum()), "dx2_w": float(dx2 @ np.clip(w, 0.0, None)), "dx2": float(dx2.sum()),
            "dy2_w": float(dy2 @ np.clip(w, 0.0, None)), "dy2": float(dy2.sum()), "n_pix": int(w.size)}


def _window_mean(a: np.ndarray, px: tuple[int, int]) -> float:
    """Mean of ``a`` over the 3 x 3 pixels around ``px`` (fewer at the image's edge)."""
    iy, ix = px
    return float(a[max(iy - 1, 0):iy + 2, max(ix - 1, 0):ix + 2].mean())


def _peak_beside_field(band: np.ndarray, dark: np.ndarray, lit: np.ndarray, ys: np.ndarray,
                       xs: np.ndarray) -> tuple[float, float]:
    """The spot's peak (largest ``band`` minus ``dark`` over its pixels ``ys``, ``xs``) and the largest over the
    pixels outside ``lit`` next to them (8-neighbours; -inf when the spot does not touch the field's edge),
    computed in the spot's bounding window only.

    A spot whose light rises beyond the edge is the wing of a port outside the lit field (a short image circle),
    not a port: its pixels hold a few DN of the port's light (seed 16 of the tiny scale: 14-20 DN against the
    port's 8,000)."""
    win = _bounding_window(band.shape, ys, xs, 1)
    img = band[win].astype(float) - dark[win]
    spot = np.zeros(img.shape, bool)
    spot[ys - win[0].start, xs - win[1].start] = True
    near = ndimage.binary_dilation(spot, np.ones((3, 3), bool)) & ~lit[win]
    outside = float(img[near].max()) if near.any() else -np.inf
    return float(img[spot].max()), outside


def _deg_per_px(theta: np.ndarray) -> float:
    """Angular size of a pixel near the optical axis, from the theta map's gradient."""
    gy, gx = np.gradient(np.nan_to_num(theta, nan=0.0))
    near = np.isfinite(theta) & (theta < 20.0)
    return float(np.median(np.hypot(gx, gy)[near])) if near.any() else float("nan")


def reduce_rolloff(dataset: Dataset, geometry: dict[str, xr.Dataset], config: dict,
                   progress: bool = False, corners: FrameCorners | None = None,
                   linearity: dict[str, xr.Dataset] | None = None) -> dict:
    """Stream the roll-off frames once (dark frames first).

    With a lens's linearity artefact every dark-subtracted pixel the stage
    measures (the averaging circle, the halo annulus, the port's own pixels) goes through the chain's response
    steps that artefact fitted, the inverse nonlinearity and the flat field
    (:class:`pipeline.radiometry.response.PixelResponse`): a roll-off point is the ratio of the light at an
    angle to that on the axis, and a sensor that bends its bright readings makes that ratio too high (beta
    0.047 at F = 15,600 DN, the axis at 11,000 DN: g at 55 degrees 0.6 % high); with the nonlinearity the
    same pixels at beta + sigma_beta are kept as well, for its uncertainty (:func:`compute`).

    Parameters
    ----------
    dataset : pipeline.io.dataset.Dataset
        The dataset; its ``rolloff`` experiment's frames are read (and immersion/water.yaml when present).
    geometry : dict[str, xarray.Dataset]
        Lens -> its geometry artefact (field angle maps per medium and band).
    config : dict
        The run's configuration (section ``rolloff``).
    progress : bool, default False
        Show a progress bar.
    corners : pipeline.radiometry.unlit_corners.FrameCorners or None, optional
        When given, records each signal frame's unlit corners against the dark model.
    linearity : dict[str, xarray.Dataset] or None, optional
        Lens -> its linearity artefact, whose response steps are applied.

    Returns
    -------
    dict
        ``acc`` ((lens, medium, azimuth, angle, band) -> one dict per frame: the dark-subtracted, linearised
        pixel values of the circle in DN, annulus and halo means in DN, saturation, exposure and ISO),
        ``masks`` and ``dropped`` (per setting: its pixel sets, or why its spot cannot be measured), ``static``
        ((lens, medium) -> dark levels and variances, field angle maps), ``inputs``, ``water`` (the tank's
        water or None), ``response_corrections`` and ``beta_shift``.

    Raises
    ------
    pipeline.errors.InputError
        If the linearity artefact's flat field does not match the band images.
    """
    cfg = config[STAGE]
    frames = dataset.frames(STAGE)
    order = pd.concat([frames[frames["kind"] == "dark"], frames[frames["kind"] == "signal"]])
    dark = defaultdict(RunningMoments)          # (lens, medium, band) -> moments
    inputs = {}
    setting_masks = {}                          # (lens, medium, az, angle) -> (circle, annulus, spot, centre)
    dropped = {}                                # (lens, medium, az, angle) -> why its spot cannot be measured
    acc = defaultdict(list)                     # (lens, medium, az, angle, band) -> per-frame dicts
    static = {}
    corners = corners if corners is not None else FrameCorners(None, dataset.projection, 1.0)
    linearity = linearity or {}
    response = {(lens, band): PixelResponse(linearity.get(lens), band) for lens in dataset.lenses for band in BANDS}
    shift = any(r.beta_sigma > 0 for r in response.values())
    for file_index, dec in enumerate(iter_frames(dataset, STAGE, order, progress=progress)):
        row = dec.row
        inputs[row["file"]] = dec.raw.sha256
        medium = row["medium"]
        if row["kind"] == "dark":
            lenses = list(dataset.lenses) if row["lens"] == "both" else [row["lens"]]
            for lens in lenses:
                for band in BANDS:
                    dark[(lens, medium, band)].add(dec.lenses[lens].bands[band])
            continue
        lens = row["lens"]
        images = dec.lenses[lens]
        corners.add(lens, images, dec.raw, row.get("temperature_c", np.nan), file_index=file_index, medium=medium,
                    azimuth_deg=float(row["azimuth_deg"]), angle_deg=float(row["angle_deg"]))
        if (lens, medium) not in static:
            geo = geometry[lens].sel(medium=medium)
            theta = geo["theta_deg"].sel(band="G").values.astype(float)
            half = float(geo["half_fov_deg"].sel(band="G"))
            lit = np.isfinite(theta) & (theta <= half - 1.0)
            deg_per_px = _deg_per_px(theta)
            static[(lens, medium)] = {
                "lit": lit, "theta": geo["theta_deg"].values, "phi": geo["phi_deg"].values,
                "r_avg": max(1.0, cfg["spot_radius_deg"] / deg_per_px),
                "circle_px": float(np.sqrt(np.sum(np.isfinite(theta) & (theta <= half)) / np.pi)),
                "dark": {b: dark[(lens, medium, b)].mean() for b in BANDS},
                "dark_var": {b: float(np.mean(dark[(lens, medium, b)].variance())) for b in BANDS},
                "n_dark": dark[(lens, medium, "G")].n,
                "deg_per_px": deg_per_px,
                # the same pixels' field angles in air: the closure maps each water point to its air angle
                "theta_air": (geometry[lens].sel(medium="air")["theta_deg"].values
                              if medium == "water" and "air" in geometry[lens]["medium"].values else None),
            }
            if medium == "water" and static[(lens, medium)]["theta_air"] is None:
                raise InputError(dataset.root / STAGE / "frames.csv", f"in-water roll-off frames of lens {lens}, but "
                                 "its geometry artefact has no air model: the in-water closure needs both media")
            air_geo = geometry[lens].sel(medium="air") if medium == "water" else None
            # the air model's stated field-angle uncertainty per pixel, if any
            static[(lens, medium)]["theta_air_sigma"] = (air_geo["theta_deg_sigma"].values
                                                         if air_geo is not None and "theta_deg_sigma" in air_geo else None)
            static[(lens, medium)]["centre"] = _centre_geometry(geometry[lens], medium)
            static[(lens, medium)]["theta_sigma"] = geo["theta_deg_sigma"].values if "theta_deg_sigma" in geo else None
            static[(lens, medium)]["centre_air"] = (_centre_geometry(geometry[lens], "air") if air_geo is not None
                                                    else None)
            if static[(lens, medium)]["theta_air"] is not None:
                static[(lens, medium)]["deg_per_px_air"] = _deg_per_px(
                    geometry[lens].sel(medium="air")["theta_deg"].sel(band="G").values.astype(float))
            if static[(lens, medium)]["n_dark"] < 2:
                raise InputError(dataset.root / STAGE / "frames.csv", f"needs at least two dark frames in {medium}")
        st = static[(lens, medium)]
        key = (lens, medium, float(row["azimuth_deg"]), float(row["angle_deg"]))
        if key not in setting_masks and key not in dropped:
            # the first frame of a setting finds its pixels
            masks, reason = _setting_masks(images.bands, st["dark"], st["lit"], st["r_avg"],
                                           cfg["stray_light_psf_sigma_fraction"] * st["circle_px"], cfg,
                                           np.sqrt(st["dark_var"]["G"]) / 3.0)
            if masks is None:
                dropped[key] = reason
                log.warning("rolloff %s %s azimuth %g deg, angle %g deg (%s): setting dropped: %s",
                            lens, medium, key[2], key[3], row["file"], reason)
            else:
                setting_masks[key] = masks
        if key in dropped:
            continue
        circle, annulus, spot, weights, first_centroid, centroid = setting_masks[key]
        # the G spot's centroid in this frame, the same cut around the first frame's peak (the first frame's own
        # is the setting's): the frames' scatter measures the centroid's noise, the cut's flips included
        frame_centroid = (first_centroid if key + ("G",) not in acc else
                          _find_spot(images.bands["G"], st["dark"]["G"], st["lit"], cfg["spot_threshold_fraction"],
                                     centroid["peak_px"])[:2])
        for band in BANDS:
            # dark-subtracted at the setting's pixels only (the same values as the whole image's there), then
            # the response steps the linearity stage fitted
            img, dk = images.bands[band].ravel(), st["dark"][band].ravel()
            resp = response[(lens, band)]
            if resp.flat is not None and resp.flat.size != img.size:
                raise InputError(dataset.root / STAGE / "frames.csv", f"lens {lens} band {band}: the linearity "
                                 f"artefact's flat field has {resp.flat.size} pixels, the band image {img.size}")
            raw_circle = img[circle].astype(float) - dk[circle]
            raw_ann = img[annulus].astype(float) - dk[annulus]
            raw_spot = img[spot].astype(float) - dk[spot]
            entry = {"saturated": bool(images.saturated[band].ravel()[circle].any()),
                     "exposure_s": float(dec.raw.exposure_s), "iso": float(dec.raw.iso)}
            if band == "G":
                entry["spot_centroid_px"] = frame_centroid
            for suffix, k in (("", 0.0), ("_beta", 1.0)) if shift else (("", 0.0),):
                ann = resp(raw_ann, annulus, k)
                entry["circle" + suffix] = resp(raw_circle, circle, k)
                entry["annulus_mean" + suffix] = float(ann.mean()) if annulus.size else np.nan
                entry["halo" + suffix] = float(weights @ resp(raw_spot, spot, k)) if annulus.size else 0.0
            acc[key + (band,)].append(entry)
    water_file = dataset.root / "immersion" / "water.yaml"
    water = read_water(dataset) if water_file.exists() else None
    corrections = sorted({e for r in response.values() for e in r.corrections})
    return {"acc": acc, "masks": setting_masks, "static": static, "inputs": inputs, "water": water,
            "dropped": dropped, "response_corrections": corrections, "beta_shift": shift}


def _centre_geometry(geo: xr.Dataset, medium: str) -> dict | None:
    """Per band of one medium's geometry: the fitted model and the covariance of its principal point, for the
    correlated centre term (:mod:`pipeline.geometry.centre_shift`); None for a geometry without the fisheye
    model's covariance (a rectilinear region, or maps without a fit), whose spots have only
    ``rolloff.field_angle_sigma_px`` as independent noise."""
    if "geometry_parameter_covariance" not in geo or geo.attrs.get("projection", "fisheye") != "fisheye":
        return None
    names = [str(n) for n in geo["geometry_parameter"].values]
    if names[:2] != ["xc_px", "yc_px"]:
        return None
    out = {}
    for band in BANDS:
        cov = geo["geometry_parameter_covariance"].sel(medium=medium, band=band).values[:2, :2]
        if not np.all(np.isfinite(cov)):
            return None
        out[band] = {"model": model_from_dataset(geo, medium, band), "cov": cov}
    return out


def _halo_weights(spot: np.ndarray, annulus: np.ndarray, sigma_px: float) -> np.ndarray:
    """Weights w such that w . spot_values is the mean over the annulus of the spot flux
    convolved with a unit-sum Gaussian of width ``sigma_px`` (the stray-light model kernel)."""
    sy, sx = np.nonzero(spot)
    ay, ax = np.nonzero(annulus)
    if not ay.size or not sy.size:
        return np.zeros(sy.size)
    d2 = (sy[:, None] - ay[None, :]) ** 2 + (sx[:, None] - ax[None, :]) ** 2
    kernel = np.exp(-0.5 * d2 / sigma_px**2) / (2 * np.pi * sigma_px**2)
    kernel[d2 > (4 * sigma_px) ** 2] = 0.0
    return kernel.mean(axis=1)


def setting_table(reduced: dict, config: dict, beta_shift: bool = False) -> pd.DataFrame:
    """One row per setting and band; with ``beta_shift`` the pixels linearised at beta + sigma_beta.

    Parameters
    ----------
    reduced : dict
        What :func:`reduce_rolloff` returned.
    config : dict
        The run's configuration.
    beta_shift : bool, default False
        Read the pixels linearised at beta + sigma_beta instead of beta.

    Returns
    -------
    pandas.DataFrame
        Per (lens, band, medium, azimuth, angle): ``signal_dn`` (mean dark-subtracted signal over the circle,
        DN), ``diff_var_dn2`` (frame-to-frame variance, DN^2), ``theta_deg`` and ``phi_deg`` (the spot's field
        angle and azimuth, degree) with their uncertainties and gradients, annulus and halo means (DN), dark
        variance (DN^2), the spot's position (band pixels), ``saturated``, ``exposure_s`` and ``iso``.
    """
    sfx = "_beta" if beta_shift else ""
    rows = []
    for key, frames in reduced["acc"].items():
        lens, medium, az, angle, band = key
        st = reduced["static"][(lens, medium)]
        circle, annulus, _, _, (cx, cy), centroid = reduced["masks"][key[:4]]
        # the G centroid of every frame of the setting, the same cut: its scatter about the setting's mean
        each = np.array([f["spot_centroid_px"] for f in reduced["acc"][key[:4] + ("G",)]], float).reshape(-1, 2)
        frame_ss = np.sum((each - each.mean(axis=0)) ** 2, axis=0)
        bi = BANDS.index(band)
        theta = st["theta"][bi].ravel()[circle]
        phi = np.radians(st["phi"][bi].ravel()[circle])
        stack = np.array([f["circle" + sfx] for f in frames])
        m = len(frames)
        theta_air = (float(np.mean(st["theta_air"][bi].ravel()[circle])) if st.get("theta_air") is not None
                     else np.nan)
        theta_air_sigma = (float(np.sqrt(np.nanmean(st["theta_air_sigma"][bi].ravel()[circle] ** 2)))
                           if st.get("theta_air_sigma") is not None else np.nan)
        spot_theta = float(ndimage.map_coordinates(np.nan_to_num(st["theta"][bi]), [[cy], [cx]], order=1)[0])
        # the principal point's share of the field angle's error: d theta / d (xc, yc) at the spot's pixels
        width = st["theta"].shape[-1]
        pix_u, pix_v = (circle % width).astype(float), (circle // width).astype(float)
        grad = (centre_theta_gradient(st["centre"][band]["model"], pix_u, pix_v) if st.get("centre")
                else np.full(2, np.nan))
        grad_air = (centre_theta_gradient(st["centre_air"][band]["model"], pix_u, pix_v) if st.get("centre_air")
                    else np.full(2, np.nan))
        theta_sigma = (float(np.sqrt(np.nanmean(st["theta_sigma"][bi].ravel()[circle] ** 2)))
                       if st.get("theta_sigma") is not None else np.nan)
        rows.append({
            "lens": lens, "band": band, "medium": medium, "azimuth_deg": az, "angle_deg": angle,
            "n_frames": m, "n_pix": int(circle.size), "n_annulus": int(annulus.size),
            "signal_dn": float(stack.mean()),
            "diff_var_dn2": float(np.mean(stack.var(axis=0, ddof=1))) if m > 1 else np.nan,
            "theta_deg": float(np.mean(theta)), "theta_air_deg": theta_air, "deg_per_px_air": st.get("deg_per_px_air", np.nan),
            "theta_air_sigma_deg": theta_air_sigma, "theta_sigma_deg": theta_sigma,
            "theta_centre_grad_x_deg_per_px": grad[0], "theta_centre_grad_y_deg_per_px": grad[1],
            "theta_air_centre_grad_x_deg_per_px": grad_air[0], "theta_air_centre_grad_y_deg_per_px": grad_air[1],
            "phi_deg": float(np.degrees(np.arctan2(np.mean(np.sin(phi)), np.mean(np.cos(phi))))),
            "spot_theta_deg": spot_theta, "spot_x_px": cx, "spot_y_px": cy,
            "spot_weight_sum_dn": centroid["w_sum"], "spot_dx2_weight_dn": centroid["dx2_w"],
            "spot_dx2_px2": centroid["dx2"], "spot_dy2_weight_dn": centroid["dy2_w"], "spot_dy2_px2": centroid["dy2"],
            "spot_n_pix": centroid["n_pix"], "spot_n_centroid_frames": len(each),
            "spot_frames_ss_x_px2": frame_ss[0], "spot_frames_ss_y_px2": frame_ss[1],
            "annulus_dn": float(np.mean([f["annulus_mean" + sfx] for f in frames])),
            "halo_raw_dn": float(np.mean([f["halo" + sfx] for f in frames])),
            "saturated": any(f["saturated"] for f in frames),
            "dark_var_dn2": st["dark_var"][band], "n_dark": st["n_dark"], "dark_var_g_dn2": st["dark_var"]["G"],
            "deg_per_px": st["deg_per_px"],
            # the frames' settings (tags): the cross-experiment closure turns the on-axis DN into DN per second
            "exposure_s": float(np.mean([f["exposure_s"] for f in frames])),
            "iso": float(np.mean([f["iso"] for f in frames])),
        })
    return pd.DataFrame(rows)


def noise_model(tab: pd.DataFrame) -> dict[str, tuple[float, float]]:
    """Per band: pixel variance = k * signal + r (pooled photon transfer).

    r is the temporal variance of the dark frames (the zero-signal point); k is
    fitted to the frame-to-frame variances of the settings, iteratively
    reweighted by 1 / model^2 (weights from the noisy estimates themselves
    would favour the low ones).

    Parameters
    ----------
    tab : pandas.DataFrame
        The setting table of :func:`setting_table` (``band``, ``signal_dn``, ``diff_var_dn2``,
        ``dark_var_dn2``, ``saturated``).

    Returns
    -------
    dict[str, tuple[float, float]]
        Band -> (k in DN, r in DN^2).
    """
    out = {}
    for band, g in tab.groupby("band"):
        r = float(g["dark_var_dn2"].mean())
        g = g[np.isfinite(g["diff_var_dn2"]) & ~g["saturated"]]
        x = g["signal_dn"].clip(lower=0).to_numpy()
        v = g["diff_var_dn2"].to_numpy() - r
        k = float(np.sum(x * v) / np.sum(x * x))
        for _ in range(5):
            w = 1.0 / np.maximum(k * x + r, 1e-6) ** 2
            k = float(np.sum(w * x * v) / np.sum(w * x * x))
        out[band] = (k, r)
    return out


# ----------------------------------------------------------------------------- fitting
def _poly_columns(theta_deg: np.ndarray) -> dict[str, np.ndarray]:
    """Base columns ``x_p0`` .. ``x_p8``: Eq. (13)'s design matrix in theta / THETA_SCALE_DEG."""
    a = rolloff_design_matrix(theta_deg, THETA_SCALE_DEG)
    return {f"x_p{p}": a[..., k] for k, p in enumerate(ROLLOFF_POWERS)}


def _centre_terms(tab: pd.DataFrame, slope: np.ndarray, static: dict, which: str, grad_cols) -> tuple:
    """The whitened principal-point columns of each row (n, 2) and the variance of theta they stand for (n,),
    NaN where the geometry has no centre covariance: the slope (per degree) of the fitted quantity times
    d theta / d (xc, yc) at the row's pixels times L, L L^T the centre's covariance of that band image
    (``which``: "centre" the spot's own geometry, "centre_air" the air model of a water point)."""
    n = len(tab)
    cols, var = np.zeros((n, 2)), np.full(n, np.nan)
    grad = tab[list(grad_cols)].to_numpy(float)
    slope = np.asarray(slope, float)
    for i, (lens, medium, band) in enumerate(zip(tab["lens"], tab["medium"], tab["band"])):
        geo = static[(lens, medium)].get(which)
        if not geo or not np.all(np.isfinite(grad[i])) or not np.isfinite(slope[i]):
            continue
        cov = geo[band]["cov"]
        cols[i] = centre_columns(slope[i:i + 1], grad[i:i + 1], centre_root(cov))[0]
        var[i] = centre_variance(grad[i:i + 1], cov)[0]
    return cols, var


def _centre_prior_rows(rows: pd.DataFrame) -> pd.DataFrame:
    """The prior of the whitened centre shift as two pseudo-measurements per group, u_k = 0 +/- 1: the
    geometry stage's statement of how well it knows the principal point, so that every fit of the table
    (the stage's and the diagnostics') can move the centre only as far as that covariance allows. Rows of
    kind ``centre_prior``: no effect column touches them (the effects' columns are those of the spots or
    the halo), their base columns are zero but their own centre column."""
    out = []
    for _, g in rows.groupby("group", sort=True):
        for col in CENTRE_COLUMNS:
            r = g.iloc[[0]].copy()
            for c in [c for c in r.columns if c.startswith("x_")]:
                r[c] = 1.0 if c == col else 0.0
            r = r.assign(kind=CENTRE_PRIOR_KIND, value_dn=0.0, sigma_dn=1.0, pred_dn=0.0, used=1, saturated=False,
                         spot_x_px=np.nan, spot_y_px=np.nan)
            if "halo_column_dn" in r:
                r["halo_column_dn"] = 0.0
            out.append(r)
    return pd.concat(out, ignore_index=True) if out else rows.iloc[:0]


def _fit_setting(obs: pd.DataFrame, effects: list[str]):
    """WLS of the setting table: even polynomial per group plus the model's effect columns (iterated)."""
    used = obs["used"].to_numpy(bool)
    y, s = obs["value_dn"].to_numpy(float), obs["sigma_dn"].to_numpy(float)
    X, names = base_design(obs)
    obs["pred_dn"] = 0.0
    fit = wls(y[used], s[used], X[used])
    obs.loc[used, "pred_dn"] = X[used] @ fit.coef[:X.shape[1]]
    obs.loc[~used, "pred_dn"] = X[~used] @ fit.coef[:X.shape[1]]
    extra = []
    for _ in range(4):
        extra = [(e, get_effect(e).columns(STAGE, "setting", obs)) for e in effects if e in SETTING_EFFECTS]
        extra = [(e, c) for e, c in extra if c is not None]
        if not extra:
            break
        Xf = np.hstack([X] + [c for _, c in extra])
        fit = wls(y[used], s[used], Xf[used])
        obs["pred_dn"] = X @ fit.coef[:X.shape[1]]    # base prediction (effect columns multiply it)
    Xf = np.hstack([X] + [c for _, c in extra]) if extra else X
    pred = Xf @ fit.coef
    return fit, names, extra, pred, X


def water_indices(reduced: dict, config: dict) -> tuple[dict[str, float], float]:
    """n_w per band (Quan and Fry at the band's nominal wavelength) and n_g.

    The tank's water from immersion/water.yaml, else ``rolloff.water_temperature_c`` and
    ``rolloff.water_salinity_psu``.

    Parameters
    ----------
    reduced : dict
        What :func:`reduce_rolloff` returned (its ``water``).
    config : dict
        The run's configuration (section ``rolloff``).

    Returns
    -------
    n_w : dict[str, float]
        Band -> the water's refractive index.
    n_g : float
        The refractive index of the lens's front surface (``rolloff.front_surface_index``).
    """
    cfg = config[STAGE]
    water = reduced.get("water") or {"temperature_c": cfg["water_temperature_c"],
                                     "salinity_psu": cfg["water_salinity_psu"]}
    n_w = {b: float(refractive_index_water(NOMINAL_WAVELENGTH_NM[b], water["temperature_c"], water["salinity_psu"]))
           for b in BANDS}
    return n_w, float(cfg["front_surface_index"])


def _water_closure(wat: pd.DataFrame, air_fits: dict, n_w: dict, n_g: float, max_air_deg: float,
                   field_angle_sigma_px: float, static: dict) -> pd.DataFrame:
    """The in-water roll-off predicted from the in-air fit and the immersion physics, per lens/band.

    Each water point (its own normalisation, the water fit's a0) is predicted as
    g_air(theta_a) * water_rolloff_factor(theta_a, theta_w): theta_a the same pixels' field angle in
    the geometry artefact's air model, the factor the outer surface's Fresnel transmissions
    (radiometry.immersion_rolloff). No shape parameter is fitted: the base column ``x_scale`` is the
    prediction itself, one free scale per group for the normalisation. The prediction's uncertainty
    (the air fit's covariance at theta_a, and the air model's field-angle uncertainty through the air
    curve's slope: the geometry artefact's theta_deg_sigma, else ``rolloff.field_angle_sigma_px``) is
    added to the point's in quadrature; points whose theta_a lies beyond the air measurements are not used (no extrapolation of the air fit).
    """
    out = []
    for (lens, band), g in wat.groupby(["lens", "band"]):
        coef_air, cov_air = air_fits[(lens, band)]
        theta_a = g["theta_air_deg"].to_numpy(float)
        ok = np.isfinite(theta_a) & (theta_a <= max_air_deg)
        ta = np.where(ok, theta_a, 0.0)
        factor = water_rolloff_factor(ta, g["theta_deg"].to_numpy(float), n_w[band], n_g)
        g_air, sig_air = evaluate_rolloff(coef_air, ta, cov_air)
        # field-angle uncertainty of theta_a: the geometry artefact's stated theta_deg_sigma at those pixels
        # where it has one, else rolloff.field_angle_sigma_px in air band pixels
        sig_theta = g["theta_air_sigma_deg"].to_numpy(float)
        # the air model's principal point: common to every point of the lens and band (nuisance columns with
        # their prior, as in the setting table). The stated theta uncertainty stays in each point's sigma as
        # well: its radial share is correlated too, but the closure's one scale does not absorb it (it would
        # mimic immersion_angle); the centre's share is so counted twice here, on the safe side
        slope_air = rolloff_slope(coef_air, ta)
        centre_cols, centre_var = _centre_terms(g, slope_air * factor, static, "centre_air",
                                                ("theta_air_centre_grad_x_deg_per_px",
                                                 "theta_air_centre_grad_y_deg_per_px"))
        has_centre = np.isfinite(centre_var) & np.isfinite(sig_theta)
        sig_theta = np.where(np.isfinite(sig_theta), sig_theta, field_angle_sigma_px * g["deg_per_px_air"].to_numpy(float))
        sig_air = np.hypot(sig_air, np.abs(slope_air) * sig_theta)
        pred = g_air * factor
        t = g.assign(x_scale=pred, pred_dn=pred, water_factor=factor, air_prediction_sigma=sig_air * factor,
                     **{c: np.where(has_centre & ok, centre_cols[:, k], 0.0) for k, c in enumerate(CENTRE_COLUMNS)})
        t["sigma_dn"] = np.hypot(t["sigma_dn"], sig_air * factor)
        t["used"] = (t["used"].to_numpy(bool) & ok).astype(int)
        t["group"] = lens + "/" + band + "/water_from_air"
        out.append(t)
        if np.any(has_centre & ok):
            out.append(_centre_prior_rows(t[has_centre & ok]))
    return pd.concat(out, ignore_index=True) if out else pd.DataFrame()


#: the per-setting sums of :func:`_centroid_sums` and of the frames' centroids that :func:`_add_centroid_sigma`
#: turns into the centroid's uncertainty (not kept in the artefact)
_CENTROID_SUMS = ("spot_weight_sum_dn", "spot_dx2_weight_dn", "spot_dx2_px2", "spot_dy2_weight_dn", "spot_dy2_px2",
                  "spot_frames_ss_x_px2", "spot_frames_ss_y_px2", "dark_var_g_dn2")


def _add_centroid_sigma(tab: pd.DataFrame, noise_g: tuple[float, float]) -> None:
    """The G spot centroid's standard uncertainty per axis, ``spot_x_sigma_px`` and ``spot_y_sigma_px`` (module
    docstring, "the centroid's uncertainty"), and its three terms per axis (``spot_centroid_<term>_<axis>_px``):

    * ``pixel``: the pixels' noise through the flux-weighted centroid, sum (x_i - cx)^2 var_i / W^2 with
      var_i = k w_i + r + the dark mean's variance (the G noise model ``noise_g`` = (k, r), known only now:
      the setting keeps the sums, :func:`_centroid_sums`);
    * ``cut``: the frames' scatter of the centroid (each frame through the same cut) pooled over the settings
      of a lens, medium and azimuth plane, beyond the pixel term's mean: the pixels that pass the cut or not
      with the noise (a pixel at the threshold moves the centroid by its weight times its distance, which the
      linear pixel term does not hold); 0 with one frame a setting;
    * ``grid``: the pixel grid's sampling of a sharp-edged spot, 1 / (12 pi n R), R = sqrt(N / pi) the radius
      (band pixels) of the cut's N pixels, n = :data:`G_SITES_PER_BAND_PIXEL`: the cut's edge falls at a
      uniform position within each pixel it crosses (variance 1/12 px^2 per unit length of edge), whose first
      moment about the centre, over the spot's weight, is that variance.
    """
    k, r = noise_g
    var0 = r + tab["dark_var_g_dn2"] / tab["n_dark"]
    w2 = tab["spot_weight_sum_dn"].clip(lower=1e-12) ** 2
    grid = 1.0 / (12.0 * np.pi * G_SITES_PER_BAND_PIXEL * np.sqrt(tab["spot_n_pix"].clip(lower=1) / np.pi))
    g = tab["band"] == "G"
    plane = [tab["lens"], tab["medium"], tab["azimuth_deg"]]
    for ax in ("x", "y"):
        pixel = (k * tab[f"spot_d{ax}2_weight_dn"] + var0 * tab[f"spot_d{ax}2_px2"]) / w2
        ss = tab[f"spot_frames_ss_{ax}_px2"].where(g, 0.0).groupby(plane).transform("sum")
        dof = (tab["spot_n_centroid_frames"] - 1).where(g, 0).groupby(plane).transform("sum")
        mean_pixel = pixel.where(g, 0.0).groupby(plane).transform("sum") / g.groupby(plane).transform("sum")
        cut = np.where(dof > 0, np.clip(ss / dof.clip(lower=1) - mean_pixel, 0.0, None), 0.0)
        tab[f"spot_centroid_pixel_{ax}_px"] = np.sqrt(pixel)
        tab[f"spot_centroid_cut_{ax}_px"] = np.sqrt(cut)
        tab[f"spot_centroid_grid_{ax}_px"] = np.sqrt(grid)
        tab[f"spot_{ax}_sigma_px"] = np.sqrt(pixel + cut + grid)
    # the sums the terms were made from are not kept: the terms and spot_n_pix (the grid term's N) say it all
    for column in _CENTROID_SUMS:
        del tab[column]


def analyse_rolloff(reduced: dict, config: dict, effects: list[str], beta_shift: bool = False) -> dict[str, xr.Dataset]:
    """Fit the roll-off curves of every lens, medium and band from the reduced settings; one artefact per lens.

    The spots' values are normalised by a first fit's a0 (g(0) = 1) and fitted with their halo, the
    principal point's share of the field angle's error and the model's effects (docs/stages.md).

    Parameters
    ----------
    reduced : dict
        What :func:`reduce_rolloff` returned.
    config : dict
        The run's configuration.
    effects : list[str]
        The model's effects.
    beta_shift : bool, default False
        Use the pixels linearised at beta + sigma_beta (for :func:`add_nonlinearity_covariance`).

    Returns
    -------
    dict[str, xarray.Dataset]
        Lens -> its roll-off artefact: the curves' coefficients and covariance per medium and band, the
        observation tables and the noise model.
    """
    tab = setting_table(reduced, config, beta_shift)
    noise = noise_model(tab)
    k = tab["band"].map(lambda b: noise[b][0])
    r = tab["band"].map(lambda b: noise[b][1])
    var_pix = k * tab["signal_dn"].clip(lower=0) + r
    tab["sigma_raw_dn"] = np.sqrt(var_pix / (tab["n_pix"] * tab["n_frames"]) + tab["dark_var_dn2"] / (tab["n_pix"] * tab["n_dark"]))
    ann_var = k * tab["annulus_dn"].clip(lower=0) + r
    tab["sigma_annulus_dn"] = np.sqrt(ann_var / (tab["n_annulus"].clip(lower=1) * tab["n_frames"])
                                      + tab["dark_var_dn2"] / (tab["n_annulus"].clip(lower=1) * tab["n_dark"]))
    _add_centroid_sigma(tab, noise["G"])
    tab["group"] = tab["lens"] + "/" + tab["band"] + "/" + tab["medium"]
    # normalisation: a0 of a first polynomial fit per group (g(0) = 1)
    norm = {}
    slope = pd.Series(0.0, index=tab.index)
    for grp, g in tab.groupby("group"):
        ok = ~g["saturated"]
        f = fit_rolloff(g.loc[ok, "theta_deg"], g.loc[ok, "signal_dn"], g.loc[ok, "sigma_raw_dn"])
        norm[grp] = float(f.coefficients[0])
        slope[g.index] = rolloff_slope(f.coefficients, g["theta_deg"])
    a0 = tab["group"].map(norm)
    # the field angle itself is uncertain (geometric calibration). Its error is that of the geometry's fitted
    # parameters, common to every spot of a band image: the principal point's share (odd in azimuth, the
    # look-alike of rolloff_azimuth) as two nuisance columns per group with their prior as pseudo-measurements
    # (_centre_terms, _centre_prior_rows). The spots keep rolloff.field_angle_sigma_px as an independent term
    # beside it, through dg/dtheta: without it the rim spots (the steepest slope) weigh more and the published
    # curve moved at the rim of the in-water field (the truth-sky test's random spread, water/close/G 1.04 ->
    # 1.17); the centre's share is so counted twice, on the safe side (docs/stages.md, "Uncertainty of the field angle")
    centre_cols, centre_var = _centre_terms(tab, slope / a0, reduced["static"], "centre",
                                            ("theta_centre_grad_x_deg_per_px", "theta_centre_grad_y_deg_per_px"))
    has_centre = np.isfinite(centre_var)
    theta_sigma = config["rolloff"]["field_angle_sigma_px"] * tab["deg_per_px"].to_numpy(float)
    sigma_spot = np.hypot(tab["sigma_raw_dn"] / a0, np.abs(slope) / a0 * theta_sigma)
    spot = tab.assign(kind="spot", value_dn=tab["signal_dn"] / a0, sigma_dn=sigma_spot,
                      halo_column_dn=0.0, **_poly_columns(tab["theta_deg"]),
                      **{c: np.where(has_centre, centre_cols[:, k], 0.0) for k, c in enumerate(CENTRE_COLUMNS)})
    spot["used"] = (~spot["saturated"]).astype(int)
    halo = tab.assign(kind="halo", value_dn=tab["annulus_dn"] / a0, sigma_dn=tab["sigma_annulus_dn"] / a0,
                      halo_column_dn=tab["halo_raw_dn"] / a0, group=tab["group"] + "/halo",
                      **{c: 0.0 for c in _poly_columns(tab["theta_deg"])}, **{c: 0.0 for c in CENTRE_COLUMNS})
    halo["used"] = ((tab["n_annulus"] > 0) & np.isfinite(tab["annulus_dn"])).astype(int)
    prior = _centre_prior_rows(spot[has_centre])
    obs = pd.concat([spot, halo] + ([prior] if len(prior) else []), ignore_index=True)
    fit, names, extra, pred, X = _fit_setting(obs, effects)
    obs["pred_dn"] = pred
    obs["z"] = (obs["value_dn"] - pred) / obs["sigma_dn"]
    obs.loc[obs["used"] == 0, "z"] = np.nan
    # effect contributions removed from the spot values before the per-group polynomial
    nb = X.shape[1]
    effect_params, contrib = {}, np.zeros(len(obs))
    col = nb
    for name, cols in extra:
        kk = cols.shape[1]
        effect_params[name] = (fit.coef[col:col + kk], fit.cov[col:col + kk, col:col + kk])
        contrib += cols @ fit.coef[col:col + kk]
        col += kk
    obs["effect_dn"] = contrib

    curves = {}
    sp = obs[(obs["kind"] == "spot") & (obs["used"] == 1)]
    for (lens, band, medium), g in sp.groupby(["lens", "band", "medium"]):
        f = fit_rolloff(g["theta_deg"], g["value_dn"] - g["effect_dn"], g["sigma_dn"])
        c, cv = normalise_rolloff(f.coefficients, f.covariance)
        curves[(lens, band, medium)] = (c, cv, f)

    # closure: each in-water point against its prediction from the air fit and the immersion physics
    max_air = float(sp.loc[sp["medium"] == "air", "theta_deg"].max()) if (sp["medium"] == "air").any() else 0.0
    wat = obs[(obs["kind"] == "spot") & (obs["medium"] == "water")].drop(
        columns=[c for c in obs.columns if c.startswith("x_")] + ["halo_column_dn"])
    water_tab, scale, water_params = pd.DataFrame(), {}, {}
    air_fits = {(l_, b_): (curves[(l_, b_, "air")][0], curves[(l_, b_, "air")][1])
                for (l_, b_, m_) in curves if m_ == "air"}
    if len(wat) and air_fits:
        wat = wat[[(l_, b_) in air_fits for l_, b_ in zip(wat["lens"], wat["band"])]]
        n_w, n_g = water_indices(reduced, config)
        water_tab = _water_closure(wat, air_fits, n_w, n_g, max_air, config[STAGE]["field_angle_sigma_px"],
                                   reduced["static"])
        used = water_tab["used"].to_numpy(bool)
        Xw, wnames = base_design(water_tab)
        wcols = [(e, get_effect(e).columns(STAGE, "water", water_tab)) for e in effects if e in WATER_EFFECTS]
        wcols = [(e, c) for e, c in wcols if c is not None]
        Xf = np.hstack([Xw] + [c for _, c in wcols])
        wfit = wls(water_tab["value_dn"].to_numpy()[used], water_tab["sigma_dn"].to_numpy()[used], Xf[used])
        water_tab["pred_dn"] = Xf @ wfit.coef
        water_tab["z"] = (water_tab["value_dn"] - water_tab["pred_dn"]) / water_tab["sigma_dn"]
        water_tab.loc[~used, "z"] = np.nan
        for k, name in enumerate(wnames):
            if not name.endswith(":scale"):
                continue
            lens_, band_ = name.split("/")[:2]
            scale[(lens_, band_)] = (float(wfit.coef[k]), float(np.sqrt(max(wfit.cov[k, k], 0.0))))
        col = Xw.shape[1]
        for name, cols in wcols:
            kk = cols.shape[1]
            water_params[name] = (wfit.coef[col:col + kk], wfit.cov[col:col + kk, col:col + kk])
            col += kk
    for name, val in water_params.items():
        if name not in effect_params:
            effect_params[name] = val

    lenses = sorted({key[0] for key in reduced["static"]})
    return {lens: _lens_dataset(lens, obs, water_tab, curves, scale, effect_params, fit, noise, config,
                                reduced.get("dropped", {}))
            for lens in lenses}


def check_settings(reduced: dict, config: dict, frames_csv) -> None:
    """Stop with one line when a lens and medium keeps too few measured settings.

    That is fewer than ``rolloff.min_settings`` after the settings whose spot cannot be measured were
    dropped (:func:`_setting_masks`).

    Parameters
    ----------
    reduced : dict
        What :func:`reduce_rolloff` returned.
    config : dict
        The run's configuration.
    frames_csv : pathlib.Path
        The roll-off frames.csv, named in the error.

    Raises
    ------
    pipeline.errors.InputError
        Naming the lens, the medium and why the first dropped setting was dropped.
    """
    need = int(config[STAGE]["min_settings"])
    dropped = reduced.get("dropped", {})
    for lens, medium in sorted(reduced["static"]):
        kept = sum(1 for k in reduced["masks"] if k[:2] == (lens, medium))
        gone = [k for k in dropped if k[:2] == (lens, medium)]
        if kept < need:
            first = dropped[gone[0]] if gone else "none dropped"
            raise InputError(frames_csv, f"lens {lens}, {medium}: only {kept} roll-off settings with a measurable "
                                         f"spot (need rolloff.min_settings = {need}); {len(gone)} dropped, the first "
                                         f"because: {first}")


def _lens_dataset(lens, obs, water_tab, curves, scale, effect_params, fit, noise, config,
                  dropped: dict | None = None) -> xr.Dataset:
    n_coef = len(ROLLOFF_POWERS)
    coef = np.full((len(MEDIA), len(BANDS), n_coef), np.nan)
    cov = np.full((len(MEDIA), len(BANDS), n_coef, n_coef), np.nan)
    red = np.full((len(MEDIA), len(BANDS)), np.nan)
    for i, m in enumerate(MEDIA):
        for j, b in enumerate(BANDS):
            if (lens, b, m) in curves:
                c, cv, f = curves[(lens, b, m)]
                coef[i, j], cov[i, j], red[i, j] = c, cv, f.reduced_chi2
    comp = np.array([scale.get((lens, b), (np.nan, np.nan)) for b in BANDS])
    o = obs[obs["lens"] == lens].reset_index(drop=True)
    z = o["z"].to_numpy(float)
    data = {
        "rolloff_coefficients": (("medium", "band", "power"), coef,
                                 {"long_name": "roll-off g(theta) = sum a_k theta^k, Eq. (13), normalised g(0) = 1", "units": "1",
                                  "comment": "theta is the field angle in degrees taken as a number (theta / degree): "
                                             "a_k is in degree^-k of the angle"}),
        "rolloff_covariance": (("medium", "band", "power", "power_b"), cov,
                               {"long_name": "covariance of rolloff_coefficients", "units": "1",
                                "comment": "element (k, l) in degree^-(k+l) of the angle (rolloff_coefficients)"}),
        "rolloff_reduced_chi2": (("medium", "band"), red, {"long_name": "reduced chi-square of the roll-off fit", "units": "1"}),
        "water_closure_scale": (("band",), comp[:, 0],
                                {"long_name": "c in g_water(theta_w) = c g_air(theta_a) F(theta_a, theta_w): the in-water "
                                              "roll-off against its prediction from air and the immersion physics", "units": "1"}),
        "water_closure_scale_sigma": (("band",), comp[:, 1], {"long_name": "standard error of water_closure_scale",
                                                              "units": "1"}),
        "noise_slope_dn": (("band",), np.array([noise[b][0] for b in BANDS]),
                           {"long_name": "pixel variance per DN of signal (pooled)", "units": "DN"}),
        "noise_read_dn2": (("band",), np.array([noise[b][1] for b in BANDS]),
                           {"long_name": "pixel variance at zero signal (pooled)", "units": "DN2"}),
        "rms_z": ((), float(np.sqrt(np.nanmean(z**2))) if np.isfinite(z).any() else np.nan,
                  {"long_name": "RMS of the noise-normalised residuals of the roll-off model", "units": "1"}),
    }
    gone = {m: sorted(k for k in (dropped or {}) if k[:2] == (lens, m)) for m in MEDIA}
    data["n_settings_dropped"] = (("medium",), np.array([len(gone[m]) for m in MEDIA], float), {
        "long_name": "settings whose port spot could not be measured (no light above the noise in the lit field, "
                     "or the port beyond its edge), neither fitted nor in obs_setting",
        "units": "1",
        "reasons": "; ".join(f"{m} azimuth {k[2]:g} deg angle {k[3]:g} deg: {dropped[k]}" for m in MEDIA
                             for k in gone[m]) or "none"})
    for name, (c, cv) in effect_params.items():
        se = np.sqrt(np.clip(np.diag(cv), 0, None))
        units = get_effect(name).amplitude_units
        if name == "rolloff_azimuth":
            amp, amp_se, phi0, phi0_se = azimuth_from_coefficients(c, cv)
            data["effect_rolloff_azimuth_phi0_deg"] = ((), phi0, {"long_name": "azimuth of the roll-off asymmetry", "units": "degree"})
            data["effect_rolloff_azimuth_phi0_deg_sigma"] = ((), phi0_se, {"units": "degree"})
            c, se = np.array([amp]), np.array([amp_se])
        data[f"effect_{name}"] = (f"{name}_param", np.asarray(c, float), {"long_name": f"fitted parameter(s) of {name}", "units": units})
        data[f"effect_{name}_sigma"] = (f"{name}_param", np.asarray(se, float), {"units": units})
    ds = xr.Dataset(data, coords={"medium": list(MEDIA), "band": list(BANDS), "power": list(ROLLOFF_POWERS),
                                  "power_b": list(ROLLOFF_POWERS)})
    store = o.assign(used=o["used"].astype(int), saturated=o["saturated"].astype(int))
    ds = ds.merge(table_to_dataset(store, "obs_setting"))
    for ax in ("x", "y"):
        if f"obs_setting__spot_{ax}_sigma_px" in ds:
            ds[f"obs_setting__spot_{ax}_sigma_px"].attrs.update({
                "units": "pixel", "long_name": f"standard uncertainty of the G spot centroid spot_{ax}_px (band pixels)",
                "description": "sqrt of the sum of spot_centroid_pixel, _cut and _grid squared: the pixels' noise "
                               "through the flux-weighted centroid (noise model var = k S + r), the frames' scatter "
                               "of the centroid through the same cut beyond it (pooled per lens, medium and azimuth "
                               "plane), and the grid's sampling of a sharp-edged spot, 1 / (12 pi n R), R = "
                               "sqrt(spot_n_pix / pi), n = 2 green sites a band pixel"})
            for term in ("pixel", "cut", "grid"):
                ds[f"obs_setting__spot_centroid_{term}_{ax}_px"].attrs.update({
                    "units": "pixel", "long_name": f"{term} term of spot_{ax}_sigma_px"})
    if len(water_tab):
        w = water_tab[water_tab["lens"] == lens].reset_index(drop=True)
        w = w.assign(used=w["used"].astype(int), saturated=w["saturated"].astype(int))
        ds = ds.merge(table_to_dataset(w, "obs_water"))
    return ds


# ----------------------------------------------------------------------------- the stage
def add_nonlinearity_covariance(art: xr.Dataset, shifted: xr.Dataset) -> None:
    """The fitted nonlinearity's uncertainty in the roll-off curves.

    The whole analysis is repeated on the pixels linearised at beta + sigma_beta (``shifted``); the change d
    of each curve's coefficients is added to its covariance as d d^T (first order; common to the points of a
    curve, so it is a covariance, not a point's noise). The change is kept as ``rolloff_nonlinearity_shift``.

    Parameters
    ----------
    art : xarray.Dataset
        The lens's roll-off artefact, modified in place.
    shifted : xarray.Dataset
        The same artefact from the pixels at beta + sigma_beta.
    """
    delta = shifted["rolloff_coefficients"].values - art["rolloff_coefficients"].values
    delta = np.where(np.isfinite(delta), delta, 0.0)
    art["rolloff_covariance"].values = art["rolloff_covariance"].values + delta[..., :, None] * delta[..., None, :]
    art["rolloff_covariance"].attrs["nonlinearity"] = ("includes the fitted nonlinearity's uncertainty: d d^T, d the "
                                                       "change of the coefficients at beta + sigma_beta")
    art["rolloff_nonlinearity_shift"] = (art["rolloff_coefficients"].dims, delta, {
        "long_name": "change of rolloff_coefficients with the nonlinearity at beta + sigma_beta (its one-sigma "
                     "shift, in rolloff_covariance)", "units": art["rolloff_coefficients"].attrs.get("units", "1")})


def compute(ctx) -> xr.Dataset:
    """The roll-off artefact of one lens (the stage runner's contract).

    Parameters
    ----------
    ctx : pipeline.runner.workflow.StageContext
        The job: the lens's dataset, the configuration, the model's effects and the upstream ``geometry``
        artefact, and when given the ``dark`` (the unlit corners' records) and ``linearity`` ones.

    Returns
    -------
    xarray.Dataset
        The lens's roll-off artefact with its ``obs_corner`` table; the frames' sha256 are recorded in ``ctx``.

    Raises
    ------
    pipeline.errors.InputError
        If the lens has too few measurable settings or no roll-off frames.
    """
    geometry = {ctx.lens: ctx.upstream["geometry"]}
    corners = FrameCorners.of_upstream(ctx.lens, ctx.upstream, ctx.dataset.projection, ctx.config["bias"])
    linearity = {ctx.lens: ctx.upstream["linearity"]} if ctx.upstream.get("linearity") is not None else None
    reduced = reduce_rolloff(ctx.dataset, geometry, ctx.config, progress=ctx.progress, corners=corners,
                             linearity=linearity)
    ctx.record_frames(reduced["inputs"])
    check_settings(reduced, ctx.config, ctx.dataset.root / STAGE / "frames.csv")
    arts = analyse_rolloff(reduced, ctx.config, ctx.effects)
    if ctx.lens not in arts:
        raise InputError(ctx.dataset.root / STAGE / "frames.csv", f"no roll-off frames for lens {ctx.lens}")
    if reduced["beta_shift"]:
        shifted = analyse_rolloff(reduced, ctx.config, ctx.effects, beta_shift=True)
        add_nonlinearity_covariance(arts[ctx.lens], shifted[ctx.lens])
    arts[ctx.lens].attrs["response_corrections"] = ",".join(reduced["response_corrections"])
    # the signal frames' unlit corners against the dark model, for the closure (pipeline.diagnostics.cross_closure)
    return with_corner_table(arts[ctx.lens], corners.of_lens(ctx.lens))
