"""Target (metric) calibrations kept by the service, one per camera and lens setting.

Stored as ``DATA/metric-calibrations/<serial>/metric-<serial>-z<zoom>-f<focus>.json`` (the file
``plenodust calibrate-target`` writes, format in docs/interfaces.md): a newer upload for the same
setting replaces the older. Each job's worker picks the one of its exposure's camera, zoom and
focus (:func:`analysis.calibration.metric_files.coordinates_for`); where none fits, the
metadata's thin lens stands in and the result says so.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from analysis.calibration.metric_files import file_name, metric_calibration_from_doc, read_metric_calibration
from analysis.camera.target_mapping import MetricCalibration
from analysis.errors import MetricCalibrationError
from analysis.formats.atomic_write import write_atomic


def _folder_name(serial: str | None) -> str:
    cleaned = "".join(c if c.isalnum() or c in "._-" else "_" for c in (serial or "unknown"))
    return cleaned.lstrip(".") or "unknown"


def parse(data: bytes) -> MetricCalibration:
    """The calibration in an upload.

    Raises
    ------
    MetricCalibrationError
        Not JSON, or not a metric calibration plenodust can read.
    """
    try:
        doc = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MetricCalibrationError(f"the upload is not JSON ({exc}); send the file plenodust calibrate-target "
                                     "wrote") from exc
    return metric_calibration_from_doc(doc, sha1=hashlib.sha1(data).hexdigest())


def adopt(folder: Path, data: bytes) -> tuple[MetricCalibration, Path]:
    """Validate an uploaded calibration file and keep it under ``folder`` (replacing one of the same
    camera and lens setting)."""
    calibration = parse(data)
    target = folder / _folder_name(calibration.camera.serial) / file_name(calibration.camera)
    target.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(target, data)
    return calibration, target


def describe(calibration: MetricCalibration, path: Path) -> dict[str, Any]:
    """What the API says about a stored calibration."""
    held = calibration.report.get("comparison", {}).get(calibration.mapping.kind, {})
    return {**calibration.camera.to_dict(), "model": calibration.mapping.kind, "mapping": calibration.mapping.name,
            "sha1": calibration.sha1, "created_utc": calibration.created_utc, "file": path.name,
            "held_out_rms_um": held.get("held_out_rms_um"), "volume": calibration.volume.to_dict()}


def listing(folder: Path) -> list[dict[str, Any]]:
    """Every stored calibration, by serial, zoom and focus."""
    items = []
    for path in sorted(folder.glob("*/*.json")):
        try:
            items.append(describe(read_metric_calibration(path), path))
        except (MetricCalibrationError, OSError):
            continue
    return items
