"""``plenodust serve`` in a subprocess on a free loopback port, for end-to-end tests."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]


class ServiceProcess:
    """The real service (uvicorn, worker pool) in its own process group.

    Parameters
    ----------
    data_dir : Path
        ``--data``; reuse it to restart a service on the same state.
    env : dict
        Extra ``PLENODUST_*`` variables.
    """

    def __init__(self, data_dir: Path, *, env: dict[str, str] | None = None, args: list[str] = ()) -> None:
        self.data_dir = data_dir
        full_env = {**os.environ, **(env or {})}
        full_env.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".cache" / "numba"))
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "service.cli.main", "serve", "--port", "0", "--data", str(data_dir), *args],
            cwd=ROOT, env=full_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            start_new_session=True)
        self.lines: list[str] = []
        self._port: int | None = None
        self._found = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)
            m = re.search(r"Uvicorn running on http://127\.0\.0\.1:(\d+)", line)
            if m:
                self._port = int(m.group(1))
                self._found.set()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self._port}"

    def wait_ready(self, timeout_s: float = 120.0) -> ServiceProcess:
        """Wait for ``/readyz`` to answer 200. A service that does not get there is stopped (a
        failed test must not leave a server and its workers running) and the error says what
        ``/readyz`` last answered (workers warming, data disk full, ...)."""
        deadline = time.monotonic() + timeout_s
        last = ""
        try:
            if not self._found.wait(timeout_s):
                raise TimeoutError("service did not start:\n" + "".join(self.lines[-30:]))
            while time.monotonic() < deadline:
                if self.proc.poll() is not None:
                    raise RuntimeError("service exited:\n" + "".join(self.lines[-30:]))
                try:
                    r = httpx.get(self.url + "/readyz", timeout=5)
                    if r.status_code == 200:
                        return self
                    last = r.text
                except httpx.TransportError:
                    pass
                time.sleep(0.2)
            raise TimeoutError(f"service never became ready: /readyz said {last}\n" + "".join(self.lines[-30:]))
        except BaseException:
            self.stop()
            raise

    def kill(self, *, group: bool = False) -> None:
        """SIGKILL the server process (``group``: and its workers at once, as a power cut would)."""
        if group:
            os.killpg(self.proc.pid, signal.SIGKILL)
        else:
            os.kill(self.proc.pid, signal.SIGKILL)
        self.proc.wait(timeout=30)

    def children(self) -> list[int]:
        """Process ids of the server's children (pool workers, resource tracker)."""
        found = []
        for task in Path(f"/proc/{self.proc.pid}/task").iterdir():
            found += [int(c) for c in (task / "children").read_text().split()]
        return found

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=30)
        self._reader.join(timeout=5)
        if self.proc.stdout is not None:
            self.proc.stdout.close()

    def log(self) -> str:
        return "".join(self.lines)
