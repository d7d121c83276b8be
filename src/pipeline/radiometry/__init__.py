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

from . import absolute, exposure, fresnel, immersion, rolloff, source, spectral, water

__all__ = ["absolute", "exposure", "fresnel", "immersion", "rolloff", "source", "spectral", "water"]
