"""The camera's files and ours, read and written byte-exactly; no optics here.

- ``raw12``: the sensor's packed 12-bit big-endian raw (``unpack12``, ``pack12``).
- ``lfp``: the LFP container (sections found by magic, SHA-1 verified, byte-exact re-write).
- ``frame_metadata``: the ``.TXT`` frame metadata, plain or in the white images' ``master`` form.
- ``exposure``: an :class:`~analysis.formats.exposure.Exposure` (raw image + metadata) from an
  ``.lfp`` or a ``.RAW``/``.TXT`` pair, and back.
- ``whites``: white images (``MOD_nnnn.RAW``/``.TXT``) and the camera's ``data.C.N`` bundles.
- ``file_report``: what ``plenodust inspect`` prints about any of those files.
- ``atomic_write``: temp file, fsync, rename: nothing half-written.
- ``mapped_npz``: ``.npz`` members memory-mapped instead of read (the calibration and table caches).
- ``particle_table``: the particle table on disk (CSV, NeXus HDF5).

Hands exposures and white images to :mod:`analysis.calibration` and :mod:`analysis.pipeline`.
"""
