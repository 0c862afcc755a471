"""The one geometry everything shares (docs/camera-model.md).

- ``model``: :class:`~analysis.camera.model.CameraModel` from a picture's metadata: the
  micro-image lattice, the thin-lens optics (``z_of_alpha``), sensor levels.
- ``image_grid``: the regular output grid of refocused images (pixels <-> lens-plane metres).
- ``coordinates``: pixels and alpha to ``X, Y, Z`` in mm (thin lens, a user's calibration, or a
  target calibration), and the tilted-layer check of the paper.
- ``front_optics``: an auxiliary thin lens in front of the camera and radial distortion, as a map
  between where points are and where the main lens sees them.
- ``dot_grid``: rows and columns of a calibration target's dots (the dot nearest the axis at 0, 0).
- ``target_mapping``: :class:`~analysis.camera.target_mapping.MetricCalibration` and its mappings
  (polynomial, physical); ``mapping_fit`` fits them and keeps the one better on held-back positions.

Used by every other subpackage; uses only :mod:`analysis.errors`.
"""
