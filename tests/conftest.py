"""Shared test set-up: a writable numba cache, a small free-space margin for the services, and
paths to the real fixtures."""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".cache" / "numba"))
# The service keeps 1 GB free on a lab's data disk; the tests' services write a few MB each, and a
# shared CI disk may have less than 1 GB left (CI failed so: every service "not ready"). The margin
# itself is tested with its own setting (test_service_first_hour).
os.environ.setdefault("PLENODUST_MIN_FREE_BYTES", str(100_000_000))

import pytest  # noqa: E402

SHARED = ROOT.parent / "shared"
FIXTURES_REAL = SHARED / "fixtures" / "real"


@pytest.fixture(scope="session")
def real_fixtures() -> Path:
    if not FIXTURES_REAL.is_dir():
        pytest.fail(f"real fixtures not found at {FIXTURES_REAL}; CI clones shared/ beside the repository")
    return FIXTURES_REAL


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--camera", action="store_true", default=False,
                     help="also run the tests that need a real Lytro F01 on USB (tests/test_driver_with_device.py)")


@pytest.fixture()
def real_camera(request: pytest.FixtureRequest):
    """An open real F01 on USB; the test is skipped unless pytest runs with ``--camera``."""
    if not request.config.getoption("--camera"):
        pytest.skip("needs a real Lytro F01 on USB: run pytest with --camera")
    import driver

    with driver.open_usb() as camera:
        yield camera
