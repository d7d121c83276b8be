"""Radiometric physics of the camera calibration (Larouche et al. 2024, Sections 2.1 and 2.4-2.7).

Small modules of pure, vectorised functions:

* ``exposure``  normalisation by exposure time and gain, Eq. (2)
* ``water``     refractive index of water (Quan and Fry 1995) and air
* ``fresnel``   Fresnel reflectance / transmittance, t_aw
* ``immersion`` n-squared law, immersion-factor fit (Eq. 11), Eq. (10) and its inverse
* ``spectral``  peak-normalised response, Eq. (8), bandwidth, Eq. (3)
* ``source``    Planck radiance, scaling to a reference reading
* ``absolute``  inverse responsivity, Eq. (9), with its uncertainty budget
* ``rolloff``   Eq. (13): design matrix, fit, evaluation, slope
"""

import importlib

__all__ = ["absolute", "exposure", "fresnel", "immersion", "rolloff", "source", "spectral", "water"]


def __getattr__(name: str):
    """The submodules imported when first named (``apply``'s chain needs none of scipy.stats, which
    ``immersion`` imports)."""
    if name in __all__:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
