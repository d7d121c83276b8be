"""Geometric calibration of fisheye lenses (Scaramuzza / OCamCalib model).

Modules: :mod:`.scaramuzza` (the camera model), :mod:`.chessboard` (the
chessboard and its projection), :mod:`.corners` (corner detection),
:mod:`.calibrate` (calibration from detected corners), :mod:`.image_circle`
(image circle and half field of view), :mod:`.maps` (per-pixel theta, phi and
solid angle maps), :mod:`.sphere` (a pixel's direction and grid cell on the
full sphere of the two lenses). Conventions are in :mod:`.scaramuzza`'s docstring.
"""

from .scaramuzza import FisheyeModel

__all__ = ["FisheyeModel"]
