"""Geometric-calibration experiment (Larouche et al. 2024, Sections 2.3 and 3.2).

A planar chessboard, lit uniformly, photographed by each lens in air and in
water at poses that cover the field of view up to its edge
(:func:`pipeline.simulate.chessboard.poses_covering_fov`). The board is
rendered through the TRUE camera model of every raw pixel's own band:

* per lens and medium the nominal model is the published fit
  (:func:`pipeline.simulate.lens.default_model` at raw resolution);
* chromatic differences: per band a magnification of the polynomial about its
  centre (R +0.2 %, B -0.15 % in air; +0.3 % / -0.3 % in water, giving
  edge differences of 0.1-0.35 degree against G, the size of Fig. 4c-d) and a
  principal-point offset of a fraction of a band pixel;
* each raw pixel integrates the board over its own area (inverse mapping,
  ``SUPERSAMPLE`` x ``SUPERSAMPLE`` sub-pixels wherever the 1-sample image
  changes within the pixel's neighbourhood, one sample elsewhere, which is
  exact there); the renderer then adds roll-off, the unlit border outside
  the image circle, and noise. No optical point-spread function is simulated
  beyond the pixel area.

Band images are 2 x 2 Bayer cells (RGGB): an R band pixel is the raw site
``(2i, 2j)``, B is ``(2i+1, 2j+1)``, G averages ``(2i, 2j+1)`` and
``(2i+1, 2j)``. The true band-image model of band b therefore is the raw
model scaled by 1/2 with the site offset: R centre +0.25 band px, B -0.25 band
px relative to the cell centre convention of
:meth:`pipeline.geometry.scaramuzza.FisheyeModel.scaled` (G).

Board: 8 x 6 inner corners (30 mm squares in air, 20 mm in water); the tiny
scale's coarse images use a board with fewer, larger squares
(:data:`BOARD_BY_SCALE`). dataset.yaml declares the board of the scale.

Frame counts: the real counts are not published per lens (16 in air, 20 in
water for one calibration, Section 2.3); we use ``FRAMES_PER_MEDIUM``
(20 per lens and medium at the full scale).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.ndimage import maximum_filter, minimum_filter

from pipeline.io.bands import BANDS
from pipeline.geometry.chessboard import Board, project_points
from pipeline.geometry.image_circle import ImageCircle, half_fov_from_circle
from pipeline.geometry.scaramuzza import FisheyeModel
from pipeline.simulate.chessboard import board_reflectance, poses_covering_fov
from pipeline.simulate.lens import HALF_FOV_DEG, default_model
from pipeline.simulate.plan import ExperimentPlan, FrameSpec, SimContext, planner

#: the board of the small, medium and full scales (dataset.yaml declares the board of
#: :func:`board_design`)
INNER_CORNERS = (8, 6)
SQUARE_MM = {"air": 30.0, "water": 20.0}
MEDIA = ("air", "water")
#: frames per lens and medium, by scale name (full: real counts unpublished, ~20)
FRAMES_PER_MEDIUM = {"tiny": 12, "small": 16, "medium": 20, "full": 20}
#: per-band magnification of f(rho) about the centre (chromatic), per medium
MAGNIFICATION = {"air": {"R": 1.002, "G": 1.0, "B": 0.9985},
                 "water": {"R": 1.003, "G": 1.0, "B": 0.997}}
#: per-band principal-point offset (band pixels) on top of the Bayer site offset
CENTRE_OFFSET_BAND_PX = {"R": (0.3, -0.2), "G": (0.0, 0.0), "B": (-0.2, 0.3)}
#: raw-site position of each band inside its 2 x 2 cell (RGGB), raw pixels (du, dv)
SITE_OFFSET_RAW = {"R": (0.0, 0.0), "G": (0.5, 0.5), "B": (1.0, 1.0)}
SUPERSAMPLE = 4
EXPOSURE_S = 0.05
ISO = 100.0
#: DN (above bias, on the axis) of a perfectly white board per band; R and B are
#: dimmer than G as with a halogen lamp seen through the broad camera bands
WHITE_DN = {"R": 8000.0, "G": 10000.0, "B": 6000.0}
REFLECTANCE = {"white": 0.9, "black": 0.05, "background": 0.35}
#: board half-angle (deg) on the axis and at the edge of the field
BOARD_HALF_ANGLE_DEG = (50.0, 20.0)


@dataclass(frozen=True)
class BoardDesign:
    """The chessboard the lab photographs and how large it appears.

    ``half_angle_deg``: half-angle (deg) that the board's half-diagonal
    subtends on the axis and at the edge of the field
    (:func:`pipeline.simulate.chessboard.poses_covering_fov`).
    """

    inner_corners: tuple[int, int]
    square_mm: dict
    half_angle_deg: tuple[float, float]

    def board(self, medium: str) -> Board:
        """The board photographed in one medium.

        Parameters
        ----------
        medium : str
            ``air`` or ``water`` (the square size differs).

        Returns
        -------
        Board
            The inner corners and the square size of that medium, mm.
        """
        return Board(*self.inner_corners, self.square_mm[medium])

    def dataset_entry(self) -> dict:
        """The ``chessboard`` entry of dataset.yaml.

        Returns
        -------
        dict
            ``inner_corners`` (list of two int) and ``square_mm`` (medium -> square size, mm).
        """
        return {"inner_corners": list(self.inner_corners), "square_mm": dict(self.square_mm)}


BOARD = BoardDesign(INNER_CORNERS, SQUARE_MM, BOARD_HALF_ANGLE_DEG)
#: Boards by scale name where :data:`BOARD` cannot be resolved. A chessboard is
#: detectable only when each square spans at least two pixels (the sampling
#: limit). At the tiny scale (64-px band images, about 3 deg per band pixel) the
#: 8 x 6 board's smallest square images to 1.5 band px in the median pose (0.8 at
#: worst) and the board is found in 0 to 5 of 12 frames; a lab with so coarse a
#: camera uses a board with fewer, larger squares, held closer: 5 x 4 inner
#: corners (odd sum: the orientation stays unambiguous), half-angles 55 deg on the
#: axis and 35 deg at the edge, whose smallest square images to 2.9 band px in the
#: median pose (1.9 at worst). Square sizes keep the distances of a lab bench
#: (0.2-0.4 m in air) and a tank (0.13-0.26 m in water).
BOARD_BY_SCALE = {"tiny": BoardDesign((5, 4), {"air": 60.0, "water": 40.0}, (55.0, 35.0))}


def board_design(scale_name: str) -> BoardDesign:
    """The board the simulated lab uses at a scale (dataset.yaml declares it).

    Parameters
    ----------
    scale_name : str
        The dataset's scale (tiny, small, medium, full).

    Returns
    -------
    BoardDesign
        :data:`BOARD_BY_SCALE`'s board for that scale, else :data:`BOARD`.
    """
    return BOARD_BY_SCALE.get(scale_name, BOARD)


def magnified(model: FisheyeModel, m: float) -> FisheyeModel:
    """The model with the image magnified by m about its principal point.

    Parameters
    ----------
    model : FisheyeModel
        The model.
    m : float
        The magnification, dimensionless (polynomial coefficient a_k scaled by m^(1 - k)).

    Returns
    -------
    FisheyeModel
        The magnified model (a copy).
    """
    return replace(model, poly=tuple(a * m ** (1 - k) for k, a in enumerate(model.poly)))


def true_raw_models(lens: str, medium: str, lens_px: int) -> dict[str, FisheyeModel]:
    """Per-band true model in raw-pixel coordinates of the lens region.

    The nominal model (:func:`pipeline.simulate.lens.default_model`) with each band's chromatic magnification
    (:data:`MAGNIFICATION`) and principal-point offset (:data:`CENTRE_OFFSET_BAND_PX`, doubled to raw pixels).

    Parameters
    ----------
    lens : str
        The lens (``close`` or ``far``).
    medium : str
        ``air`` or ``water``.
    lens_px : int
        Side of the square lens region, raw pixels.

    Returns
    -------
    dict[str, FisheyeModel]
        Band (R, G, B) -> its model in raw pixels.
    """
    base = default_model(lens, medium, (lens_px, lens_px))
    out = {}
    for band in BANDS:
        du, dv = CENTRE_OFFSET_BAND_PX[band]
        m = magnified(base, MAGNIFICATION[medium][band])
        out[band] = replace(m, xc=m.xc + 2 * du, yc=m.yc + 2 * dv, meta={"lens": lens, "medium": medium})
    return out


def band_model(raw: FisheyeModel, band: str) -> FisheyeModel:
    """True band-image model of a raw-coordinate model (Bayer site offset included).

    Parameters
    ----------
    raw : FisheyeModel
        A band's model in raw pixels of the lens region.
    band : str
        R, G or B (its site in the 2 x 2 cell, :data:`SITE_OFFSET_RAW`).

    Returns
    -------
    FisheyeModel
        The model in that band's image pixels (half the raw scale).
    """
    b = raw.scaled(0.5)
    su, sv = SITE_OFFSET_RAW[band]
    # band pixel i of this band sits at raw 2i + su: u_band = (u_raw - su) / 2
    return replace(b, xc=(raw.xc - su) / 2.0, yc=(raw.yc - sv) / 2.0)


def true_image_circle(lens: str, medium: str, lens_px: int, band: str) -> ImageCircle:
    """The lit disc of the renderer (nominal model, theta <= half FOV) in band coordinates.

    Parameters
    ----------
    lens : str
        The lens.
    medium : str
        ``air`` or ``water``.
    lens_px : int
        Side of the square lens region, raw pixels.
    band : str
        R, G or B.

    Returns
    -------
    ImageCircle
        Centre (x, y) and radius in band pixels, fit RMS 0.
    """
    nominal = default_model(lens, medium, (lens_px, lens_px))
    r = nominal.image_circle_radius()
    su, sv = SITE_OFFSET_RAW[band]
    return ImageCircle((nominal.xc - su) / 2.0, (nominal.yc - sv) / 2.0, r / 2.0, 0.0, 0)


class ChessboardScene:
    """Scene callable: the uniformly lit board at one pose, per raw site through its band's model."""

    def __init__(self, board: Board, rvec, tvec, raw_models: dict, radiance_white: dict,
                 supersample: int = SUPERSAMPLE):
        self.board = board
        self.rvec = np.asarray(rvec, float)
        self.tvec = np.asarray(tvec, float)
        self.models = raw_models
        self.radiance_white = radiance_white
        self.ss = int(supersample)

    def reflectance(self, model, u, v):
        """The board's reflectance along the rays of one band's pixels, with the geometry experiment's reflectances.

        Parameters
        ----------
        model : FisheyeModel
            The band's raw-pixel model.
        u : numpy.ndarray
            Raw pixel column coordinates.
        v : numpy.ndarray
            Raw pixel row coordinates, same shape.

        Returns
        -------
        numpy.ndarray
            Reflectance, dimensionless, shape of ``u`` (:func:`pipeline.simulate.chessboard.board_reflectance`).
        """
        return board_reflectance(model, self.board, self.rvec, self.tvec, u, v,
                                 white=REFLECTANCE["white"], black=REFLECTANCE["black"],
                                 background=REFLECTANCE["background"], outside=REFLECTANCE["background"],
                                 half_fov_deg=180.0)

    def band_sites(self, band: str, shape) -> np.ndarray:
        """Reflectance integrated over every raw pixel of one band's sites: list of (row offset, column offset, values).

        Parameters
        ----------
        band : str
            R, G or B.
        shape : tuple of (int, int)
            (rows, cols) of the lens region, raw pixels.

        Returns
        -------
        list of tuple of (int, int, numpy.ndarray)
            One entry per site of the band in the 2 x 2 cell (two for G): its row and column offset in the cell and
            the reflectance of the raw pixels ``[dy::2, dx::2]``, each averaged over the pixel's area (supersampled
            near edges).
        """
        model = self.models[band]
        out = []
        sites = {"R": [(0, 0)], "G": [(0, 1), (1, 0)], "B": [(1, 1)]}[band]
        for dy, dx in sites:
            rows = np.arange(dy, shape[0], 2)
            cols = np.arange(dx, shape[1], 2)
            # only the board's neighbourhood needs rays; elsewhere it is background
            r0, r1, c0, c1 = self._bbox(model, shape)
            sel_r = rows[(rows >= r0) & (rows < r1)]
            sel_c = cols[(cols >= c0) & (cols < c1)]
            val = np.full((rows.size, cols.size), REFLECTANCE["background"])
            if sel_r.size and sel_c.size:
                uu, vv = np.meshgrid(sel_c.astype(float), sel_r.astype(float))
                centre = self.reflectance(model, uu, vv)
                # supersample where the site grid changes within one site (edges of squares or board)
                edge = maximum_filter(centre, 3) != minimum_filter(centre, 3)
                if edge.any():
                    offs = (np.arange(self.ss) + 0.5) / self.ss - 0.5
                    du, dv = np.meshgrid(offs, offs)
                    ue = uu[edge][:, None] + du.ravel()[None, :]
                    ve = vv[edge][:, None] + dv.ravel()[None, :]
                    centre[edge] = self.reflectance(model, ue, ve).mean(axis=1)
                ir = np.searchsorted(rows, sel_r)
                ic = np.searchsorted(cols, sel_c)
                val[np.ix_(ir, ic)] = centre
            out.append((dy, dx, val))
        return out

    def _bbox(self, model, shape):
        pts = self.board.outline_mm(64)
        uv = project_points(model, pts, self.rvec, self.tvec)
        if not np.all(np.isfinite(uv)):
            return 0, shape[0], 0, shape[1]
        m = 4
        c0 = max(0, int(np.floor(uv[:, 0].min())) - m)
        c1 = min(shape[1], int(np.ceil(uv[:, 0].max())) + m + 1)
        r0 = max(0, int(np.floor(uv[:, 1].min())) - m)
        r1 = min(shape[0], int(np.ceil(uv[:, 1].max())) + m + 1)
        return r0, r1, c0, c1

    def __call__(self, lens, geo, band_index):
        shape = band_index.shape
        out = np.empty(shape)
        for band in BANDS:
            for dy, dx, val in self.band_sites(band, shape):
                out[dy::2, dx::2] = val * self.radiance_white[band]
        return out


def white_radiance(ctx: SimContext) -> dict:
    """Band radiance of a perfect white board giving WHITE_DN on the axis at ISO 100.

    Parameters
    ----------
    ctx : SimContext
        The simulation (the camera's responsivity).

    Returns
    -------
    dict[str, float]
        Band -> radiance, W m-2 sr-1 nm-1 (band-averaged), at the experiment's exposure ``EXPOSURE_S``.
    """
    resp = ctx.camera.radiometry.responsivity_dn_s_per_radiance
    return {b: WHITE_DN[b] / (resp[b] * EXPOSURE_S) for b in BANDS}


def plan_poses(ctx: SimContext, lens: str, medium: str, n: int):
    """Board poses for one lens and medium, covering the field (:func:`~pipeline.simulate.chessboard.poses_covering_fov`).

    Parameters
    ----------
    ctx : SimContext
        The simulation (scale, and the generator the poses' seed is drawn from).
    lens : str
        The lens.
    medium : str
        ``air`` or ``water``.
    n : int
        Number of poses.

    Returns
    -------
    list of tuple of (numpy.ndarray, numpy.ndarray)
        Per pose, (rvec, tvec): rotation (Rodrigues vector, rad) and board centre, mm.
    """
    raw = true_raw_models(lens, medium, ctx.scale.lens_px)["G"]
    design = board_design(ctx.scale.name)
    seed = int(ctx.rng.integers(2**31))
    return poses_covering_fov(n, HALF_FOV_DEG[medium], seed, board=design.board(medium), model=raw,
                              board_half_angle_deg=design.half_angle_deg)


@planner("geometry")
def plan_geometry(ctx: SimContext) -> ExperimentPlan:
    """Plan the geometric-calibration experiment: chessboard frames of each lens in air and in water.

    Parameters
    ----------
    ctx : SimContext
        The simulation.

    Returns
    -------
    ExperimentPlan
        The frames (:data:`FRAMES_PER_MEDIUM` per lens and medium) and the truth: the board, the true raw and
        band models with their image circles, and each frame's pose.
    """
    n = FRAMES_PER_MEDIUM.get(ctx.scale.name, 20)
    lens_px = ctx.scale.lens_px
    radiance = white_radiance(ctx)
    frames = []
    design = board_design(ctx.scale.name)
    truth = {**design.dataset_entry(), "board_half_angle_deg": list(design.half_angle_deg),
             "supersample": SUPERSAMPLE, "exposure_s": EXPOSURE_S, "iso": ISO, "white_radiance": radiance,
             "models": {}, "frames": []}
    for medium in MEDIA:
        board = design.board(medium)
        for lens in ctx.camera.lens_names:
            raw = true_raw_models(lens, medium, lens_px)
            models = truth["models"].setdefault(lens, {}).setdefault(medium, {})
            for band in BANDS:
                bm = band_model(raw[band], band)
                circle = true_image_circle(lens, medium, lens_px, band)
                bm = replace(bm, half_fov_deg=half_fov_from_circle(bm, circle, 360))
                models[band] = {"raw": raw[band].to_dict(), "band": bm.to_dict(),
                                "image_circle": {"xc": circle.xc, "yc": circle.yc, "radius": circle.radius}}
            for rvec, tvec in plan_poses(ctx, lens, medium, n):
                truth["frames"].append({"frame_index": len(frames), "lens": lens, "medium": medium,
                                        "rvec": list(map(float, rvec)), "tvec_mm": list(map(float, tvec))})
                frames.append(FrameSpec(lens, "signal", ISO, EXPOSURE_S, {"medium": medium},
                                        ChessboardScene(board, rvec, tvec, raw, radiance), medium=medium))
    return ExperimentPlan(frames, truth=truth)
