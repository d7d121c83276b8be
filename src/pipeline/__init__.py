"""Calibration pipeline that turns a RAW camera into a calibrated radiometer."""

__version__ = "0.1.0"
