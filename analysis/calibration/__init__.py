"""One camera at one zoom/focus, from its white images.

- ``white_choice``: which white image calibrates a picture (same camera, nearest zoom, then
  focus; dark ones skipped).
- ``lattice_fit``: the global hexagonal micro-image lattice fitted to a white image.
- ``profile``: the optical blur, the aperture image's radius and the rim response fitted to a white
  image's micro-images (kernels in ``profile_kernels``).
- ``defects``: hot, stuck and dead pixels from a camera's calibration frames (kernels in
  ``defects_kernels``); ``camera_defects``: which frames, their lattices, the maps kept on disk.
- ``calibrate``: :class:`~analysis.calibration.calibrate.Calibration` (fitted lattice, devignetting
  map, micro-image profile; the defect map joins it) from one white image.
- ``cache``: calibrations kept on disk by camera serial and white SHA-1, and
  ``load_calibration``, the one call a picture needs.
- ``metric_files``: target (metric) calibrations as JSON files, picked per camera, zoom and focus
  like the white images; the thin-lens fallback where none fits.

Hands a Calibration to :mod:`analysis.lightfield` (its look-up table) and :mod:`analysis.pipeline`.
"""
