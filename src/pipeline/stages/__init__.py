"""One module per calibration experiment: reduce its frames for one lens, fit, return the artefact.

Each module provides ``compute(ctx)`` for the stage runner (:mod:`pipeline.runner.workflow`).
"""
