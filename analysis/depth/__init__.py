"""Depth and position from the raw pixels: a fit of the forward model around each candidate.

- ``rayfit``: :func:`~analysis.depth.rayfit.fit_rays` (a grid search over depth and position,
  :class:`~analysis.depth.rayfit.FitGrid` per pass) and :class:`~analysis.depth.rayfit.RayFit`;
  ``rayfit_kernels`` and ``render_kernels`` are its numba kernels, ``table_index`` its per-table
  lookups, ``footprint`` the points that stand for a blurred pixel, ``sample_apertures`` which
  aperture each point of a pixel sees.
- ``refine``: the pipeline's first stage (fit, keep, merge, probe for hidden particles) and the
  :class:`~analysis.depth.refine.RayFitter` every stage shares, with the thresholds they use.
- ``deblend``: crowds (refit with the neighbours' light taken off; split fits holding two
  particles on one line of sight).
- ``prior``: the neighbours' surface as a prior where one micro-lens holds a particle's light.

Hands the particles (Peaks moved to their fits, and the RayFit) to :mod:`analysis.pipeline`.
"""
