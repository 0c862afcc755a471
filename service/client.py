"""A small Python client of the plenodust service, for experiment-control scripts.

Standard library only (``urllib``), so a lab PC's script needs nothing else::

    from service.client import Client

    client = Client("http://127.0.0.1:8000", api_key=None)
    shot = client.take_shot()                       # or client.upload("IMG_0001.lfp")
    job = client.wait(shot.job_id)                  # by the event stream; poll=True polls
    table = client.particles(shot.exposure_id)      # {"X": [...], "Y": [...], "Z": [...], ...}

Every error the service answers arrives as :class:`ProblemError` carrying the problem
document (``status``, ``title``, ``detail``, and any extra fields such as ``job_id``).
"""

from __future__ import annotations

import json
import math
import time
import urllib.error
import urllib.parse
import urllib.request
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: Job states after which a job changes no more (unless sent again).
FINAL_STATES = ("done", "failed")


class ClientError(Exception):
    """The service could not be reached, or answered something that is not the API."""


class ProblemError(ClientError):
    """The service answered with an error (``application/problem+json``).

    Attributes
    ----------
    status : int
        HTTP status.
    problem : dict
        The problem document: ``type``, ``title``, ``status``, ``detail`` and extra fields.
    """

    def __init__(self, status: int, problem: dict[str, Any]) -> None:
        self.status = status
        self.problem = problem
        super().__init__(f"{status} {problem.get('title', '')}: {problem.get('detail', '')}".strip())

    @property
    def detail(self) -> str:
        return str(self.problem.get("detail", ""))


class JobFailed(ClientError):
    """A job ended ``failed``; ``job`` holds it (its ``error`` says why, ``waits_for`` what it lacks)."""

    def __init__(self, job: Job) -> None:
        self.job = job
        super().__init__(f"job {job.id} failed: {job.error}")


class WaitTimeout(ClientError):
    """A job did not finish in the time allowed; ``job`` is its last state."""

    def __init__(self, job: Job, timeout_s: float) -> None:
        self.job = job
        super().__init__(f"job {job.id} still {job.state} after {timeout_s:.0f} s")


@dataclass(frozen=True)
class Accepted:
    """An exposure the service accepted, and its job."""

    exposure_id: str
    job_id: str
    run: str
    frame: int
    created: bool = True


@dataclass(frozen=True)
class Job:
    """A job's state (see ``GET /api/v1/jobs/{id}``)."""

    id: str
    exposure_id: str
    state: str
    progress: float
    error: str | None = None
    stage: str | None = None
    waits_for: str | None = None
    extra: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Job:
        known = ("id", "exposure_id", "state", "progress", "error", "stage", "waits_for")
        return cls(id=data["id"], exposure_id=data["exposure_id"], state=data["state"],
                   progress=float(data.get("progress") or 0.0), error=data.get("error"), stage=data.get("stage"),
                   waits_for=data.get("waits_for"), extra={k: v for k, v in data.items() if k not in known})


class Client:
    """The service at ``base_url``.

    Parameters
    ----------
    base_url : str
        e.g. ``http://127.0.0.1:8000``.
    api_key : str, optional
        The service's ``PLENODUST_API_KEY``, for uploads and shots.
    timeout_s : float
        For each request (a wait is bounded by its own ``timeout_s``).
    """

    def __init__(self, base_url: str, *, api_key: str | None = None, timeout_s: float = 60.0) -> None:
        self.base_url = base_url.rstrip("/")
        self.api_key = api_key
        self.timeout_s = timeout_s

    # -- requests ----------------------------------------------------------------------

    def _request(self, method: str, path: str, *, body: bytes | None = None, content_type: str | None = None,
                 accept: str = "application/json", timeout_s: float | None = None) -> tuple[int, dict, bytes]:
        headers = {"Accept": accept}
        if content_type:
            headers["Content-Type"] = content_type
        if self.api_key:
            headers["Authorization"] = f"Bearer {self.api_key}"
        request = urllib.request.Request(self.base_url + path, data=body, method=method, headers=headers)
        try:
            with urllib.request.urlopen(request, timeout=timeout_s or self.timeout_s) as response:
                return response.status, dict(response.headers), response.read()
        except urllib.error.HTTPError as exc:
            data = exc.read()
            try:
                problem = json.loads(data)
            except ValueError:
                problem = {"title": exc.reason, "detail": data.decode(errors="replace")[:500]}
            raise ProblemError(exc.code, problem if isinstance(problem, dict) else {"detail": str(problem)}) from None
        except (urllib.error.URLError, OSError) as exc:
            raise ClientError(f"cannot reach {self.base_url}: {getattr(exc, 'reason', exc)}") from exc

    def _json(self, method: str, path: str, **kwargs: Any) -> Any:
        _, _, data = self._request(method, path, **kwargs)
        try:
            return json.loads(data)
        except ValueError as exc:
            raise ClientError(f"{method} {path}: the answer is not JSON") from exc

    # -- exposures ---------------------------------------------------------------------

    def upload(self, exposure: str | Path | bytes, *, run: str | None = None,
               metadata: str | Path | bytes | None = None) -> Accepted:
        """Upload an exposure: an ``.lfp`` (path or bytes), or a ``.RAW`` with its ``.TXT`` (``metadata``)."""
        raw = exposure if isinstance(exposure, bytes) else Path(exposure).read_bytes()
        query = f"?run={urllib.parse.quote(run)}" if run else ""
        if metadata is None:
            data = self._json("POST", "/api/v1/exposures" + query, body=raw, content_type="application/octet-stream")
        else:
            txt = metadata if isinstance(metadata, bytes) else Path(metadata).read_bytes()
            body, content_type = _multipart({"raw": ("exposure.RAW", raw), "metadata": ("exposure.TXT", txt)})
            data = self._json("POST", "/api/v1/exposures" + query, body=body, content_type=content_type)
        return _accepted(data)

    def take_shot(self) -> Accepted:
        """Have the camera take a picture; it is pulled and queued (``POST /api/v1/camera/shots``)."""
        return _accepted(self._json("POST", "/api/v1/camera/shots", body=b""))

    def job(self, job_id: str) -> Job:
        return Job.from_json(self._json("GET", f"/api/v1/jobs/{job_id}"))

    def wait(self, job_id: str, *, timeout_s: float = 300.0, poll: bool = False, poll_s: float = 0.5) -> Job:
        """Wait until the job is done and return it.

        Listens to the event stream (``poll=True``: asks every ``poll_s`` seconds instead).

        Raises
        ------
        JobFailed
            If the job failed (``exc.job.error`` says why).
        WaitTimeout
            If it is not finished within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        job = self.job(job_id)
        if job.state not in FINAL_STATES and not poll:
            job = self._wait_by_events(job, deadline)
        while job.state not in FINAL_STATES and time.monotonic() < deadline:
            time.sleep(min(poll_s, max(0.0, deadline - time.monotonic())))
            job = self.job(job_id)
        if job.state == "failed":
            raise JobFailed(job)
        if job.state != "done":
            raise WaitTimeout(job, timeout_s)
        return job

    def _wait_by_events(self, job: Job, deadline: float) -> Job:
        # Events may have passed between reading the job and subscribing: read it once more
        # after the stream is open (the first event, 'hello', says it is).
        try:
            for kind, data in self.events(timeout_s=max(1.0, deadline - time.monotonic())):
                if kind == "hello":
                    job = self.job(job.id)
                elif kind == "job" and data.get("id") == job.id and data.get("state") in FINAL_STATES:
                    return self.job(job.id)
                if job.state in FINAL_STATES or time.monotonic() > deadline:
                    return job
        except (ClientError, TimeoutError):
            pass  # fall back to polling
        return self.job(job.id)

    def events(self, *, timeout_s: float = 300.0) -> Iterator[tuple[str, dict]]:
        """Server-sent events as ``(kind, data)``: ``hello``, ``job``, ``result``, ``camera``, ``run``."""
        request = urllib.request.Request(self.base_url + "/api/v1/events", headers={"Accept": "text/event-stream"})
        try:
            response = urllib.request.urlopen(request, timeout=timeout_s)
        except (urllib.error.URLError, OSError) as exc:
            raise ClientError(f"cannot open the event stream of {self.base_url}: {exc}") from exc
        with response:
            kind, lines = None, []
            for raw in response:
                line = raw.decode().rstrip("\r\n")
                if line.startswith("event:"):
                    kind = line[6:].strip()
                elif line.startswith("data:"):
                    lines.append(line[5:].strip())
                elif not line and kind is not None:
                    yield kind, json.loads("\n".join(lines)) if lines else {}
                    kind, lines = None, []

    def particles(self, exposure_id: str) -> dict[str, list[float]]:
        """The particle table of an exposure, by column (``x, y, alpha, X, Y, Z, brightness, ...``;
        NaN where the table has none)."""
        data = self._json("GET", f"/api/v1/exposures/{exposure_id}/particles?format=json")
        return {name: [math.nan if v is None else v for v in values] for name, values in data["columns"].items()}

    def run_particles(self, run: str) -> dict[str, list[float]]:
        """All particles of a run, with a ``frame`` column."""
        data = self._json("GET", f"/api/v1/runs/{urllib.parse.quote(run)}/particles?format=json")
        return {name: [math.nan if v is None else v for v in values] for name, values in data["columns"].items()}

    def set_run(self, name: str) -> None:
        """File the camera's next shots under run ``name``."""
        self._json("PUT", "/api/v1/runs/current", body=json.dumps({"name": name}).encode(),
                   content_type="application/json")


def _accepted(data: dict[str, Any]) -> Accepted:
    return Accepted(exposure_id=data["exposure_id"], job_id=data["job_id"], run=data["run"], frame=data["frame"],
                    created=data.get("created", True))


def _multipart(files: dict[str, tuple[str, bytes]]) -> tuple[bytes, str]:
    boundary = uuid.uuid4().hex
    parts = []
    for name, (filename, data) in files.items():
        parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"; filename="{filename}"\r\n'
                     "Content-Type: application/octet-stream\r\n\r\n".encode() + data + b"\r\n")
    return b"".join(parts) + f"--{boundary}--\r\n".encode(), f"multipart/form-data; boundary={boundary}"
