"""A simulated F01 with known truth, and scoring against it.

- ``camera``: the simulated lens and its metadata.
- ``scenarios``: particle scenes (tilted layer, shadowing pairs, ball, cloud), as designed or varied.
- ``target``: a calibration target, a plate of dots at several stage positions, and the simulated
  camera's front optics (an auxiliary lens, distortion: :mod:`analysis.camera.front_optics`).
- ``render``: white images and exposures rendered by ray tracing; ``kernels`` holds its numba kernels.
- ``scenario_files``: scenario folders written as the camera writes them, with their truth.
- ``realism``: what a real F01 in a chamber adds (the ``Realism`` parameters, a typical preset);
  ``camera_effects`` resolves the camera's part for one serial (blur, micro-image response, lens
  transmission, second stop, hot pixels, lattice drift), ``chamber`` the glow gradient and the
  out-of-focus reflections; ``realism_kernels`` holds their numba kernels.
- ``scoring``: found particles against the truth (recall, precision, depth and lateral errors).
- ``floor_kernels``: the depth floor's grid search (what no estimate from the pixels alone can beat).

Used by the tests, the benches and ``plenodust simulate``; the pipeline only borrows its metadata
of a tiny sensor to compile the kernels on (``analysis.pipeline.process.warm_up``).
"""
