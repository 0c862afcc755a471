"""A simulated F01 with known truth, and scoring against it.

- ``camera``: the simulated lens and its metadata.
- ``scenarios``: particle scenes (tilted layer, shadowing pairs, ball).
- ``render``: white images and exposures rendered by ray tracing, and scenario folders written
  as the camera writes them; ``kernels`` holds its numba kernels.
- ``scoring``: found particles against the truth (recall, precision, depth and lateral errors).
- ``floor_kernels``: the depth floor's grid search (what no estimate from the pixels alone can beat).

Used by the tests, the benches and ``plenodust simulate``; the pipeline only borrows its metadata
of a tiny sensor to compile the kernels on (``analysis.pipeline.process.warm_up``).
"""
