"""Per shot, the structure of a linked run: count, drift and rotation, RMS velocity and kinetic
temperature (position noise taken out), pair correlation g(r) and a ball's shells.

:func:`summarize` measures the run's position noise once (:func:`analysis.tracking.temperature.
position_noise`) and then describes each shot (:func:`analysis.tracking.temperature.
shot_temperature`, :mod:`analysis.tracking.structure`). Its table has one row per frame:

``frame, t, count`` (particles found), ``with_velocity`` (those with all three velocity
components), ``vX, vY, vZ`` (the cluster's drift, mm/s), ``omegaX, omegaY, omegaZ`` (its rotation,
rad/s), ``v_rms_X ... v_rms_Z`` and ``v_rms_err_X ...`` (mm/s, about the rigid motion, noise
taken out), ``T_X_eV, T_Y_eV, T_Z_eV`` and their ``T_err_*``, ``T_eV`` (mean over the three axes),
``T_xy_eV`` (lateral only: the better measured), with ``T_err_eV`` and ``T_xy_err_eV``;
``shells`` (number of shells, 0 for no ball) and per shell ``i`` (innermost 0):
``shell{i}_r_mm, shell{i}_r_err_mm, shell{i}_n, shell{i}_n_err``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from .structure import PairCorrelation, pair_correlation, shells
from .temperature import AXES, NoiseEstimate, position_noise, shot_temperature
from .trajectories import two_sided, velocities
from .units import particle_mass_kg

if TYPE_CHECKING:
    import pandas as pd


@dataclass
class RunSummary:
    """What :func:`summarize` found: the per-frame table (columns as in the module docstring), the
    run's position noise and each frame's g(r)."""

    table: dict[str, np.ndarray]
    noise: NoiseEstimate
    pair_correlation: dict[int, PairCorrelation] = field(default_factory=dict)
    mass_kg: float = field(default_factory=particle_mass_kg)

    def to_dataframe(self) -> pd.DataFrame:
        import pandas as pd

        return pd.DataFrame(self.table)

    def temperature_ev(self) -> tuple[float, float]:
        """The run's mean kinetic temperature (eV) over the shots that have one, and its
        standard error."""
        t = np.asarray(self.table.get("T_eV", []), float)
        t = t[np.isfinite(t)]
        if t.size == 0:
            return math.nan, math.nan
        return float(t.mean()), float(t.std(ddof=1) / math.sqrt(t.size)) if t.size > 1 else math.nan


def summarize(linked: pd.DataFrame, *, mass_kg: float | None = None, lags: int = 7, g_bins: int = 40,
              frames: list[int] | None = None, noise: NoiseEstimate | None = None,
              two_sided_only: bool = False) -> RunSummary:
    """Describe each shot of a linked run (see the module docstring).

    Parameters
    ----------
    linked : pandas.DataFrame
        A linked table (:func:`analysis.tracking.trajectories.link`): ``frame, t, particle, X, Y, Z``
        and ``vX, vY, vZ``.
    mass_kg : float, optional
        Particle mass; default the paper's MF particles (9.16 um, 1510 kg/m^3).
    lags : int
        Largest lag (frames) of the noise fit.
    g_bins : int
        Bins of g(r).
    frames : list of int, optional
        Only these frames (the noise is still measured over the whole table).
    noise : NoiseEstimate, optional
        Use this position noise instead of measuring it.
    two_sided_only : bool
        Temperatures from central velocities only (the trajectory seen before and after): the
        newest shot of a run still being taken then has none, rather than a noisier one-sided
        value (four times the noise to take out) that can come out negative.

    Returns
    -------
    RunSummary
    """
    mass = particle_mass_kg() if mass_kg is None else float(mass_kg)
    particle = linked["particle"].to_numpy()
    frame = linked["frame"].to_numpy()
    t = linked["t"].to_numpy(float)
    xyz = linked[["X", "Y", "Z"]].to_numpy(float)
    if noise is None:
        noise = position_noise(particle, frame, t, xyz, lags=lags)
    velocity = linked[["vX", "vY", "vZ"]].to_numpy(float)
    if two_sided_only:
        velocity = np.where(two_sided(particle, t)[:, None], velocity, np.nan)
    _, dt = velocities(particle, t, xyz, with_dt=True)
    groups = linked.groupby("frame").indices
    wanted = sorted(groups) if frames is None else [f for f in frames if f in groups]
    rows: list[dict[str, Any]] = []
    correlations: dict[int, PairCorrelation] = {}
    for f in wanted:
        idx = groups[f]
        row: dict[str, Any] = {"frame": int(f), "t": float(t[idx[0]]), "count": int(len(idx))}
        temp = shot_temperature(xyz[idx], velocity[idx], dt[idx], noise, mass_kg=mass)
        row["with_velocity"] = temp.count
        for k, axis in enumerate(AXES):
            row[f"v{axis}"] = temp.drift_mm_s[k]
            row[f"omega{axis}"] = temp.omega_rad_s[k]
            row[f"v_rms_{axis}"] = temp.rms_mm_s[k]
            row[f"v_rms_err_{axis}"] = temp.rms_err_mm_s[k]
            row[f"T_{axis}_eV"] = temp.temperature_ev[k]
            row[f"T_err_{axis}_eV"] = temp.temperature_err_ev[k]
        row["T_eV"] = float(np.mean(temp.temperature_ev))
        row["T_err_eV"] = float(np.sqrt(np.sum(temp.temperature_err_ev ** 2)) / 3)
        row["T_xy_eV"] = float(np.mean(temp.temperature_ev[:2]))
        row["T_xy_err_eV"] = float(np.sqrt(np.sum(temp.temperature_err_ev[:2] ** 2)) / 2)
        correlations[int(f)] = pair_correlation(xyz[idx], bins=g_bins)
        found = shells(xyz[idx], noise_mm=noise.sigma_mm)
        row["shells"] = 0 if found is None else int(found.count.size)
        if found is not None:
            for s in range(found.count.size):
                row[f"shell{s}_r_mm"] = float(found.radius_mm[s])
                row[f"shell{s}_r_err_mm"] = float(found.radius_err_mm[s])
                row[f"shell{s}_n"] = int(found.count[s])
                row[f"shell{s}_n_err"] = float(found.count_err[s])
        rows.append(row)
    return RunSummary(_columns(rows), noise, correlations, mass)


def _columns(rows: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    """Rows as columns; a shell column a frame lacks is NaN there."""
    names = list(dict.fromkeys(name for row in rows for name in row))
    suffixes = ["r_mm", "r_err_mm", "n", "n_err"]
    shell_names = sorted((n for n in names if n.startswith("shell") and n != "shells"),
                         key=lambda n: (int(n[5:].split("_")[0]), suffixes.index(n.split("_", 1)[1])))
    names = [n for n in names if n not in shell_names] + shell_names
    out = {}
    for name in names:
        values = [row.get(name, math.nan) for row in rows]
        integer = name in ("frame", "count", "with_velocity", "shells")
        out[name] = np.array(values, dtype=np.int64 if integer else float)
    return out
