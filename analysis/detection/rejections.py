"""Candidates that did not become particles, each with the reason why.

A wrong particle is worse than a missing one, so the pipeline drops candidates readily; every
stage that drops one says why here, so that a user can see what was left out and judge it (the
``--save-stack`` file and the service's result file list them).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .curves import Peaks

#: Why a candidate was dropped (the ``reason`` column), and what that means.
REASONS: dict[str, str] = {
    "noise": ("it stands out too little from the local noise (the shot noise of bright extended light behind it, "
              "a reflection or glow)"),
    "faint": "its fitted light is below the intensity threshold (noise, or the tail of another particle)",
    "fragment": "its fit lights a small part of one micro-image's worth of samples: a hot pixel or a fragment, "
                "not a point source in view",
    "misfit": "the point-source model does not explain its light (its fit's misfit is too large)",
    "duplicate": "its fit converged onto a particle already found",
    "outside_range": "its fit left the alpha range",
    "edge_of_range": "its brightness is highest at the edge of the alpha range: it may lie outside",
    "seen_twice": ("its light is explained by a neighbouring particle (a duplicate, a ghost at another depth, "
                   "or one particle fitted twice on its line of sight)"),
    "weak_residual": "left-over light of the particles found, too weak for a particle of its own",
    "too_close": ("it lies closer to a brighter particle than particles in a plasma come (PipelineParams."
                  "min_separation): that particle's light fitted twice"),
    "extended": "its light does not converge to a point: an extended source (reflection, glow, glare)",
    "glint": ("its light was a glint's far out of focus seen through the cluster (found behind the particles' fits "
              "and taken off the image): without it the fit no longer holds a particle"),
    "apart": ("a point source far in depth from all the others, left out of the range: a compact glint far out "
              "of focus looks so, and so would a lone particle (give the alpha range to include it)"),
}


@dataclass
class Rejections:
    """Dropped candidates, in the order they were dropped: output-image position, alpha, the fitted
    intensity and misfit where there was a fit (NaN otherwise), and a reason (a key of
    :data:`REASONS`)."""

    parts: list[dict[str, np.ndarray]] = field(default_factory=list)

    def add(self, peaks: Peaks, reason: str, *, intensity: np.ndarray | None = None,
            residual: np.ndarray | None = None) -> None:
        """Record ``peaks`` as dropped for ``reason``."""
        if reason not in REASONS:
            raise ValueError(f"unknown rejection reason {reason!r}; known: {sorted(REASONS)}")
        n = len(peaks)
        if n == 0:
            return
        nan = np.full(n, np.nan)
        self.parts.append({"x": np.asarray(peaks.x, float), "y": np.asarray(peaks.y, float),
                           "alpha": np.asarray(peaks.alpha, float),
                           "intensity": nan if intensity is None else np.asarray(intensity, float),
                           "residual": nan if residual is None else np.asarray(residual, float),
                           "reason": np.full(n, reason)})

    def __len__(self) -> int:
        return len(self.table()["x"])

    def counts(self) -> dict[str, int]:
        """How many were dropped for each reason."""
        reasons, n = np.unique(self.table()["reason"], return_counts=True)
        return {str(r): int(k) for r, k in zip(reasons, n)}

    def table(self) -> dict[str, np.ndarray]:
        """The dropped candidates as columns (``reason`` as text), each once: a later detection pass
        finds many of an earlier one's candidates again where the particles' light does not
        change them, and drops them for the same reason (the first record is kept)."""
        names = ("x", "y", "alpha", "intensity", "residual", "reason")
        if not self.parts:
            return {name: (np.empty(0, dtype=str) if name == "reason" else np.empty(0)) for name in names}
        cols = {name: np.concatenate([p[name] for p in self.parts]) for name in names}
        key = np.rec.fromarrays([cols["x"], cols["y"], cols["alpha"], cols["reason"]])
        first = np.sort(np.unique(key, return_index=True)[1])
        return {name: v[first] for name, v in cols.items()}
