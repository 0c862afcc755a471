"""Each run's shots linked into trajectories as their results arrive.

After a job's result is stored, :meth:`RunTracker.advance` links the run's frames in order, as far
as their results allow: the next frame with a result is linked
(:class:`analysis.tracking.linking.Linker`), a failed one is skipped (the linker's memory
bridges it), one still queued or running stops it until its result comes. Linking one frame:

- reads that frame's table from its result file and its shot time (the metadata's clock, in the
  result's provenance; the upload time where the metadata have none);
- writes, in place in the run file (:func:`service.run_file.update_columns`), its ``particle``
  (trajectory id) and ``t`` (s since the run's first linked shot), and ``vX, vY, vZ`` of every
  frame whose velocities this shot changes (the last ``memory + 2``);
- stores the structure of the shot before it (whose velocities are now central) and of this one
  (provisional: count and shells, no temperature until its velocities are central) in the
  ``frame_summaries`` table (:mod:`analysis.tracking.summary`), with the
  position noise measured over the last :data:`NOISE_FRAMES` frames.

Everything it touches is a fixed number of recent frames, so a shot costs the same at frame 10
and at frame 10 000. The linker lives in memory; its counters (next frame, next id, clock origin)
are in the ``run_tracks`` table, and after a restart the linker is rebuilt from the run file's
last frames. Where a run file had to be rebuilt from the result files (a crash), its trajectory
columns start empty and the run is linked again from frame 0 (once).
"""

from __future__ import annotations

import json
import logging
import math
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from analysis.tracking.linking import LinkParams, Linker
from analysis.tracking.summary import summarize
from analysis.tracking.temperature import position_noise
from analysis.tracking.trajectories import velocities
from analysis.tracking.uncertainty import depth_errors
from analysis.tracking.units import particle_mass_kg
from service import run_file
from service.store import Store

log = logging.getLogger(__name__)

#: Frames of recent rows kept per run: the position noise is measured over them.
NOISE_FRAMES = 12
_KEPT = ("index", "particle", "t", "X", "Y", "Z", "alpha", "alpha_std", "blur_pitches")


@dataclass
class _RunState:
    linker: Linker
    next_frame: int = 0
    t0: float | None = None
    last_t: float | None = None
    recent: list[tuple[int, dict[str, np.ndarray]]] = field(default_factory=list)


class RunTracker:
    """Links each run's frames as their results arrive (see the module docstring).

    Parameters
    ----------
    store : Store
    params : LinkParams, optional
    mass_kg : float, optional
        Particle mass for temperatures (default: the paper's MF particles).
    """

    def __init__(self, store: Store, *, params: LinkParams | None = None, mass_kg: float | None = None) -> None:
        self.store = store
        self.params = params or LinkParams()
        self.mass_kg = particle_mass_kg() if mass_kg is None else mass_kg
        self._states: dict[str, _RunState] = {}
        self._locks: dict[str, threading.Lock] = {}
        self._guard = threading.Lock()

    def _lock(self, run: str) -> threading.Lock:
        with self._guard:
            return self._locks.setdefault(run, threading.Lock())

    def forget(self, run: str) -> None:
        """Link the run again from frame 0 (its run file was rebuilt without trajectories)."""
        with self._guard:
            self._states.pop(run, None)
        with self.store.db.write() as conn:
            conn.execute("DELETE FROM run_tracks WHERE run = ?", (run,))
            conn.execute("DELETE FROM frame_summaries WHERE run = ?", (run,))

    def advance(self, run: str) -> list[int]:
        """Link the run's frames that can be linked now; returns them."""
        with self._lock(run):
            state = self._states.get(run) or self._load(run)
            self._states[run] = state
            linked = []
            while True:
                rows = self.store.db.read(
                    "SELECT e.id, e.created_at, r.exposure_id AS result, (SELECT state FROM jobs WHERE "
                    "exposure_id = e.id ORDER BY seq DESC LIMIT 1) AS state FROM exposures e LEFT JOIN results r "
                    "ON r.exposure_id = e.id WHERE e.run = ? AND e.frame = ?", (run, state.next_frame))
                if not rows:
                    break
                row = rows[0]
                if row["result"] is not None:
                    if not self._link(run, state, row["id"], float(row["created_at"])):
                        break
                    linked.append(state.next_frame - 1)
                elif row["state"] == "failed":
                    state.next_frame += 1  # never processed: the memory bridges it
                    self._save(run, state)
                else:
                    break
            return linked

    # -- one frame ----------------------------------------------------------------------------

    def _link(self, run: str, state: _RunState, exposure_id: str, uploaded_at: float) -> bool:
        frame = state.next_frame
        columns = self.store.read_columns(exposure_id)
        shot = self.store.read_provenance(exposure_id).get("shot_time") or uploaded_at
        if state.t0 is None:
            state.t0 = float(shot)
        t = float(shot) - state.t0
        if state.last_t is not None and t <= state.last_t:
            log.warning("run %s frame %d: its clock (%.3f s) is not after the frame before's (%.3f s); "
                        "taking it 1 ms later", run, frame, t, state.last_t)
            t = state.last_t + 1e-3
        step = state.linker.add(frame, t, columns)
        n = len(step.particle)
        kept = {name: np.asarray(columns[name]) for name in _KEPT if name in columns}
        kept.update(particle=step.particle, t=np.full(n, t))
        state.recent.append((frame, kept))
        state.recent = [(f, r) for f, r in state.recent if f >= frame - max(NOISE_FRAMES, 2 * self.params.memory + 3)]
        updates, window = self._velocity_updates(state, frame)
        updates[frame].update(particle=step.particle, t=np.full(n, t))
        with self.store.run_guard(run):
            written = run_file.update_columns(self.store.run_path(run), updates)
        if not written:
            log.warning("run %s: frame %d's rows are not in the run file as expected; linking the run again "
                        "from its first frame", run, frame)
            self.forget(run)
            return False
        state.next_frame, state.last_t = frame + 1, t
        self._summaries(run, window, frames=[f for f in (frame - 1, frame) if f in updates])
        self._save(run, state)
        return True

    def _velocity_updates(self, state: _RunState, frame: int) -> tuple[dict[int, dict[str, np.ndarray]], Any]:
        """Velocities of the recent frames, and the columns to write for those this shot changed."""
        import pandas as pd

        table = pd.concat([pd.DataFrame({**rows, "frame": np.full(len(rows["particle"]), f)})
                           for f, rows in state.recent], ignore_index=True)
        open_depth = np.zeros(len(table), bool)
        for f, idx in table.groupby("frame").indices.items():
            part = table.iloc[idx]
            open_depth[idx] = depth_errors({c: part[c].to_numpy() for c in part.columns},
                                           open_blur_pitches=self.params.open_blur_pitches).open
        v = velocities(table["particle"].to_numpy(), table["t"].to_numpy(float),
                       table[["X", "Y", "Z"]].to_numpy(float), open_depth)
        table["vX"], table["vY"], table["vZ"] = v[:, 0], v[:, 1], v[:, 2]
        changed = [f for f, _ in state.recent if f >= frame - self.params.memory - 1]
        groups = table.groupby("frame").indices
        updates = {f: {name: table[name].to_numpy()[groups[f]] for name in ("vX", "vY", "vZ")} for f in changed}
        return updates, table

    def _summaries(self, run: str, window: Any, *, frames: list[int]) -> None:
        linked = window[window["particle"] >= 0]
        if linked.empty:
            return
        noise = position_noise(linked["particle"].to_numpy(), linked["frame"].to_numpy(), linked["t"].to_numpy(),
                               linked[["X", "Y", "Z"]].to_numpy(float), blocks=4)
        # The newest shot's velocities are one-sided: its temperature waits for the next shot.
        summary = summarize(window, mass_kg=self.mass_kg, frames=frames, noise=noise, two_sided_only=True)
        rows = []
        for k in range(len(summary.table["frame"])):
            data = {name: _plain(values[k]) for name, values in summary.table.items()}
            data["noise_X_mm"], data["noise_Y_mm"], data["noise_Z_mm"] = (_plain(v) for v in noise.sigma_mm)
            rows.append((run, int(data["frame"]), data["t"], json.dumps(data)))
        with self.store.db.write() as conn:
            conn.executemany("INSERT INTO frame_summaries (run, frame, t, data) VALUES (?, ?, ?, ?) "
                             "ON CONFLICT (run, frame) DO UPDATE SET t = excluded.t, data = excluded.data", rows)

    # -- state --------------------------------------------------------------------------------

    def _save(self, run: str, state: _RunState) -> None:
        with self.store.db.write() as conn:
            conn.execute("INSERT INTO run_tracks (run, next_frame, next_id, t0, last_t) VALUES (?, ?, ?, ?, ?) "
                         "ON CONFLICT (run) DO UPDATE SET next_frame = excluded.next_frame, next_id = excluded.next_id,"
                         " t0 = excluded.t0, last_t = excluded.last_t",
                         (run, state.next_frame, state.linker.next_id, state.t0, state.last_t))

    def _load(self, run: str) -> _RunState:
        """The run's state after a restart: counters from the database, recent frames from the run file."""
        rows = self.store.db.read("SELECT * FROM run_tracks WHERE run = ?", (run,))
        if not rows or rows[0]["next_frame"] == 0:
            return _RunState(Linker(self.params))
        row = rows[0]
        first = row["next_frame"] - max(NOISE_FRAMES, 2 * self.params.memory + 3)
        with self.store.run_guard(run):
            path = self.store.run_path(run)
            try:
                table = run_file.read_frames(path, first, row["next_frame"] - 1) if path.exists() else {}
            except (run_file.RunFileDamaged, run_file.RunFileBusy):
                table = {}
        recent = []
        if table and "particle" in table:
            for f in np.unique(table["frame"]):
                sel = table["frame"] == f
                recent.append((int(f), {name: np.asarray(table[name])[sel] for name in _KEPT if name in table}))
        last = [r for f, r in recent if f == row["next_frame"] - 1]
        if not recent or (last and last[0]["particle"].size and np.all(last[0]["particle"] < 0)):
            # The run file lost its trajectory columns (rebuilt): link again from the start.
            log.warning("run %s: its run file holds no trajectories for the frames linked; linking it again", run)
            self.forget(run)
            return _RunState(Linker(self.params))
        linker = Linker.resume([(f, float(r["t"][0]) if len(r["t"]) else 0.0, r) for f, r in recent],
                               next_id=row["next_id"], params=self.params)
        return _RunState(linker, row["next_frame"], row["t0"], row["last_t"], recent)

    def summary(self, run: str) -> dict[str, np.ndarray] | None:
        """The run's per-shot structure by column (None before any shot is linked)."""
        rows = self.store.db.read("SELECT data FROM frame_summaries WHERE run = ? ORDER BY frame", (run,))
        if not rows:
            return None
        data = [json.loads(r["data"]) for r in rows]
        names = list(dict.fromkeys(name for d in data for name in d))
        out = {}
        for name in names:
            values = [d.get(name) for d in data]
            numbers = [math.nan if v is None else v for v in values]
            integer = name in ("frame", "count", "with_velocity", "shells") and None not in values
            out[name] = np.array(numbers, dtype=np.int64 if integer else float)
        return out


def _plain(value: Any) -> Any:
    """A JSON value: NaN and infinities as null, numpy numbers as Python ones."""
    value = value.item() if hasattr(value, "item") else value
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
