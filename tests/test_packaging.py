"""The project's own packaging: its metadata builds without deprecation warnings."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_metadata_builds_without_setuptools_warnings(tmp_path: Path) -> None:
    # The licence as an SPDX string (not the deprecated TOML table) is what keeps `pip install`
    # free of the ~100 lines of setuptools warnings; any deprecation warning is an error here.
    script = ("import setuptools.build_meta as b, sys; "
              f"print(b.prepare_metadata_for_build_wheel({str(tmp_path)!r}))")
    done = subprocess.run([sys.executable, "-W", "error", "-c", script], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    metadata = next(tmp_path.glob("*.dist-info")) / "METADATA"
    text = metadata.read_text()
    assert "License-Expression: MIT" in text
