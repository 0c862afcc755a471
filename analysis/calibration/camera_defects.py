"""A camera's defect map from its white images, and the maps kept on disk.

The map depends on every frame searched (:func:`analysis.calibration.white_choice.defect_search_frames`:
the picture's white image, a few more bright ones and the dark ones), not only on the white image a
calibration is fitted to, so it is kept in a file of its own, keyed by the frames' SHA-1s
(:func:`analysis.calibration.defects.frames_key`): ``<cache>/<serial>/<key>.defects.v<version>.npz``.
"""

from __future__ import annotations

import json
import logging
import re
import zipfile
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from analysis.camera.model import CameraModel
from analysis.errors import CalibrationError, FormatError
from analysis.formats.atomic_write import atomic_path
from analysis.formats.whites import WhiteImage

from .calibrate import Calibration
from .defects import DEFECTS_VERSION, CalibrationFrame, DefectMap, find_defects, frames_key
from .lattice_fit import fit_lattice
from .white_choice import remembered

log = logging.getLogger(__name__)


def defects_cache_path(cache_dir: Path, serial: str | None, key: str) -> Path:
    """``cache_dir/<serial>/<key>.defects.v<version>.npz`` (serial reduced to safe characters)."""
    safe = re.sub(r"[^A-Za-z0-9_-]", "_", serial) if serial else "unknown-serial"
    return Path(cache_dir) / safe / f"{key}.defects.v{DEFECTS_VERSION}.npz"


def save_defects(defects: DefectMap, path: Path) -> None:
    """Write a defect map (its pixel indices and kinds) through a temp file and an atomic rename."""
    header = {"version": DEFECTS_VERSION, "key": defects.key, "height": defects.height, "width": defects.width,
              "frames": list(defects.frames)}
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, header=np.array(json.dumps(header)), index=defects.index, kind=defects.kind)


def read_defects(path: Path, *, key: str | None = None) -> DefectMap:
    """Read a defect map written by :func:`save_defects`.

    Raises
    ------
    CalibrationError
        If the file is unreadable, of another version, or for other frames.
    """
    try:
        with np.load(path, allow_pickle=False) as npz:
            header: dict[str, Any] = json.loads(str(npz["header"]))
            index, kind = npz["index"].astype(np.int64), npz["kind"].astype(np.int8)
    except (OSError, EOFError, ValueError, KeyError, TypeError, zipfile.BadZipFile) as exc:
        raise CalibrationError(f"defect map {path} is unreadable ({type(exc).__name__}: {exc}); delete it, or let "
                               "load_calibration rebuild it") from None
    if header.get("version") != DEFECTS_VERSION or (key is not None and header.get("key") != key):
        raise CalibrationError(f"defect map {path} is of version {header.get('version')} for frames "
                               f"{header.get('key')}, not {DEFECTS_VERSION} for {key}; delete it, or let "
                               "load_calibration rebuild it")
    size = int(header["height"]) * int(header["width"])
    if index.shape != kind.shape or (index.size and (index.min() < 0 or index.max() >= size)):
        raise CalibrationError(f"defect map {path} holds pixels off its sensor; delete it, or let load_calibration "
                               "rebuild it")
    return DefectMap(int(header["height"]), int(header["width"]), index, kind, tuple(header["frames"]),
                     str(header["key"]))


def search_frames(frames: Sequence[tuple[WhiteImage, bool]], calibration: Calibration) -> Iterator[CalibrationFrame]:
    """The white images to search, decoded one at a time, each with its micro-image lattice.

    Frames at the calibration's zoom and focus share its fitted lattice; others get their own fit
    (seeded from their metadata). A frame whose lattice cannot be fitted, or of another size, is left
    out (logged).
    """
    shape = (calibration.model.height, calibration.model.width)
    for white, dark in frames:
        try:
            raw = white.image()
            if raw.shape != shape:
                log.info("defect search: %s is %s px, the calibration %s; left out", white.name, raw.shape, shape)
                continue
            if (white.zoom_step, white.focus_step) == (calibration.zoom_step, calibration.focus_step):
                lattice = calibration.lattice
            else:
                model = CameraModel.from_metadata(white.metadata)
                lattice = fit_lattice(raw, model.lattice, black_level=model.black_level).lattice
        except (CalibrationError, FormatError) as exc:
            log.info("defect search: %s left out (%s)", white.name, exc)
            continue
        yield CalibrationFrame(white.name, raw, lattice, dark)


def camera_defects(frames: Sequence[tuple[WhiteImage, bool]], calibration: Calibration, *,
                   cache_dir: Path | None = None, serial: str | None = None) -> DefectMap:
    """The defect map of the camera whose white images ``frames`` are (from
    :func:`analysis.calibration.white_choice.defect_search_frames`), read from ``cache_dir`` if kept
    there, else searched (:func:`analysis.calibration.defects.find_defects`) and kept.

    A cache file that cannot be read is logged and rebuilt; one that cannot be written is logged.
    """
    key = frames_key([remembered(white, "sha1", lambda w: w.sha1) for white, _ in frames])
    path = None if cache_dir is None else defects_cache_path(Path(cache_dir), calibration.serial or serial, key)
    if path is not None and path.is_file():
        try:
            defects = read_defects(path, key=key)
            if (defects.height, defects.width) == (calibration.model.height, calibration.model.width):
                return defects
            log.warning("defect map %s is for another sensor size; searching again", path)
        except CalibrationError as exc:
            log.warning("defect map cache %s is unusable (%s); searching again", path, exc)
    decoded = search_frames(frames, calibration)
    model = calibration.model
    defects = find_defects(decoded, black_level=model.black_level, radius_px=model.optics.micro_image_radius_px,
                           key=key)
    if path is not None:
        try:
            save_defects(defects, path)
        except OSError as exc:
            log.warning("could not write defect map cache %s (%s); continuing without it", path, exc)
    return defects
