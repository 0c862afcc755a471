"""A run's particle tables as one linked table in trackpy's conventions, with velocities.

Columns of the linked table: ``frame`` (0-based, in shot-time order), ``t`` (s since the run's
first shot), ``particle`` (trajectory id, as trackpy's ``link`` names it), ``index`` (the row in its
exposure's own table), ``x, y`` (output-image pixels), ``alpha``, ``X, Y, Z`` (mm), ``vX, vY, vZ``
(mm/s) and the pipeline's quality columns. A velocity is the difference of the trajectory's
neighbouring positions in time over their time apart: central where the particle is seen before
and after, one-sided at a trajectory's ends, empty (NaN) for a trajectory of one shot; ``vZ`` is
empty too where a position it would use has its depth left open (one micro-lens held its light).

Two engines link: ``"plenodust"`` (:class:`analysis.tracking.linking.Linker`, per-particle depth
uncertainty, the cluster's turn predicted) and ``"trackpy"`` (``trackpy.link`` on positions with
depth scaled by the measured lateral-to-depth step ratio, trackpy's nearest-velocity predictor);
``bench/bench_tracking.py`` compares them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from analysis.errors import ParameterError

from .linking import POSITION_COLUMNS, LinkParams, Linker
from .uncertainty import depth_errors

if TYPE_CHECKING:
    import pandas as pd

#: Columns first in a linked table, in this order (the rest follow as they came).
LEADING_COLUMNS = ("frame", "t", "particle", "index", "x", "y", "alpha", "X", "Y", "Z", "vX", "vY", "vZ")
VELOCITY_COLUMNS = ("vX", "vY", "vZ")
Engine = Literal["plenodust", "trackpy"]


def link(table: pd.DataFrame, params: LinkParams | None = None, *, engine: Engine = "plenodust",
         interval_s: float | None = None) -> pd.DataFrame:
    """Link a run's particles into trajectories and add their velocities.

    Parameters
    ----------
    table : pandas.DataFrame
        One row per particle and shot: ``frame``, ``X, Y, Z`` (mm), and ``t`` (s) unless
        ``interval_s`` is given; ``alpha``, ``alpha_std`` and ``blur_pitches`` (as the pipeline
        writes them) let linking weigh each particle's depth by how well it is known. An existing
        ``particle`` column (a per-exposure row number in older tables) becomes ``index``.
    params : LinkParams, optional
    engine : {"plenodust", "trackpy"}
    interval_s : float, optional
        Time between frames, for a table without ``t``.

    Returns
    -------
    pandas.DataFrame
        The rows sorted by ``frame`` then ``index``, with ``particle`` (trajectory id; -1 for a
        row without a finite position), ``t`` and ``vX, vY, vZ`` (see the module docstring).

    Raises
    ------
    ParameterError
        A column is missing, or neither ``t`` nor ``interval_s`` is there.

    Examples
    --------
    >>> import pandas as pd
    >>> shots = pd.DataFrame({"frame": [0, 0, 1, 1], "t": [0.0, 0.0, 1.0, 1.0], "X": [0.0, 1.0, 1.02, 0.01],
    ...                       "Y": [0.0, 0.0, 0.0, 0.0], "Z": [60.0, 60.0, 60.0, 60.0]})
    >>> linked = link(shots)
    >>> linked["particle"].tolist(), linked["vX"].round(2).tolist()
    ([0, 1, 1, 0], [0.01, 0.02, 0.02, 0.01])
    """
    df = prepare(table, interval_s=interval_s)
    params = params or LinkParams()
    if engine == "trackpy":
        df["particle"] = _trackpy_particles(df, params)
    elif engine == "plenodust":
        df["particle"] = _plenodust_particles(df, params)
    else:
        raise ParameterError(f"engine={engine!r}: choose 'plenodust' or 'trackpy'")
    return add_velocities(df, open_blur_pitches=params.open_blur_pitches)


def prepare(table: pd.DataFrame, *, interval_s: float | None = None) -> pd.DataFrame:
    """A copy of ``table`` sorted by frame, with ``index`` and ``t`` (see :func:`link`)."""
    missing = [c for c in ("frame", *POSITION_COLUMNS) if c not in table.columns]
    if missing:
        raise ParameterError(f"the table has no column(s) {missing}; link a run's table with frame, X, Y, Z "
                             "(`plenodust process DIR --out run.csv` writes one)")
    df = table.copy()
    if "particle" in df.columns and "index" not in df.columns:
        df = df.rename(columns={"particle": "index"})
    elif "particle" in df.columns:
        df = df.drop(columns="particle")
    if "index" not in df.columns:
        df["index"] = df.groupby("frame").cumcount()
    if "t" not in df.columns:
        if interval_s is None:
            raise ParameterError("the table has no t column (s since the first shot); give the time between "
                                 "shots (interval_s, --interval) or link exposures whose metadata carry the clock")
        df["t"] = df["frame"].astype(float) * float(interval_s)
    df = df.sort_values(["frame", "index"], kind="stable").reset_index(drop=True)
    return df


def _plenodust_particles(df: pd.DataFrame, params: LinkParams) -> np.ndarray:
    linker = Linker(params)
    out = np.full(len(df), -1, np.int64)
    for frame, rows in df.groupby("frame", sort=True).indices.items():
        part = df.iloc[rows]
        t = float(part["t"].iloc[0])
        step = linker.add(int(frame), t, {c: part[c].to_numpy() for c in part.columns})
        out[rows] = step.particle
    return out


def _trackpy_particles(df: pd.DataFrame, params: LinkParams) -> np.ndarray:
    """trackpy.link on X, Y and Z scaled by the measured lateral-to-depth step ratio."""
    import trackpy

    # Step spreads measured by our linker on the first frames set the scale and search range.
    first = df[df["frame"] <= df["frame"].min() + 3]
    linker = Linker(params)
    for frame, rows in first.groupby("frame", sort=True).indices.items():
        part = first.iloc[rows]
        linker.add(int(frame), float(part["t"].iloc[0]), {c: part[c].to_numpy() for c in part.columns})
    step = linker.step_mm if linker.step_mm is not None else np.ones(3)
    lateral = float(np.mean(step[:2]))
    work = df[["frame", "X", "Y", "Z"]].copy()
    work["Zs"] = work["Z"] * (lateral / float(step[2]))
    ok = np.all(np.isfinite(work[["X", "Y", "Z"]].to_numpy()), axis=1)
    work = work[ok]
    search = min(params.gate_sigma * lateral, params.max_step_nn * (linker.nn_mm or np.inf))
    trackpy.quiet()
    predictor = trackpy.predict.NearestVelocityPredict()
    linked = predictor.link_df(work, search, pos_columns=["X", "Y", "Zs"], memory=params.memory,
                               adaptive_stop=0.1 * search, adaptive_step=0.9)
    out = np.full(len(df), -1, np.int64)
    out[np.flatnonzero(ok)] = linked.loc[work.index, "particle"].to_numpy()
    return out


def add_velocities(df: pd.DataFrame, *, open_blur_pitches: float = 1.0) -> pd.DataFrame:
    """``vX, vY, vZ`` (mm/s) from each trajectory's neighbours in time (see the module docstring);
    the columns in :data:`LEADING_COLUMNS` order."""
    df = df.copy()
    open_depth = np.zeros(len(df), bool)
    for _, rows in df.groupby("frame").indices.items():
        part = df.iloc[rows]
        open_depth[rows] = depth_errors({c: part[c].to_numpy() for c in part.columns},
                                        open_blur_pitches=open_blur_pitches).open
    velocity = velocities(df["particle"].to_numpy(), df["t"].to_numpy(float),
                          df[list(POSITION_COLUMNS)].to_numpy(float), open_depth)
    for k, name in enumerate(VELOCITY_COLUMNS):
        df[name] = velocity[:, k]
    return order_columns(df)


def velocities(particle: np.ndarray, t: np.ndarray, xyz: np.ndarray, open_depth: np.ndarray | None = None, *,
               with_dt: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Velocity of each row from its trajectory's neighbours in time.

    Parameters
    ----------
    particle : ndarray of int, shape (n,)
        Trajectory ids (-1: not linked, no velocity).
    t : ndarray of shape (n,)
    xyz : ndarray of shape (n, 3)
    open_depth : ndarray of bool, shape (n,), optional
        Rows whose depth is open: a ``vZ`` that would use one is NaN.

    with_dt : bool
        Also return the time apart (s) of the two positions each velocity is taken from (0: none).

    Returns
    -------
    ndarray of shape (n, 3), and ndarray of shape (n,) with ``with_dt``
    """
    n = len(particle)
    out = np.full((n, 3), np.nan)
    out_dt = np.zeros(n)
    if n == 0:
        return (out, out_dt) if with_dt else out
    open_depth = np.zeros(n, bool) if open_depth is None else np.asarray(open_depth, bool)
    order = np.lexsort((t, particle))
    p, tt, r, op = particle[order], t[order], xyz[order], open_depth[order]
    same_prev = np.r_[False, p[1:] == p[:-1]] & (p >= 0)
    same_next = np.r_[p[1:] == p[:-1], False] & (p >= 0)
    prev = np.where(same_prev, np.arange(n) - 1, np.arange(n))
    nxt = np.where(same_next, np.arange(n) + 1, np.arange(n))
    dt = tt[nxt] - tt[prev]
    ok = dt > 0
    v = np.full((n, 3), np.nan)
    v[ok] = (r[nxt[ok]] - r[prev[ok]]) / dt[ok, None]
    v[op[prev] | op[nxt], 2] = np.nan
    out[order] = v
    out_dt[order] = dt
    return (out, out_dt) if with_dt else out


def two_sided(particle: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rows whose trajectory is seen both before and after them (their velocity is central).

    >>> two_sided(np.array([0, 0, 0, 1]), np.array([0.0, 1.0, 2.0, 1.0])).tolist()
    [False, True, False, False]
    """
    particle, t = np.asarray(particle), np.asarray(t, float)
    order = np.lexsort((t, particle))
    p = particle[order]
    same = p[1:] == p[:-1]
    out = np.zeros(len(p), bool)
    out[order] = np.r_[False, same] & np.r_[same, False] & (p >= 0)
    return out


def order_columns(df: pd.DataFrame) -> pd.DataFrame:
    lead = [c for c in LEADING_COLUMNS if c in df.columns]
    return df[lead + [c for c in df.columns if c not in lead]]


def trajectory_lengths(df: pd.DataFrame) -> Any:
    """Shots per trajectory (a pandas Series by ``particle``)."""
    return df[df["particle"] >= 0].groupby("particle").size()
