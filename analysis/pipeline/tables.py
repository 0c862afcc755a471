"""The look-up tables of a calibration, from the caller's cache, from disk, or built.

Two tables per calibration: the refocus's (micro-image rims left out, where neighbours' light
leaks in) and the depth fit's (:data:`FIT_TABLE_RIM_PX`: rims kept, where a particle's light that
splits between lenses often lands). Both are kept in the caller's :class:`analysis.cache.Cache`
and, when it has a directory, on disk beside the calibration cache, with the refocus
normalisations computed so far.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
from pathlib import Path

import numpy as np

from analysis.cache import Cache, remove_older_versions
from analysis.calibration.calibrate import Calibration
from analysis.calibration.drift import LatticeDrift
from analysis.errors import CalibrationError
from analysis.formats.mapped_npz import release_pages
from analysis.calibration.profile import micro_image_template
from analysis.lightfield.drifted_table import MicroImageTemplate, shifted_table
from analysis.lightfield.table import (NORMALISATION, TABLE_FORMAT_VERSION, LightFieldTable, build_table, load_table,
                                       save_table)

from .stages import trim_heap

log = logging.getLogger(__name__)

#: The depth fit's table keeps the micro-image rims (half a pixel beyond the aperture's image).
FIT_TABLE_RIM_PX = -0.5
#: The refocus's table leaves out a pixel of rim (crosstalk from the neighbouring micro-image).
REFOCUS_TABLE_RIM_PX = 1.0
#: Smallest white-image value of a pixel either table uses (gaps between micro-images, dead pixels).
MIN_WEIGHT = 0.05


def table_cache_path(cache_dir: Path, calibration: Calibration, grid_oversample: float,
                     rim_px: float = REFOCUS_TABLE_RIM_PX) -> Path:
    """Where the look-up table of a calibration is kept, beside the calibration cache (named by its white
    image and, when it leaves defective pixels out, by the defect map's key)."""
    serial = calibration.serial or "unknown-serial"
    defects = f".d{calibration.defects_key[:16]}" if calibration.defects_key else ""
    return (Path(cache_dir) / serial
            / f"{calibration.white_sha1}.lut.v{TABLE_FORMAT_VERSION}{defects}.o{grid_oversample:g}.r{rim_px:g}.npz")


def get_table(calibration: Calibration, cache: Cache, *, grid_oversample: float = 1.0,
              rim_px: float = REFOCUS_TABLE_RIM_PX) -> LightFieldTable:
    """The look-up table of a calibration: from ``cache``, else from its directory, else built.

    The table leaves the calibration's defective pixels out (``Calibration.defect_mask``). A table
    built here is written to the cache's directory (when it has one);
    :func:`save_normalisations` writes it again once the cache holds new refocus normalisations
    for it. ``rim_px`` as in :func:`analysis.lightfield.table.build_table`.
    """
    key = ("table", calibration.serial, calibration.white_sha1, calibration.model.lattice, calibration.defects_key,
           float(grid_oversample), float(rim_px))
    table = cache.get(key)
    if table is not None:
        return table
    path = (table_cache_path(cache.directory, calibration, grid_oversample, rim_px)
            if cache.directory is not None else None)
    if path is not None and path.is_file():
        try:
            table = load_table(path, cache=cache)
        except Exception as exc:  # a stale or broken cache is rebuilt, never trusted
            log.warning("look-up table cache %s unusable (%s); rebuilding it", path, exc)
            table = None
    if table is not None and not _built_for(table, calibration):
        log.warning("look-up table cache %s was built for another sensor or lattice than its calibration's; "
                    "rebuilding it", path)
        table = None
    if table is None:
        table = build_table(calibration, grid_oversample=grid_oversample, rim_px=rim_px, min_weight=MIN_WEIGHT)
        release_pages(calibration.devignetting)
        if path is not None and _save_quietly(table, path, cache):
            table = _mapped_again(table, path, cache)
        trim_heap()  # the build's temporaries: 3 times the table
    return cache.put(key, table)


def normalisation_keys(table: LightFieldTable, cache: Cache) -> frozenset:
    """Which refocus normalisations ``cache`` holds for the table."""
    return frozenset(key for key, _ in cache.entries(NORMALISATION, table.uid))


def save_normalisations(table: LightFieldTable, calibration: Calibration, cache: Cache, *,
                        grid_oversample: float, before: frozenset) -> None:
    """Write the table again with its normalisations when ``cache`` holds any beyond ``before``
    (and has a directory), so that a fresh process refocuses at full speed from its first exposure."""
    if cache.directory is not None and normalisation_keys(table, cache) != before:
        path = table_cache_path(cache.directory, calibration, grid_oversample)
        if _save_quietly(table, path, cache):
            _mapped_again(table, path, cache)  # the new normalisations too


def release_table_pages(table: LightFieldTable, cache: Cache) -> None:
    """Give back the pages of the table's per-sample columns and of the refocus normalisations
    ``cache`` holds for it, where they are mapped from the disk cache
    (:func:`analysis.lightfield.table.load_table`): read back from the file cache if used again.

    Between the refocus stages and the depth fits, which read the raw image through the fit's own
    table: an F01's refocus table and the ~90 normalisations of a survey and a fine stack hold 95 MB;
    and the fit table's pages while a later detection pass refocuses."""
    for column in (table.pixel_index, table.lens, table.u_m, table.v_m, table.weight):
        release_pages(column)
    for _, value in cache.entries(NORMALISATION, table.uid):
        release_pages(value)


def _built_for(table: LightFieldTable, calibration: Calibration) -> bool:
    """Whether ``table`` maps the sensor as ``calibration``'s lattice does, checked on a few samples.

    A table file is named by its white image, and a white image's lattice can change without its
    bytes changing (a newer lattice fit, a calibration cache rebuilt); a table of the old lattice
    would put every sample at the wrong aperture point."""
    model = calibration.model
    if (table.height, table.width) != (model.height, model.width) or table.pixel_index.size == 0:
        return False
    picks = np.unique(np.linspace(0, table.pixel_index.size - 1, 17).astype(np.int64))
    rows, cols = np.divmod(table.pixel_index[picks].astype(np.int64), model.width)
    u, v = model.aperture_coordinates(cols + 0.5, rows + 0.5)
    tolerance = 1e-4 * model.optics.aperture_m_per_px  # float32 storage: far below a lattice change
    basis = model.lattice.basis * (model.optics.pixel_pitch_m / model.optics.projection_factor)
    return bool(np.all(np.abs(u - table.u_m[picks]) <= tolerance) and np.all(np.abs(v - table.v_m[picks]) <= tolerance)
                and np.allclose(basis, table.basis_m, rtol=1e-9, atol=0.0))


def _save_quietly(table: LightFieldTable, path: Path, cache: Cache) -> bool:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        save_table(table, path, cache=cache)
        remove_older_versions(path.parent, path.name.split(".lut.v")[0] + ".lut.v", TABLE_FORMAT_VERSION)
    except OSError as exc:
        log.warning("could not write look-up table cache %s (%s); continuing without it", path, exc)
        return False
    return True


def _mapped_again(table: LightFieldTable, path: Path, cache: Cache) -> LightFieldTable:
    """The table (and its normalisations in ``cache``) as just written to ``path``, mapped from it
    instead of held in memory, so that a worker that built them holds only what a worker that reads
    them holds (:func:`analysis.lightfield.table.load_table`); the table itself if it cannot be read."""
    try:
        return load_table(path, cache=cache)
    except CalibrationError as exc:
        log.warning("look-up table cache %s unreadable just after writing it (%s); keeping it in memory", path, exc)
        return table


#: A drift is applied in steps of this (pixels; radians for the rotation, which moves the sensor's
#: corners by about 2300 times as much), so that exposures of one run, whose lattice drifts slowly,
#: share their drifted table.
DRIFT_STEP_PX = 0.01
DRIFT_STEP_RAD = 4e-6
#: Spacing (px) of the fine grid of the micro-image model a drifted table scales to each lens's core.
DRIFT_TEMPLATE_STEP_PX = 1.0 / 16.0


def drifted_fit_table(calibration: Calibration, cache: Cache, drift: LatticeDrift | None) -> LightFieldTable:
    """The depth fit's table as an exposure with this lattice drift sees it (the calibration's own
    when there is none, or less than a step): :func:`analysis.lightfield.drifted_table.shifted_table`.

    ``cache`` keeps one drifted table per calibration, the last one asked for: a run's lattice
    drifts slowly, and each drifted table holds 90 MB (an F01's) that older drifts would keep
    until the cache's budget pushed them out. With a directory, the cache also keeps the last
    :data:`DRIFTED_TABLES_KEPT` drifted tables of each white image on disk, and the table is mapped
    from its file, as the others are: its pages can then be given back while the stacks are made
    (:func:`release_table_pages`), and a new process reads it instead of deriving it again. The
    undrifted table's columns, which the drifted one replaces, give their pages back when they are
    mapped from the disk cache."""
    base = get_table(calibration, cache, rim_px=FIT_TABLE_RIM_PX)
    if drift is None:
        return base
    q = (round(drift.shift_px[0] / DRIFT_STEP_PX), round(drift.shift_px[1] / DRIFT_STEP_PX),
         round(drift.rotation_rad / DRIFT_STEP_RAD))
    if q == (0, 0, 0):
        return base
    key = ("drifted_table", base.uid)
    held = cache.take(key)  # taken, so that the previous drift's is not held while another is built
    if held is not None and held[0] == q:
        return cache.put(key, held)[1]
    del held
    template = drift_template(calibration)
    path = None
    if cache.directory is not None:
        path = _drifted_table_path(cache.directory, calibration, base, q, template)
        table = _read_drifted(path)
        if table is not None:
            return cache.put(key, (q, table))[1]
    lattice = calibration.model.lattice
    steps = LatticeDrift((q[0] * DRIFT_STEP_PX, q[1] * DRIFT_STEP_PX), q[2] * DRIFT_STEP_RAD, drift.sigma_px,
                         drift.n_blocks)
    cx, cy = lattice.centre(base.lens_ij[:, 0], base.lens_ij[:, 1])
    shift = np.column_stack(steps.displacement(cx, cy, lattice))
    optics = calibration.model.optics
    table = shifted_table(base, calibration.devignetting, shift, m_per_px=optics.pixel_pitch_m / optics.projection_factor,
                          template=template, defects=calibration.defect_mask, min_weight=MIN_WEIGHT)
    release_pages(calibration.devignetting)
    if path is not None and _save_quietly(table, path, cache):
        table = _mapped_again(table, path, cache)
        _remove_older_drifts(path)
    return cache.put(key, (q, table))[1]


#: Drifted tables kept on disk per white image (an F01's: 90 MB each), the most recently written.
DRIFTED_TABLES_KEPT = 4
#: Part of a drifted table file's name: change it when :func:`shifted_table` changes what it makes.
DRIFTED_TABLE_VERSION = 1


def _drifted_table_path(cache_dir: Path, calibration: Calibration, base: LightFieldTable, q: tuple[int, int, int],
                        template: MicroImageTemplate) -> Path:
    """Beside the undrifted table, named by everything the drifted one is made from: the undrifted
    table (its uid changes when it is built again), the drift's steps, the micro-image model."""
    digest = hashlib.sha1(repr((DRIFTED_TABLE_VERSION, base.uid, q, MIN_WEIGHT, template.step_px)).encode())
    digest.update(np.ascontiguousarray(template.values).tobytes())
    serial = calibration.serial or "unknown-serial"
    return Path(cache_dir) / serial / f"{calibration.white_sha1}.drift.{digest.hexdigest()[:20]}.npz"


def _read_drifted(path: Path) -> LightFieldTable | None:
    if not path.is_file():
        return None
    try:
        table = load_table(path)
    except CalibrationError as exc:  # rebuilt, never trusted
        log.warning("drifted look-up table cache %s unusable (%s); deriving it again", path, exc)
        return None
    with contextlib.suppress(OSError):
        path.touch()  # recently used: kept by _remove_older_drifts
    return table


def _remove_older_drifts(path: Path) -> None:
    """Delete all but the :data:`DRIFTED_TABLES_KEPT` most recently used drifted tables of the white image."""
    def used(p: Path) -> float:
        try:
            return p.stat().st_mtime
        except OSError:
            return -math.inf  # gone already: not one of those kept
    others = sorted(path.parent.glob(path.name.split(".drift.")[0] + ".drift.*.npz"), key=used, reverse=True)
    for old in others[DRIFTED_TABLES_KEPT:]:
        with contextlib.suppress(OSError):
            old.unlink()


def drift_template(calibration: Calibration) -> MicroImageTemplate:
    """The calibration's micro-image, to which :func:`analysis.lightfield.drifted_table.shifted_table`
    scales each lens's core for its gain: its fitted profile, or without one the lattice's aperture
    image under the default blur."""
    profile = calibration.profile
    if profile is None:
        blur, radius, rim = calibration.blur_px, calibration.model.optics.micro_image_radius_px, 1.0
    else:
        blur, radius, rim = profile.blur_px, profile.radius_px, profile.rim_response
    return micro_image_model(blur, radius, rim)


def micro_image_model(blur_px: float, radius_px: float, rim_response: float) -> MicroImageTemplate:
    """A micro-image of this profile (:func:`analysis.calibration.profile.micro_image_template`) as
    :func:`analysis.lightfield.drifted_table.shifted_table` takes it."""
    values = micro_image_template(blur_px, radius_px, rim_response, half_width_px=radius_px + 5.0 * blur_px + 2.0,
                                  step_px=DRIFT_TEMPLATE_STEP_PX)
    return MicroImageTemplate.cropped(values, DRIFT_TEMPLATE_STEP_PX)
