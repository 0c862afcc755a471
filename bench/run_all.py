"""Run every benchmark in this folder in turn and print their reports (``make bench``).

Each benchmark is its own process, so one's memory and numba warm-up do not colour the next.
Pass benchmark names to run only those, e.g. ``bench/run_all.py calibration refocus``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def main(argv: list[str]) -> int:
    scripts = sorted(HERE.glob("bench_*.py"))
    if argv:
        wanted = {f"bench_{name.removeprefix('bench_').removesuffix('.py')}.py" for name in argv}
        scripts = [s for s in scripts if s.name in wanted]
        if not scripts:
            print(f"no benchmark named {', '.join(argv)}; have: "
                  + ", ".join(s.stem.removeprefix('bench_') for s in sorted(HERE.glob('bench_*.py'))))
            return 2
    env = dict(os.environ)
    env.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".cache" / "numba"))
    failed = []
    for script in scripts:
        print(f"\n===== {script.stem} =====", flush=True)
        start = time.perf_counter()
        rc = subprocess.call([sys.executable, str(script)], cwd=ROOT, env=env)
        print(f"----- {script.stem}: exit {rc}, {time.perf_counter() - start:.1f} s", flush=True)
        if rc:
            failed.append(script.stem)
    if failed:
        print("failed: " + ", ".join(failed))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
