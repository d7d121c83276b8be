"""The measurement model as a list of named physical effects.

Each effect is a small class (see :mod:`pipeline.effects.base`) that carries
both sides of the same physics: the simulator's forward hooks (how the effect
changes electrons, exposure, gain or DN) and the pipeline's side (the columns
it adds to a stage's linear model, i.e. its signature in the residuals of a
model without it, and how a fitted coefficient turns into a physical
amplitude).

Users add their own effects without editing the package: write a module that
subclasses :class:`Effect` and decorates it with :func:`register`, then list
the module under ``model.plugins`` in ``config.yaml``.
"""

from pipeline.effects.base import (
    CATALOGUE,
    Effect,
    available,
    get,
    load_plugins,
    register,
)
from pipeline.effects import catalogue as _catalogue  # noqa: F401  (registers the built-ins)

__all__ = ["CATALOGUE", "Effect", "available", "get", "load_plugins", "register"]
from pipeline.effects import optics as _optics  # noqa: F401,E402  (registers the roll-off and immersion effects)
from pipeline.effects import field as _field  # noqa: F401,E402  (registers the field effects)
