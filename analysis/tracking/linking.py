"""Linking the particles of consecutive shots into trajectories, one shot at a time.

:class:`Linker` keeps the trajectories that may still continue (seen within the last ``memory``
frames) and links each new shot to them:

1. **Prediction.** Each trajectory's last position is carried to the new shot's time by the
   cluster's rigid motion (turn about its centre plus drift, :mod:`analysis.tracking.motion`),
   fitted to the previous links: a turning cluster links like a still one.
2. **Distance.** Per axis, the offset from the prediction is divided by the spread of the steps
   that remain after the prediction (thermal motion plus both positions' errors), measured from
   the run itself per axis: depth, 5 to 10 times less precise than lateral positions, weighs
   that much less. A particle whose ``alpha_std`` says its depth is worse than the table's
   typical one gets that extra room, and one whose light fell in one micro-lens (depth open over
   a known interval, :mod:`analysis.tracking.uncertainty`) is compared by the gap between the
   intervals: its depth may sit anywhere in it without costing a jump. A trajectory last seen
   ``g`` shot intervals ago gets ``g`` times the step spread, ``g`` at most ``memory + 1``: after a
   pause in shooting the range stays what ``memory`` missed shots allow (a particle that moved
   farther starts a new trajectory rather than taking a far-off one's id).
3. **Search range** from the data: ``gate_sigma`` step spreads, at most ``max_step_nn`` of the mean
   nearest-neighbour distance of the shot.
4. **Assignment.** The links of least total squared distance, one-to-one, each below the gate
   (:mod:`analysis.tracking.assignment`); what stays unlinked starts a new trajectory, or waits up
   to ``memory`` frames for its particle to be seen again.

The first pair of shots is linked three times over (no prediction, then refined prediction and
step spreads); every later shot twice (the prediction from the previous shot, then from its own
links). The cost of one shot grows with its particle count, never with the run's length.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np
from scipy.spatial import cKDTree

from analysis.errors import ParameterError

from .assignment import assign
from .motion import RigidMotion, fit_motion
from .uncertainty import DepthErrors, depth_errors

POSITION_COLUMNS = ("X", "Y", "Z")


@dataclass(frozen=True)
class LinkParams:
    """Settings of :class:`Linker`.

    Attributes
    ----------
    memory : int
        Frames a particle may go unseen and still continue its trajectory (trackpy's ``memory``).
    gate_sigma : float
        Largest normalised distance (step spreads) of a link.
    max_step_nn : float
        The search range never exceeds this fraction of the mean nearest-neighbour distance.
    open_blur_pitches : float
        Below this blur (lens pitches) a particle's depth counts as open (``blur_pitches``).
    predict : bool
        Predict positions with the cluster's rigid motion.
    step_mm : tuple of 3 float, optional
        Fixed step spread per axis (mm per shot interval); default: measured from the run.
    initial_step_nn : float
        Step spread assumed before the first links, as a fraction of the mean NN distance.
    min_step_nn : float
        Floor of the measured step spread, as a fraction of the mean NN distance.
    rescue_gate_sigma : float
        After the assignment, a trajectory and a particle both left unlinked are linked up to this
        many step spreads when each is the other's only candidate, the step beyond ``gate_sigma``
        runs along the radius from the cluster's centre, and the step stays within
        ``max_step_nn`` of the NN distance: a particle hopping between shells steps farther than
        thermal motion does, and radially, while a trajectory whose particle went unseen must not
        take a neighbour that reappears beside it. 0 turns it off.
    from_before_last : bool
        A trajectory may also continue from the position before its last one, so one detection
        far off (most often in depth) is passed over rather than ending the trajectory.
    """

    memory: int = 2
    gate_sigma: float = 5.0
    max_step_nn: float = 0.8
    open_blur_pitches: float = 1.0
    predict: bool = True
    step_mm: tuple[float, float, float] | None = None
    initial_step_nn: float = 0.25
    min_step_nn: float = 0.005
    rescue_gate_sigma: float = 8.0
    from_before_last: bool = True

    def __post_init__(self) -> None:
        if self.memory < 0 or self.gate_sigma <= 0 or self.max_step_nn <= 0:
            raise ParameterError(f"memory={self.memory} must be >= 0, gate_sigma and max_step_nn positive")
        if self.step_mm is not None and (len(self.step_mm) != 3 or min(self.step_mm) <= 0):
            raise ParameterError("step_mm: give three positive step spreads (X, Y, Z) in mm, or leave it out")

    def to_dict(self) -> dict[str, Any]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


@dataclass
class LinkStep:
    """What linking one shot gave.

    Attributes
    ----------
    particle : ndarray of int64, shape (n,)
        Trajectory id of each row (-1 where the row has no finite position).
    linked : int
        Rows that continue a trajectory.
    search_range_mm : float
        The largest offset a link was looked for within.
    step_mm : ndarray of shape (3,)
        The step spread per axis (X, Y, Z) used, mm per shot interval.
    motion : RigidMotion or None
        The cluster's rigid motion fitted to the links.
    """

    particle: np.ndarray
    linked: int = 0
    search_range_mm: float = float("nan")
    step_mm: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    motion: RigidMotion | None = None


@dataclass
class _Active:
    """Trajectories that may still continue: last id, position, time, frame and depth interval, and
    the position and time of the observation before the last (NaN where there is none)."""

    ids: np.ndarray
    xyz: np.ndarray
    t: np.ndarray
    frame: np.ndarray
    errors: DepthErrors
    prev_xyz: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    prev_t: np.ndarray = field(default_factory=lambda: np.empty(0))

    def __post_init__(self) -> None:
        if len(self.prev_t) != len(self.ids):  # none known (a restart, an old state)
            self.prev_xyz = np.full((len(self.ids), 3), np.nan)
            self.prev_t = np.full(len(self.ids), np.nan)

    @classmethod
    def empty(cls) -> _Active:
        e = np.empty(0)
        return cls(np.empty(0, np.int64), np.empty((0, 3)), e, np.empty(0, np.int64), DepthErrors.none(e))

    def take(self, index: np.ndarray) -> _Active:
        return _Active(self.ids[index], self.xyz[index], self.t[index], self.frame[index], self.errors.take(index),
                       self.prev_xyz[index], self.prev_t[index])

    @staticmethod
    def join(a: _Active, b: _Active) -> _Active:
        e = DepthErrors(*(np.concatenate([getattr(a.errors, n), getattr(b.errors, n)])
                          for n in ("extra_sigma_mm", "z_low", "z_high")))
        return _Active(np.concatenate([a.ids, b.ids]), np.vstack([a.xyz, b.xyz]), np.concatenate([a.t, b.t]),
                       np.concatenate([a.frame, b.frame]), e, np.vstack([a.prev_xyz, b.prev_xyz]),
                       np.concatenate([a.prev_t, b.prev_t]))


class Linker:
    """Links shots one at a time into trajectories (see the module docstring).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> xyz = rng.uniform(0, 5, size=(50, 3))
    >>> linker = Linker()
    >>> first = linker.add(0, 0.0, {"X": xyz[:, 0], "Y": xyz[:, 1], "Z": xyz[:, 2]})
    >>> moved = xyz[::-1] + 0.01                                   # same particles, listed backwards
    >>> second = linker.add(1, 1.0, {"X": moved[:, 0], "Y": moved[:, 1], "Z": moved[:, 2]})
    >>> bool(np.all(second.particle == first.particle[::-1]))
    True
    """

    def __init__(self, params: LinkParams | None = None) -> None:
        self.params = params or LinkParams()
        self.active = _Active.empty()
        self.next_id = 0
        self.step_mm: np.ndarray | None = None if self.params.step_mm is None else np.asarray(self.params.step_mm)
        self.interval_s: float | None = None
        self.motion: RigidMotion | None = None
        self.nn_mm: float | None = None
        self.last_frame: int | None = None

    # -- one shot -------------------------------------------------------------------------------

    def add(self, frame: int, t_s: float, table: Mapping[str, np.ndarray]) -> LinkStep:
        """Link one shot's particles to the trajectories so far.

        Parameters
        ----------
        frame : int
            Frame number; larger than the previous shot's.
        t_s : float
            Shot time in seconds (any origin), larger than the previous shot's.
        table : mapping of str to ndarray
            The shot's particle table: ``X, Y, Z`` (mm) and, where present, ``alpha``,
            ``alpha_std``, ``blur_pitches``.

        Returns
        -------
        LinkStep

        Raises
        ------
        ParameterError
            If the frame or time does not come after the previous shot's.
        """
        if self.last_frame is not None and (frame <= self.last_frame or t_s <= float(np.max(self.active.t, initial=-np.inf))):
            raise ParameterError(f"frame {frame} at t = {t_s} s does not come after frame {self.last_frame}; "
                                 "link shots in the order they were taken (frames and times increasing)")
        xyz = np.stack([np.asarray(table[c], float) for c in POSITION_COLUMNS], axis=1)
        n = len(xyz)
        errors = depth_errors(table, open_blur_pitches=self.params.open_blur_pitches)
        usable = np.flatnonzero(np.all(np.isfinite(xyz), axis=1))
        particle = np.full(n, -1, np.int64)
        step = LinkStep(particle)
        if usable.size >= 2:
            d, _ = cKDTree(xyz[usable]).query(xyz[usable], k=2)
            nn = float(d[:, 1].mean())
            self.nn_mm = nn if self.nn_mm is None else 0.8 * self.nn_mm + 0.2 * nn
        old = self.active.take(self.active.frame >= frame - self.params.memory - 1)
        rows = np.empty(0, np.int64)
        cols = np.empty(0, np.int64)
        if len(old.ids) and usable.size and self.nn_mm is not None:
            gaps = t_s - old.t
            if self.interval_s is None:
                self.interval_s = float(np.min(gaps))
            if self.step_mm is None:
                self.step_mm = np.full(3, self.params.initial_step_nn * self.nn_mm)
                passes = 3
            else:
                passes = 2
            motion = self.motion
            for k in range(passes):
                rows, cols, radius = self._link_once(old, xyz[usable], errors.take(usable), t_s, motion)
                if k < passes - 1 or self.params.step_mm is None:
                    motion = self._refit(old, rows, xyz[usable], cols, t_s, errors.take(usable), first=passes == 3)
            self.motion = motion
            step.search_range_mm = radius
            rows, cols = self._before_last(old, rows, xyz[usable], cols, errors.take(usable), t_s, motion)
            rows, cols = self._rescue(old, rows, xyz[usable], cols, errors.take(usable), t_s, motion)
            cols = usable[cols]
        step.step_mm = np.array(self.step_mm) if self.step_mm is not None else step.step_mm
        step.motion = self.motion
        particle[cols] = old.ids[rows]
        step.linked = int(rows.size)
        fresh = np.setdiff1d(usable, cols)
        particle[fresh] = self.next_id + np.arange(fresh.size)
        self.next_id += int(fresh.size)
        # Trajectories seen now, and those still within the memory.
        seen = np.r_[cols, fresh]
        prev_xyz = np.vstack([old.xyz[rows], np.full((fresh.size, 3), np.nan)])
        prev_t = np.r_[old.t[rows], np.full(fresh.size, np.nan)]
        now = _Active(particle[seen], xyz[seen], np.full(seen.size, float(t_s)), np.full(seen.size, frame, np.int64),
                      errors.take(seen), prev_xyz, prev_t)
        waiting = np.setdiff1d(np.arange(len(old.ids)), rows)
        waiting = waiting[old.frame[waiting] >= frame - self.params.memory]
        self.active = _Active.join(now, old.take(waiting))
        self.last_frame = frame
        if self.motion is None and seen.size:
            self.motion = RigidMotion.still(xyz[seen].mean(axis=0), t_s)
        return step

    def _variances(self, old: _Active, rows: np.ndarray, new_errors: DepthErrors, cols: np.ndarray,
                   t_s: float) -> np.ndarray:
        gap = self._gaps(old.t[rows], t_s)
        var = (np.asarray(self.step_mm)[None, :] * gap[:, None]) ** 2
        var[:, 2] += old.errors.extra_sigma_mm[rows] ** 2 + new_errors.extra_sigma_mm[cols] ** 2
        return var

    def _gaps(self, t_old: np.ndarray, t_s: float | np.ndarray) -> np.ndarray:
        """Shot intervals since each trajectory was seen, between 1 and ``memory + 1``."""
        return np.clip((t_s - t_old) / self.interval_s, 1.0, self.params.memory + 1.0)

    def _rescue(self, old: _Active, rows: np.ndarray, xyz: np.ndarray, cols: np.ndarray, errors: DepthErrors,
                t_s: float, motion: RigidMotion | None) -> tuple[np.ndarray, np.ndarray]:
        """Link what the assignment left unlinked among itself, with the wider rescue gate."""
        gate = self.params.rescue_gate_sigma
        if gate <= self.params.gate_sigma or rows.size == len(old.ids) or cols.size == len(xyz):
            return rows, cols
        left_old = np.setdiff1d(np.arange(len(old.ids)), rows)
        left_new = np.setdiff1d(np.arange(len(xyz)), cols)
        r, c, _ = self._link_once(old.take(left_old), xyz[left_new], errors.take(left_new), t_s, motion, gate=gate,
                                  unique=True, radial=True)
        return np.r_[rows, left_old[r]], np.r_[cols, left_new[c]]

    def _link_once(self, old: _Active, xyz: np.ndarray, errors: DepthErrors, t_s: float,
                   motion: RigidMotion | None, *, gate: float | None = None, unique: bool = False,
                   radial: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
        gate = self.params.gate_sigma if gate is None else gate
        rows, cols, cost, reach = self._candidates(old, xyz, errors, t_s, motion, gate, radial=radial)
        if unique:  # only pairs with no other candidate on either side
            one_row = np.bincount(rows, minlength=len(old.ids)) == 1
            one_col = np.bincount(cols, minlength=len(xyz)) == 1
            keep = one_row[rows] & one_col[cols]
            rows, cols, cost = rows[keep], cols[keep], cost[keep]
        r, c = assign(rows, cols, cost, len(old.ids), len(xyz), unlinked_cost=gate ** 2 / 2)
        return r, c, reach

    def _before_last(self, old: _Active, rows: np.ndarray, xyz: np.ndarray, cols: np.ndarray, errors: DepthErrors,
                     t_s: float, motion: RigidMotion | None) -> tuple[np.ndarray, np.ndarray]:
        """Trajectories left unlinked try again from the position before their last, among the
        particles left unlinked, where each is the other's only candidate: one detection far off (a
        depth outlier) is passed over instead of ending the trajectory (its particle, found again,
        would start a new one). The last detection is passed over only when the trajectory runs
        smoother without it (the new particle is fewer step spreads from the position before than
        the last one was): a trajectory whose particle went unseen must not take a neighbour
        instead (on a realistic run, most of what this pass linked wrongly)."""
        left_old = np.setdiff1d(np.arange(len(old.ids)), rows)
        left_old = left_old[np.isfinite(old.prev_t[left_old]) & ~old.errors.open[left_old]]
        left_new = np.setdiff1d(np.arange(len(xyz)), cols)
        if not self.params.from_before_last or left_old.size == 0 or left_new.size == 0:
            return rows, cols
        z = old.prev_xyz[left_old, 2]
        earlier = _Active(old.ids[left_old], old.prev_xyz[left_old], old.prev_t[left_old], old.frame[left_old],
                          DepthErrors(old.errors.extra_sigma_mm[left_old], z, z))
        r, c, _ = self._link_once(earlier, xyz[left_new], errors.take(left_new), t_s, motion, unique=True)
        before = earlier.take(r)
        smoother = (self._step_cost(before.xyz, before.t, xyz[left_new[c]], np.full(r.size, t_s), motion)
                    < self._step_cost(before.xyz, before.t, old.xyz[left_old[r]], old.t[left_old[r]], motion))
        r, c = r[smoother], c[smoother]
        return np.r_[rows, left_old[r]], np.r_[cols, left_new[c]]

    def _step_cost(self, xyz_from: np.ndarray, t_from: np.ndarray, xyz_to: np.ndarray, t_to: np.ndarray,
                   motion: RigidMotion | None) -> np.ndarray:
        """Squared steps in step spreads (per axis, scaled by the shots between) from each row of
        ``xyz_from`` to the same row of ``xyz_to``, after the cluster's motion."""
        predicted = np.array(xyz_from, float)
        if self.params.predict and motion is not None:
            for i in range(len(predicted)):
                predicted[i] = motion.predict(predicted[i:i + 1], t_from[i:i + 1], float(t_to[i]))[0]
        gap = self._gaps(t_from, t_to)
        return np.sum((xyz_to - predicted) ** 2 / (np.asarray(self.step_mm)[None, :] * gap[:, None]) ** 2, axis=1)

    def _candidates(self, old: _Active, xyz: np.ndarray, errors: DepthErrors, t_s: float,
                    motion: RigidMotion | None, gate: float, *,
                    radial: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Pairs (trajectory, particle) within the gate, their costs, and the largest reach (mm);
        ``radial``: only pairs whose offset across the radius from the cluster's centre stays
        within the regular gate and whose step stays within ``max_step_nn`` of the NN distance."""
        p = self.params
        predicted = motion.predict(old.xyz, old.t, t_s) if (p.predict and motion is not None) else old.xyz
        shift_z = predicted[:, 2] - old.xyz[:, 2]
        gap = self._gaps(old.t, t_s)
        spread = float(np.max(self.step_mm))
        reach = np.minimum(gate * spread * gap, p.max_step_nn * self.nn_mm * gap)
        open_width = (old.errors.z_high - old.errors.z_low) + float(np.max(errors.z_high - errors.z_low, initial=0.0))
        radius = reach + open_width + gate * old.errors.extra_sigma_mm
        found = cKDTree(xyz).query_ball_point(predicted, radius, return_sorted=False)
        counts = np.fromiter((len(f) for f in found), np.int64, len(found))
        rows = np.repeat(np.arange(len(found)), counts)
        cols = np.fromiter((j for f in found for j in f), np.int64, int(counts.sum()))
        offset = xyz[cols] - predicted[rows]
        # Depth: the gap between the two open intervals (zero where they overlap).
        low_old, high_old = old.errors.z_low[rows] + shift_z[rows], old.errors.z_high[rows] + shift_z[rows]
        dz = np.maximum(0.0, np.maximum(errors.z_low[cols] - high_old, low_old - errors.z_high[cols]))
        dz = np.where(old.errors.open[rows] | errors.open[cols], dz, offset[:, 2])
        offset[:, 2] = dz
        var = self._variances(old, rows, errors, cols, t_s)
        cost = np.sum(offset ** 2 / var, axis=1)
        # The search range in mm: a link also stays within max_step_nn of the mean NN distance.
        within = np.linalg.norm(offset, axis=1) <= p.max_step_nn * self.nn_mm * gap[rows]
        keep = within & (cost <= gate ** 2)
        if radial:
            # Beyond the gate only along the radius from the cluster's centre (a shell hop): the
            # step across it stays within the gate, and a hop crosses one shell spacing (about the
            # NN distance), however long the particle went unseen.
            centre = motion.centre_at(t_s) if motion is not None else xyz.mean(axis=0)
            out = predicted[rows] - centre
            out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)
            across = offset - np.sum(offset * out, axis=1, keepdims=True) * out
            keep &= ((np.sum(across ** 2 / var, axis=1) <= p.gate_sigma ** 2)
                     & (np.linalg.norm(offset, axis=1) <= p.max_step_nn * self.nn_mm))
        return rows[keep], cols[keep], cost[keep], float(np.max(reach, initial=0.0))

    def _refit(self, old: _Active, rows: np.ndarray, xyz: np.ndarray, cols: np.ndarray, t_s: float,
               errors: DepthErrors, *, first: bool) -> RigidMotion | None:
        """The rigid motion and per-axis step spreads measured from this shot's links."""
        if rows.size == 0:
            return self.motion
        settled = ~(old.errors.open[rows] | errors.open[cols])
        use = settled if settled.sum() >= 4 else np.ones(rows.size, bool)
        motion = fit_motion(old.xyz[rows[use]], old.t[rows[use]], xyz[cols[use]], t_s) if self.params.predict else None
        if self.params.step_mm is not None:
            return motion
        one = use & ((t_s - old.t[rows]) <= 1.5 * self.interval_s)
        if one.sum() < 8:
            return motion
        predicted = motion.predict(old.xyz[rows[one]], old.t[rows[one]], t_s) if motion else old.xyz[rows[one]]
        residual = xyz[cols[one]] - predicted
        # A robust spread (MAD), floored; shot to shot it changes slowly.
        measured = 1.4826 * np.median(np.abs(residual - np.median(residual, axis=0)), axis=0)
        measured = np.maximum(measured, self.params.min_step_nn * self.nn_mm)
        if first:
            self.step_mm = measured
        else:
            self.step_mm = np.sqrt(0.8 * np.asarray(self.step_mm) ** 2 + 0.2 * measured ** 2)
        return motion

    # -- state, for a service that links shots as they come ----------------------------------

    @classmethod
    def resume(cls, recent: list[tuple[int, float, Mapping[str, np.ndarray]]], *, next_id: int,
               params: LinkParams | None = None) -> Linker:
        """A linker that goes on after shots linked earlier (e.g. read back from a run file).

        Parameters
        ----------
        recent : list of (frame, t_s, table)
            The last shots linked (at least ``memory + 1`` of them), each table with its
            ``particle`` column; oldest first.
        next_id : int
            The next trajectory id to hand out.
        params : LinkParams, optional

        The step spreads and the cluster's motion are measured again on the next shot.
        """
        linker = cls(params)
        linker.next_id = int(next_id)
        if not recent:
            return linker
        parts = []
        for frame, t_s, table in sorted(recent, key=lambda r: r[0]):
            ids = np.asarray(table["particle"], np.int64)
            xyz = np.stack([np.asarray(table[c], float) for c in POSITION_COLUMNS], axis=1)
            keep = (ids >= 0) & np.all(np.isfinite(xyz), axis=1)
            errors = depth_errors(table, open_blur_pitches=linker.params.open_blur_pitches).take(keep)
            parts.append(_Active(ids[keep], xyz[keep], np.full(keep.sum(), float(t_s)),
                                 np.full(keep.sum(), int(frame), np.int64), errors))
        every = parts[0]
        for part in parts[1:]:
            every = _Active.join(part, every)  # newest first
        _, first = np.unique(every.ids, return_index=True)
        last_frame = int(recent[-1][0]) if recent else None
        latest = every.take(first)
        rest = every.take(np.setdiff1d(np.arange(len(every.ids)), first))  # each one's observation before
        ids, second = np.unique(rest.ids, return_index=True)
        where = np.searchsorted(ids, latest.ids)
        known = (where < ids.size) & (ids[np.minimum(where, ids.size - 1)] == latest.ids) if ids.size else \
            np.zeros(len(latest.ids), bool)
        latest.prev_xyz[known] = rest.xyz[second[where[known]]]
        latest.prev_t[known] = rest.t[second[where[known]]]
        linker.active = latest.take(latest.frame >= last_frame - linker.params.memory)
        linker.last_frame = last_frame
        times = sorted({float(r[1]) for r in recent})
        linker.interval_s = float(np.min(np.diff(times))) if len(times) > 1 else None
        if len(linker.active.ids) >= 2:
            linker.nn_mm = float(cKDTree(latest.xyz).query(latest.xyz, k=2)[0][:, 1].mean())
        return linker

    def state(self) -> dict[str, Any]:
        """Everything needed to go on linking later (JSON-able): :meth:`from_state` reads it."""
        a = self.active
        m = self.motion
        return {"params": self.params.to_dict(), "next_id": self.next_id, "last_frame": self.last_frame,
                "interval_s": self.interval_s, "nn_mm": self.nn_mm,
                "step_mm": None if self.step_mm is None else [float(v) for v in self.step_mm],
                "motion": None if m is None else {"centre_mm": m.centre_mm.tolist(), "t_s": m.t_s,
                                                  "velocity_mm_s": m.velocity_mm_s.tolist(),
                                                  "omega_rad_s": m.omega_rad_s.tolist()},
                "active": {"ids": a.ids.tolist(), "xyz": a.xyz.tolist(), "t": a.t.tolist(), "frame": a.frame.tolist(),
                           "extra": a.errors.extra_sigma_mm.tolist(), "z_low": a.errors.z_low.tolist(),
                           "z_high": a.errors.z_high.tolist(),
                           "prev_xyz": np.where(np.isfinite(a.prev_xyz), a.prev_xyz, None).tolist(),
                           "prev_t": np.where(np.isfinite(a.prev_t), a.prev_t, None).tolist()}}

    @classmethod
    def from_state(cls, state: Mapping[str, Any]) -> Linker:
        params = dict(state["params"])
        if params.get("step_mm") is not None:
            params["step_mm"] = tuple(params["step_mm"])
        linker = cls(LinkParams(**params))
        linker.next_id = int(state["next_id"])
        linker.last_frame = state["last_frame"]
        linker.interval_s = state["interval_s"]
        linker.nn_mm = state["nn_mm"]
        linker.step_mm = None if state["step_mm"] is None else np.asarray(state["step_mm"], float)
        m = state["motion"]
        linker.motion = None if m is None else RigidMotion(np.asarray(m["centre_mm"]), float(m["t_s"]),
                                                           np.asarray(m["velocity_mm_s"]), np.asarray(m["omega_rad_s"]))
        a = state["active"]
        linker.active = _Active(np.asarray(a["ids"], np.int64), np.asarray(a["xyz"], float).reshape(-1, 3),
                                np.asarray(a["t"], float), np.asarray(a["frame"], np.int64),
                                DepthErrors(np.asarray(a["extra"], float), np.asarray(a["z_low"], float),
                                            np.asarray(a["z_high"], float)),
                                np.asarray(a.get("prev_xyz", []), float).reshape(-1, 3),  # None -> NaN
                                np.asarray(a.get("prev_t", []), float))
        return linker
