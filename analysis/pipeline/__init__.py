"""From an exposure and its calibration to the particle table: the stages composed.

- ``params``: :class:`~analysis.pipeline.params.PipelineParams`, every setting, stored with each result.
- ``tables``: the look-up tables of a calibration, from the caller's cache or disk, or built.
- ``candidates``: detection, linking and peaks on the product stack.
- ``stages``: timing and cost-weighted progress of the stages.
- ``passes``: the detection passes after the first, on the raw image with the found particles' light off.
- ``process``: :func:`~analysis.pipeline.process.process` and ``process_many``.
- ``batch``: the exposure files a list of paths names, and each exposure's calibration from a
  folder of white images (loaded once per camera and zoom/focus setting).
- ``result``: :class:`~analysis.pipeline.result.Result`, the particle table with its provenance.
- ``target``: a metric calibration from a dot target at known stage positions (its dots found with
  ``process``, its grid identified, a mapping fitted: :func:`~analysis.pipeline.target.calibrate_target`).

The caller owns the :class:`analysis.cache.Cache` that a batch shares.
"""
