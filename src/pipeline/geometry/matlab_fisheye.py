"""Reader of a MATLAB Computer Vision Toolbox ``fisheyeParams`` calibration (``.mat``, MATLAB v5).

Such a file (e.g. the Insta360 ONE calibrations of Larouche et al. 2024) holds the fitted Scaramuzza model
and every board's detected corners as ``ReprojectedPoints - ReprojectionErrors``. MATLAB's pixel
coordinates are 1-based (the first pixel's centre at 1); the project's are 0-based
(:mod:`pipeline.geometry.scaramuzza`), so 1 is subtracted from the corners and the distortion centre.
MATLAB's mapping f(rho) = a0 + a2 rho^2 + a3 rho^3 + a4 rho^4 with tan(theta) = rho / f(rho) is the
project's with a1 = 0.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .scaramuzza import FisheyeModel

#: MATLAB pixel coordinates minus the project's (pixel centres at integers from 1, against from 0)
MATLAB_ORIGIN_PX = 1.0


def read_fisheye_params(path: Path) -> dict:
    """Corners and solution of a MATLAB ``fisheyeParams`` file.

    Parameters
    ----------
    path : pathlib.Path
        The ``.mat`` file (MATLAB v5) holding a ``fisheyeParams`` structure.

    Returns
    -------
    dict
        ``"corners"``: list over boards of ``(k, 2)`` detected (u, v), 0-based pixels; ``"board_mm"``: ``(k, 3)``
        board points (mm, z = 0); ``"model"``: the file's :class:`FisheyeModel` (0-based centre, its stretch
        matrix); ``"mean_error_px"``: the file's mean reprojection error, pixels; ``"image_shape"``: (rows, cols).
    """
    from scipy.io import loadmat

    p = loadmat(Path(path))["fisheyeParams"][0, 0]
    intr = p["Intrinsics"][0, 0]
    detected = np.asarray(p["ReprojectedPoints"], float) - np.asarray(p["ReprojectionErrors"], float)
    world = np.asarray(p["WorldPoints"], float)
    coeffs = np.ravel(intr["MappingCoefficients"]).astype(float)
    xc, yc = np.ravel(intr["DistortionCenter"]).astype(float) - MATLAB_ORIGIN_PX
    stretch = np.asarray(intr["StretchMatrix"], float)
    shape = tuple(int(n) for n in np.ravel(intr["ImageSize"]))
    model = FisheyeModel((coeffs[0], 0.0, *coeffs[1:]), xc, yc, stretch[0, 0], stretch[0, 1], stretch[1, 0],
                         shape=shape)
    return {"corners": [detected[:, :, k] - MATLAB_ORIGIN_PX for k in range(detected.shape[2])],
            "board_mm": np.column_stack([world, np.zeros(len(world))]), "model": model,
            "mean_error_px": float(np.ravel(p["MeanReprojectionError"])[0]), "image_shape": shape}
