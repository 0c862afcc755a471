"""Time from ``plenodust demo`` printing its URL to the first result (what ``make run`` shows).

Runs the demo of a checkout (default: this one) on a free port, reads its first line (the URL),
then polls the API until the first exposure is done; prints the times to the workers being
ready, the first shot queued and the first result, then stops the demo with SIGINT (as Ctrl-C
would) and says whether anything printed a traceback. The numba cache is the checkout's
``.cache/numba`` (where ``make setup`` compiled the kernels), as under ``make run``.

    .venv/bin/python bench/bench_first_result.py [--root CHECKOUT] [--runs 3]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import time
import urllib.request
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]


def _get(url: str) -> tuple[int, dict]:
    try:
        with urllib.request.urlopen(url, timeout=5) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read() or b"{}")
    except OSError:
        return 0, {}


def one_run(root: Path) -> dict:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "NUMBA_CACHE_DIR": str(root / ".cache" / "numba")}
    start = time.monotonic()
    demo = subprocess.Popen([str(root / ".venv" / "bin" / "plenodust"), "demo", "--port", str(port)], cwd=root,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    assert demo.stdout is not None
    demo.stdout.readline()
    url_at = time.monotonic()
    base = f"http://127.0.0.1:{port}"
    marks: dict[str, float] = {}
    while "first_result_s" not in marks and time.monotonic() - url_at < 300:
        status, _ = _get(base + "/readyz")
        if status == 200 and "ready_s" not in marks:
            marks["ready_s"] = time.monotonic() - url_at
        status, page = _get(base + "/api/v1/runs/demo/exposures")
        items = page.get("items", []) if status == 200 else []
        if items and "first_queued_s" not in marks:
            marks["first_queued_s"] = time.monotonic() - url_at
        if any(e["state"] == "done" for e in items):
            marks["first_result_s"] = time.monotonic() - url_at
        time.sleep(0.1)
    os.killpg(demo.pid, signal.SIGINT)
    output, _ = demo.communicate(timeout=60)
    marks["url_after_start_s"] = url_at - start
    marks["traceback_on_ctrl_c"] = "Traceback" in output or "KeyboardInterrupt" in output
    return marks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, default=HERE, help="checkout with a .venv made by make setup")
    parser.add_argument("--runs", type=int, default=1)
    args = parser.parse_args()
    for k in range(args.runs):
        marks = one_run(args.root.resolve())
        print(f"run {k + 1}: " + ", ".join(f"{name} {value:.1f}" if isinstance(value, float) else f"{name} {value}"
                                          for name, value in marks.items()), flush=True)


if __name__ == "__main__":
    main()
