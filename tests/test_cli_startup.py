"""The CLI starts without the analysis' heavy imports for ``--help`` and commands that need no
kernels (start-up time itself is measured by bench/bench_cli.py, not asserted here)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

PROBE = ("import sys\nfrom service.cli.main import main\n"
         "try:\n    code = main(sys.argv[1:])\nexcept SystemExit as exc:\n    code = exc.code\n"
         "print('IMPORTED', ' '.join(m for m in ('numba', 'scipy', 'analysis.pipeline', 'fastapi') if m in sys.modules))\n"
         "sys.exit(code or 0)")


def imported(*argv: str) -> tuple[int, set[str], str]:
    done = subprocess.run([sys.executable, "-c", PROBE, *argv], capture_output=True, text=True, cwd=ROOT, timeout=120)
    line = next(line for line in done.stdout.splitlines() if line.startswith("IMPORTED"))
    return done.returncode, set(line.split()[1:]), done.stdout + done.stderr


@pytest.mark.parametrize("argv", [["--help"], [], ["inspect", "--help"], ["camera", "--help"],
                                  ["camera", "list", "--help"], ["validate-plane", "--help"]])
def test_help_imports_no_kernels(argv) -> None:
    code, heavy, output = imported(*argv)
    assert code in (0, 2) and heavy == set(), (heavy, output)
    if argv == ["--help"]:
        for command in ("process", "simulate", "serve", "demo", "warm-up", "inspect", "camera"):
            assert command in output


def test_commands_that_need_no_kernels_import_none(real_fixtures, tmp_path) -> None:
    code, heavy, output = imported("inspect", str(real_fixtures / "f01-frame-metadata.json"))
    assert code in (0, 1) and not heavy & {"numba", "scipy", "analysis.pipeline"}, (heavy, output)
    code, heavy, output = imported("camera", "list", "--simulated", str(tmp_path))
    assert code == 0 and heavy == set(), (heavy, output)


def test_a_command_still_gets_its_full_parser() -> None:
    code, heavy, output = imported("process", "--help")
    assert code == 0 and "--calibration" in output and "--alpha-min" in output
