"""The light field from calibrated radiance sphere grids: the quantities scientists publish.

- :mod:`~pipeline.lightfield.grid`: radiance sphere grid files in (apply's format or one made by hand);
- :mod:`~pipeline.lightfield.quadrature`: exact cell solid angles and hemisphere/cone weights on the grid;
- :mod:`~pipeline.lightfield.attitude`: roll, pitch, heading from a log; the earth frame; the solar position;
- :mod:`~pipeline.lightfield.fill`: the band no lens calibrates, filled by a stated model with its uncertainty;
- :mod:`~pipeline.lightfield.quantities`: E_d, E_u, E_0d, E_0u, E_0, mu_d, mu_u, mu, L_d, L_u, Q and their
  random, systematic, fill-model, attitude and quadrature uncertainty;
- :mod:`~pipeline.lightfield.command`: ``python -m pipeline lightfield``.
"""
