"""Candidate particles in the refocused stack (stages 5 and 6 of docs/design.md).

- ``moments``: the moment method of Feng, Goree & Liu (2007) per slice.
- ``maxima``: local maxima of the stack over (alpha, y, x), where neighbours' blobs merge.
- ``curves``: detections linked across slices into brightness curves ``B(alpha)``
  (:class:`~analysis.detection.curves.Tracks`) and their peaks
  (:class:`~analysis.detection.curves.Peaks`: one per candidate particle).

Hands Peaks to :mod:`analysis.depth`.
"""
