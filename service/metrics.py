"""Counters and histograms for ``/metrics`` in the Prometheus text format.

Small enough to keep here rather than add a client library: counters with labels, one
histogram, and gauges read at scrape time.
"""

from __future__ import annotations

import bisect
import threading
from collections import defaultdict

DURATION_BUCKETS_S = (0.1, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0, 60.0, 300.0)


class Metrics:
    """Process-wide counters; thread-safe."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.counters: dict[tuple[str, tuple[tuple[str, str], ...]], float] = defaultdict(float)
        self.help: dict[str, str] = {}
        self._hist_counts = [0] * (len(DURATION_BUCKETS_S) + 1)
        self._hist_sum = 0.0
        self._latency_counts = [0] * (len(DURATION_BUCKETS_S) + 1)
        self._latency_sum = 0.0

    def inc(self, name: str, amount: float = 1.0, **labels: str) -> None:
        with self._lock:
            self.counters[(name, tuple(sorted(labels.items())))] += amount

    def observe_job(self, duration_s: float, upload_to_result_s: float | None = None) -> None:
        with self._lock:
            self._hist_counts[bisect.bisect_left(DURATION_BUCKETS_S, duration_s)] += 1
            self._hist_sum += duration_s
            if upload_to_result_s is not None:
                self._latency_counts[bisect.bisect_left(DURATION_BUCKETS_S, upload_to_result_s)] += 1
                self._latency_sum += upload_to_result_s

    def value(self, name: str, **labels: str) -> float:
        with self._lock:
            return self.counters.get((name, tuple(sorted(labels.items()))), 0.0)

    def render(self, gauges: dict[str, tuple[str, dict[tuple[tuple[str, str], ...], float]]]) -> str:
        """The exposition text; ``gauges`` maps name to (help, {labels: value})."""
        lines: list[str] = []
        helps = {
            "plenodust_jobs_total": "Jobs finished, by outcome.",
            "plenodust_job_failures_total": "Jobs that failed for good.",
            "plenodust_job_retries_total": "Jobs given back to the queue after a worker failure.",
            "plenodust_uploads_total": "Upload requests, by result.",
            "plenodust_usb_errors_total": "Errors talking to the camera.",
            "plenodust_camera_pulls_total": "Pictures pulled from the camera.",
        }
        with self._lock:
            counters = dict(self.counters)
            hist = list(self._hist_counts), self._hist_sum
            lat = list(self._latency_counts), self._latency_sum
        by_name: dict[str, list[tuple[tuple[tuple[str, str], ...], float]]] = defaultdict(list)
        for (name, labels), value in counters.items():
            by_name[name].append((labels, value))
        for name in helps:
            by_name.setdefault(name, [])
        for name in sorted(by_name):
            lines.append(f"# HELP {name} {helps.get(name, name)}")
            lines.append(f"# TYPE {name} counter")
            samples = by_name[name] or [((), 0.0)]
            for labels, value in sorted(samples):
                lines.append(f"{name}{_labels(labels)} {value:g}")
        for name, (help_text, samples) in gauges.items():
            lines.append(f"# HELP {name} {help_text}")
            lines.append(f"# TYPE {name} gauge")
            for labels, value in sorted(samples.items()):
                # Whole numbers in full (free bytes), others as %g.
                shown = str(int(value)) if float(value).is_integer() else f"{value:g}"
                lines.append(f"{name}{_labels(labels)} {shown}")
        for name, help_text, (counts, total) in (
                ("plenodust_job_duration_seconds", "Time a worker spent on a job.", hist),
                ("plenodust_upload_to_result_seconds", "Time from upload to stored result.", lat)):
            lines.append(f"# HELP {name} {help_text}")
            lines.append(f"# TYPE {name} histogram")
            cumulative = 0
            for bound, count in zip((*DURATION_BUCKETS_S, float("inf")), counts, strict=True):
                cumulative += count
                le = "+Inf" if bound == float("inf") else f"{bound:g}"
                lines.append(f'{name}_bucket{{le="{le}"}} {cumulative}')
            lines.append(f"{name}_sum {total:g}")
            lines.append(f"{name}_count {cumulative}")
        return "\n".join(lines) + "\n"


def _labels(labels: tuple[tuple[str, str], ...]) -> str:
    if not labels:
        return ""
    inner = ",".join(f'{k}="{_escape(v)}"' for k, v in labels)
    return "{" + inner + "}"


def _escape(value: str) -> str:
    return str(value).replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')
