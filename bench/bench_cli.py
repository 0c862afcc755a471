"""Start-up time of the ``plenodust`` command: ``--help`` and commands that need no kernels.

Each command runs in a fresh process, five times; prints the median and the best wall time,
and whether numba or scipy were imported (they should not be, for these commands).

    .venv/bin/python bench/bench_cli.py
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT.parent / "shared" / "fixtures" / "real" / "f01-raw-image-section-stripped.lfp"

# Runs main() and reports which heavy modules the command imported.
PROBE = ("import sys, runpy; sys.argv = ['plenodust'] + sys.argv[1:]\n"
         "from service.cli.main import main\n"
         "try:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
         "print('HEAVY', sorted(m for m in ('numba', 'scipy') if m in sys.modules), file=sys.stderr)")


def measure(argv: list[str], runs: int = 5) -> tuple[float, float, str]:
    times, heavy = [], ""
    for _ in range(runs):
        start = time.perf_counter()
        done = subprocess.run([str(ROOT / ".venv" / "bin" / "plenodust"), *argv], capture_output=True, cwd=ROOT)
        times.append(time.perf_counter() - start)
        del done
    probe = subprocess.run([sys.executable, "-c", PROBE, *argv], capture_output=True, text=True, cwd=ROOT)
    heavy = next((line for line in probe.stderr.splitlines() if line.startswith("HEAVY")), "HEAVY ?")
    return statistics.median(times), min(times), heavy.removeprefix("HEAVY ")


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "calibration").mkdir()
        commands = [["--help"], ["inspect", "--help"], ["camera", "--help"], ["process", "--help"],
                    ["inspect", str(FIXTURE)], ["camera", "list", "--simulated", tmp]]
        for argv in commands:
            median, best, heavy = measure(argv)
            shown = " ".join(a if len(a) < 40 else Path(a).name for a in argv)
            print(f"plenodust {shown:<45} median {median:.2f} s, best {best:.2f} s, imports {heavy}", flush=True)


if __name__ == "__main__":
    main()
