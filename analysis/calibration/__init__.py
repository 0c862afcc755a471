"""One camera at one zoom/focus, from its white images.

- ``white_choice``: which white image calibrates a picture (same camera, nearest zoom, then
  focus; dark ones skipped).
- ``lattice_fit``: the global hexagonal micro-image lattice fitted to a white image.
- ``calibrate``: :class:`~analysis.calibration.calibrate.Calibration` (fitted lattice and
  devignetting map) from one white image.
- ``cache``: calibrations kept on disk by camera serial and white SHA-1, and
  ``load_calibration``, the one call a picture needs.
- ``metric_files``: target (metric) calibrations as JSON files, picked per camera, zoom and focus
  like the white images; the thin-lens fallback where none fits.

Hands a Calibration to :mod:`analysis.lightfield` (its look-up table) and :mod:`analysis.pipeline`.
"""
