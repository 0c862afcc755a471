"""The light field: which pixel sees which lens and aperture point, and images refocused from it.

- ``table``: the look-up table (the paper's LOT) of a calibration, saved and loaded.
- ``refocus``: the refocus stack (shift-and-add over alpha), the sub-aperture image and their
  products; its work is cached in the caller's :class:`analysis.cache.Cache`.
- ``kernels``: refocus's numba kernels (arrays in, caller-allocated arrays out).
- ``reference``: the same refocus written plainly, which the tests compare the kernels with.
- ``glints``: compact sources far out of focus, fitted as sources spread over the lens plane and
  taken off the raw image.

Hands the product stack to :mod:`analysis.detection`, the table to :mod:`analysis.depth`.
"""
