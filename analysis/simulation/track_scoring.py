"""Linked trajectories scored against a simulated run's truth (``plenodust simulate --count N``).

Each shot's found particles are paired with the true ones (:func:`analysis.simulation.scoring.match`,
3D, within half the mean NN distance); then

- a **link** is two consecutive observations of one found trajectory; it is right when both are
  paired with the same true particle (``links_right``: the fraction of links whose two ends are
  both paired that are right);
- a **missed shot** is a true particle paired in frames ``k - 1`` and ``k + 1`` but not in ``k``; it is
  bridged when the found ids on both sides are the same (``gaps_bridged``). Of those not bridged,
  ``gaps_misplaced`` are ones where the trajectory of ``k - 1`` goes on in frame ``k`` with a row the
  scorer paired with no true particle (the particle was found, but more than ``max_distance`` off),
  and ``gaps_taken_by_spurious`` ones where the trajectory that has the particle after the gap
  followed, before it, rows paired with no true particle (a spurious detection near the particle,
  which it takes over): a detection's failing, not the linker's memory;
- **fragments**: found trajectories per true particle (1 is perfect);
- velocities: RMS of found minus true per axis (``velocity_rms_error_mm_s``; over the rows whose
  velocity comes from right links only, ``velocity_rms_error_right_links_mm_s``);
- the run's truth temperature: the true velocities' variance about the cluster's rigid motion,
  per shot, times ``m / e`` (:func:`truth_temperature_ev`; per axis :func:`truth_temperature_axes_ev`).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from analysis.tracking.temperature import shot_temperature, NoiseEstimate
from analysis.tracking.units import particle_mass_kg

from .scoring import match

if TYPE_CHECKING:
    import pandas as pd


def read_truth_run(folder: str | Path) -> pd.DataFrame:
    """A simulated run's truth as one table: ``frame, t, particle, X, Y, Z`` and, for a moving
    cluster, ``vX, vY, vZ, shell`` (from ``IMG_nnnn.truth.csv`` and ``scenario.json``)."""
    import pandas as pd

    folder = Path(folder)
    doc = json.loads((folder / "scenario.json").read_text())
    parts = []
    for frame, exposure in enumerate(doc["exposures"]):
        with open(folder / f"{exposure['name']}.truth.csv", newline="") as fh:
            rows = list(csv.DictReader(fh))
        df = pd.DataFrame(rows).apply(pd.to_numeric)
        df.insert(0, "t", float(exposure.get("t_s", frame)))
        df.insert(0, "frame", frame)
        parts.append(df)
    return pd.concat(parts, ignore_index=True)


def truth_temperature_ev(truth: pd.DataFrame, *, mass_kg: float | None = None) -> float:
    """Mean over shots of the true velocities' kinetic temperature about the rigid motion (eV)."""
    return float(np.mean(truth_temperature_axes_ev(truth, mass_kg=mass_kg)))


def truth_temperature_axes_ev(truth: pd.DataFrame, *, mass_kg: float | None = None) -> np.ndarray:
    """The same per axis (X, Y, Z), shape (3,): a run's axes differ by several % (seed 1 of the
    bench: 0.96, 1.05, 0.99 of their mean), so a measured axis is judged against its own truth."""
    mass = particle_mass_kg() if mass_kg is None else mass_kg
    noise = NoiseEstimate(np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
    values = []
    for _, shot in truth.groupby("frame"):
        xyz = shot[["X", "Y", "Z"]].to_numpy(float)
        v = shot[["vX", "vY", "vZ"]].to_numpy(float)
        values.append(shot_temperature(xyz, v, np.ones(len(v)), noise, mass_kg=mass).temperature_ev)
    return np.nanmean(np.array(values, float), axis=0)


def score_tracks(linked: pd.DataFrame, truth: pd.DataFrame, *, max_distance: float = 0.5) -> dict[str, Any]:
    """Score a linked table against the truth (see the module docstring).

    Parameters
    ----------
    linked : pandas.DataFrame
        ``frame, particle, X, Y, Z`` and ``vX, vY, vZ``.
    truth : pandas.DataFrame
        From :func:`read_truth_run`.
    max_distance : float
        Largest found-to-true distance of a pairing, in mean NN distances.

    Returns
    -------
    dict
    """
    truth_id = np.full(len(linked), -1, np.int64)
    true_v = np.full((len(linked), 3), np.nan)
    found_groups = linked.groupby("frame").indices
    truth_groups = truth.groupby("frame").indices
    paired_per_frame: dict[int, dict[int, int]] = {}
    for frame, rows in found_groups.items():
        if frame not in truth_groups:
            continue
        t_rows = truth_groups[frame]
        f = {c: linked[c].to_numpy(float)[rows] for c in ("X", "Y", "Z")}
        tt = {c: truth[c].to_numpy(float)[t_rows] for c in ("X", "Y", "Z")}
        r, c = match(f, tt, max_distance=max_distance)
        ids = truth["particle"].to_numpy()[t_rows][c]
        truth_id[rows[r]] = ids
        if "vX" in truth.columns:
            true_v[rows[r]] = truth[["vX", "vY", "vZ"]].to_numpy(float)[t_rows][c]
        paired_per_frame[int(frame)] = dict(zip(ids.tolist(), linked["particle"].to_numpy()[rows[r]].tolist()))
    particle = linked["particle"].to_numpy()
    frame = linked["frame"].to_numpy()
    order = np.lexsort((frame, particle))
    p, tid = particle[order], truth_id[order]
    link = (p[1:] == p[:-1]) & (p[1:] >= 0)
    judged = link & (tid[1:] >= 0) & (tid[:-1] >= 0)
    right = judged & (tid[1:] == tid[:-1])
    frames = sorted(paired_per_frame)
    gaps = bridged = misplaced = spurious = 0
    unpaired_ids = {int(f): set(linked["particle"].to_numpy()[rows][truth_id[rows] < 0].tolist())
                    for f, rows in found_groups.items()}
    for k in frames[1:-1]:
        before, now, after = paired_per_frame.get(k - 1, {}), paired_per_frame[k], paired_per_frame.get(k + 1, {})
        for true in set(before) & set(after) - set(now):
            gaps += 1
            if before[true] == after[true]:
                bridged += 1
            elif before[true] in unpaired_ids.get(k, set()):
                misplaced += 1
            elif any(after[true] in unpaired_ids.get(j, set()) for j in frames if j <= k):
                spurious += 1
    fragments = []
    for true in np.unique(truth_id[truth_id >= 0]):
        fragments.append(np.unique(particle[(truth_id == true) & (particle >= 0)]).size)
    found_v = linked[["vX", "vY", "vZ"]].to_numpy(float)
    err = found_v - true_v
    # Rows whose velocity comes from right links only (their trajectory's rows before and after
    # are the same true particle): a wrong link's step is a linking error, scored above, and a
    # few of them would dominate the velocities' RMS.
    same_before = np.r_[True, ~link | (tid[1:] == tid[:-1])]
    same_after = np.r_[~link | (tid[1:] == tid[:-1]), True]
    clean = np.zeros(len(linked), dtype=bool)
    clean[order] = same_before & same_after & (tid >= 0)
    possible = 0
    for k in frames[:-1]:
        possible += len(set(paired_per_frame[k]) & set(paired_per_frame.get(k + 1, {})))
    return {
        "links": int(link.sum()), "links_judged": int(judged.sum()),
        "links_right": float(right.sum() / judged.sum()) if judged.sum() else math.nan,
        "links_wrong": int(judged.sum() - right.sum()),
        "consecutive_truth_links": int(possible),
        "gaps": gaps, "gaps_bridged": bridged, "gaps_misplaced": misplaced,
        "gaps_taken_by_spurious": spurious,
        "fragments_per_particle": float(np.mean(fragments)) if fragments else math.nan,
        "detections_paired": float(np.mean(truth_id >= 0)) if len(truth_id) else math.nan,
        "velocity_rms_error_mm_s": [_rms(err[:, a]) for a in range(3)],
        "velocity_rms_error_right_links_mm_s": [_rms(err[clean, a]) for a in range(3)],
        "true_speed_rms_mm_s": [_rms(true_v[:, a]) for a in range(3)],
    }


def _rms(values: np.ndarray) -> float:
    """RMS of the finite values (NaN where there are none)."""
    finite = values[np.isfinite(values)]
    return float(np.sqrt(np.mean(finite ** 2))) if finite.size else math.nan

