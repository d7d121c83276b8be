"""The calibration bundle, ``apply`` over it, the store of published bundles and their comparison."""
