"""A batch of exposures from the command line or a notebook: the files a list of paths names, and
the calibration of each exposure from a folder of white images."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable

if TYPE_CHECKING:
    from analysis.calibration.calibrate import Calibration
    from analysis.formats.exposure import Exposure

EXPOSURE_SUFFIXES = (".lfp", ".raw")


def exposure_files(items: Iterable[str | Path]) -> list[Path]:
    """Files to process: files as given, folders expanded to their ``.lfp``/``.RAW`` (sorted; a
    ``.RAW`` left out where an ``.lfp`` of the same name sits beside it; white images ``MOD_*`` left
    out)."""
    out: list[Path] = []
    for item in items:
        path = Path(item)
        if path.is_dir():
            found = sorted(q for q in path.iterdir() if q.is_file() and q.suffix.lower() in EXPOSURE_SUFFIXES
                           and not q.name.startswith("MOD_"))
            lfp = {q.stem.lower() for q in found if q.suffix.lower() == ".lfp"}
            out.extend(q for q in found if q.suffix.lower() == ".lfp" or q.stem.lower() not in lfp)
        else:
            out.append(path)
    return out


class CalibrationFolder:
    """The calibration of each exposure from a folder of white images, fitted once per camera and
    zoom/focus setting (and kept on disk under ``cache_dir`` when given)."""

    def __init__(self, folder: str | Path, cache_dir: str | Path | None = None) -> None:
        self.folder = Path(folder)
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        self._loaded: dict[tuple, Any] = {}

    def __call__(self, exposure: Exposure) -> Calibration:
        from analysis.calibration.cache import load_calibration

        lens = exposure.metadata.get("devices", {}).get("lens", {})
        key = (exposure.serial, lens.get("zoomStep"), lens.get("focusStep"))
        if key not in self._loaded:
            self._loaded[key] = load_calibration(self.folder, exposure.metadata, serial=exposure.serial,
                                                 cache_dir=self.cache_dir)
        return self._loaded[key]
