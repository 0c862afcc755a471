"""The one geometry everything shares (docs/camera-model.md).

- ``model``: :class:`~analysis.camera.model.CameraModel` from a picture's metadata: the
  micro-image lattice, the thin-lens optics (``z_of_alpha``), sensor levels.
- ``image_grid``: the regular output grid of refocused images (pixels <-> lens-plane metres).
- ``coordinates``: pixels and alpha to ``X, Y, Z`` in mm (thin lens, or a user's calibration),
  and the tilted-layer check of the paper.

Used by every other subpackage; uses only :mod:`analysis.errors`.
"""
