"""Target calibrations on disk, one per camera and lens setting, picked like the white images.

A metric calibration (``plenodust calibrate-target``, :mod:`analysis.pipeline.target`) holds only
for the camera, zoom and focus it was made at: refocusing a different zoom or focus maps ``alpha``
to other depths. :func:`choose_metric_calibration` therefore picks, from a file or a folder of
them, the one whose serial, ``zoomStep`` and ``focusStep`` are the exposure's;
:func:`coordinates_for` falls back to the metadata's thin lens (saying so) where there is none.

File format (JSON, ``format = "plenodust.metric-calibration"``, ``version = 1``; docs/interfaces.md):
``camera`` (serial, zoom_step, focus_step), ``white_sha1``, ``created_utc``, ``model`` (the
mapping used: ``physical`` or ``polynomial``), ``mappings`` (every mapping fitted, each with its
``kind`` and parameters), ``volume`` (what the target covered), ``report`` (residuals per stage
position and axis in micrometres, fitted and held back; the comparison of the mappings; the
target, its exposures and the pipeline parameters used), ``input`` and ``frame`` (the units).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Mapping

from analysis.camera.coordinates import Calibration3D, ThinLensCalibration
from analysis.camera.model import CameraModel
from analysis.camera.target_mapping import CalibratedVolume, CameraKey, MetricCalibration, mapping_from_dict
from analysis.errors import MetricCalibrationError
from analysis.formats.atomic_write import write_atomic

FORMAT = "plenodust.metric-calibration"
VERSION = 1
SUFFIX = ".json"


def camera_key(metadata: Mapping[str, Any], serial: str | None) -> CameraKey:
    """The camera and lens setting of a picture (its serial, ``zoomStep``, ``focusStep``)."""
    model = CameraModel.from_metadata(metadata)
    return CameraKey(serial, model.zoom_step, model.focus_step)


def metric_calibration_doc(calibration: MetricCalibration) -> dict[str, Any]:
    """The file's JSON document."""
    return {"format": FORMAT, "version": VERSION, "camera": calibration.camera.to_dict(),
            "white_sha1": calibration.white_sha1, "created_utc": calibration.created_utc,
            "model": calibration.mapping.kind,
            "mappings": {calibration.mapping.kind: calibration.mapping.to_dict(),
                         **{kind: m.to_dict() for kind, m in calibration.alternatives.items()
                            if kind != calibration.mapping.kind}},
            "volume": calibration.volume.to_dict(), "report": calibration.report,
            "input": {"sx_m, sy_m": "lens-plane position in metres from the optical axis "
                                    "(analysis.camera.image_grid.ImageGrid.to_lens_plane of output pixels x, y)",
                      "alpha": "refocus parameter"},
            "frame": "the target's: X along its rows of dots, Y down its columns, Z the stage position; mm"}


def metric_calibration_from_doc(doc: Mapping[str, Any], *, sha1: str | None = None) -> MetricCalibration:
    """A :class:`MetricCalibration` from its JSON document.

    Raises
    ------
    MetricCalibrationError
        Not a metric calibration, a newer version, or damaged.
    """
    if not isinstance(doc, Mapping) or doc.get("format") != FORMAT:
        raise MetricCalibrationError("not a plenodust metric calibration (no \"format\": \"plenodust.metric-"
                                     "calibration\"); make one with plenodust calibrate-target")
    version = doc.get("version")
    if not isinstance(version, int) or version > VERSION or version < 1:
        raise MetricCalibrationError(f"metric calibration version {version!r} is not supported (this plenodust "
                                     f"reads version {VERSION}); update plenodust or calibrate again")
    try:
        mappings = {kind: mapping_from_dict(values) for kind, values in doc["mappings"].items()}
        chosen = mappings[doc["model"]]
        return MetricCalibration(mapping=chosen, camera=CameraKey.from_dict(doc["camera"]),
                                 volume=CalibratedVolume.from_dict(doc["volume"]), alternatives=mappings,
                                 report=dict(doc.get("report", {})), white_sha1=doc.get("white_sha1"),
                                 created_utc=str(doc.get("created_utc", "")), sha1=sha1)
    except (KeyError, TypeError, ValueError) as exc:
        raise MetricCalibrationError(f"the metric calibration is damaged ({type(exc).__name__}: {exc}); "
                                     "run plenodust calibrate-target again") from exc


def save_metric_calibration(calibration: MetricCalibration, path: str | Path) -> Path:
    """Write the calibration as JSON (atomically). A folder gets :func:`file_name`."""
    path = Path(path)
    if path.is_dir():
        path = path / file_name(calibration.camera)
    data = (json.dumps(metric_calibration_doc(calibration), indent=1, allow_nan=True) + "\n").encode()
    return write_atomic(path, data)


def read_metric_calibration(path: str | Path) -> MetricCalibration:
    """Read a metric calibration file.

    Raises
    ------
    MetricCalibrationError
        For a file that is not one (or not valid JSON).
    """
    data = Path(path).read_bytes()
    try:
        doc = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MetricCalibrationError(f"{path} is not JSON ({exc}); give the file plenodust calibrate-target "
                                     "wrote") from exc
    try:
        return metric_calibration_from_doc(doc, sha1=hashlib.sha1(data).hexdigest())
    except MetricCalibrationError as exc:
        raise MetricCalibrationError(f"{path}: {exc}") from None


def file_name(camera: CameraKey) -> str:
    """``metric-<serial>-z<zoomStep>-f<focusStep>.json``: one file per camera and lens setting."""
    serial = "".join(c if c.isalnum() or c in "-_" else "_" for c in (camera.serial or "unknown"))
    return f"metric-{serial}-z{camera.zoom_step}-f{camera.focus_step}{SUFFIX}"


def matches(calibration: MetricCalibration, key: CameraKey) -> bool:
    """Whether a calibration holds for a picture: same serial (when both are known), zoom and focus."""
    cam = calibration.camera
    if cam.serial is not None and key.serial is not None and cam.serial != key.serial:
        return False
    return cam.zoom_step == key.zoom_step and cam.focus_step == key.focus_step


def choose_metric_calibration(source: str | Path, metadata: Mapping[str, Any], *, serial: str | None
                              ) -> MetricCalibration | None:
    """The metric calibration for a picture from a file or a folder of them (and its subfolders).

    Parameters
    ----------
    source : path
        A calibration file (it must fit the picture), or a folder of them (the newest that fits is
        taken; None when none does).
    metadata : mapping
        The picture's frame metadata.
    serial : str or None
        The picture's camera serial.

    Raises
    ------
    MetricCalibrationError
        A file that is not a calibration, or one made for another camera or lens setting.
    """
    source = Path(source)
    key = camera_key(metadata, serial)
    if source.is_file():
        calibration = read_metric_calibration(source)
        if not matches(calibration, key):
            raise MetricCalibrationError(
                f"{source} calibrates {calibration.camera.describe()}, but the picture is from {key.describe()}: "
                "a target calibration holds for one zoom and focus only; calibrate at this setting, or give a "
                "folder of calibrations to pick from")
        return calibration
    if not source.is_dir():
        raise MetricCalibrationError(f"metric calibration {source} does not exist; give the file plenodust "
                                     "calibrate-target wrote, or a folder of them")
    found = []
    for path in sorted(source.rglob(f"*{SUFFIX}")):
        try:
            calibration = read_metric_calibration(path)
        except MetricCalibrationError:
            continue  # other JSON files may share the folder
        if matches(calibration, key):
            found.append(calibration)
    return max(found, key=lambda c: c.created_utc) if found else None


def coordinates_for(source: str | Path | None, metadata: Mapping[str, Any], *, serial: str | None
                    ) -> Calibration3D | None:
    """The physical calibration for a picture: its metric calibration from ``source``, else the
    metadata's thin lens marked as the fallback (None without a source: the pipeline's default).

    Raises
    ------
    MetricCalibrationError
        As :func:`choose_metric_calibration`.
    """
    if source is None:
        return None
    chosen = choose_metric_calibration(source, metadata, serial=serial)
    if chosen is not None:
        return chosen
    key = camera_key(metadata, serial)
    return ThinLensCalibration(CameraModel.from_metadata(metadata).optics,
                               fallback_reason=f"no target calibration in {Path(source).name} for {key.describe()}; "
                                               "calibrate this setting with plenodust calibrate-target")
