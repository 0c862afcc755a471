"""A cluster that moves between shots: rotation, drift, Langevin motion and shell hops.

``plenodust simulate --count N`` (N > 1) moves the scenario's particles with this model and renders
one shot every ``interval_s`` (the metadata clock says when). Each particle sits in a cage: a
harmonic well of angular frequency ``cage_per_s`` around its site, ``stiff_ratio`` times stiffer
(in frequency) across the cluster's layers: radially in a ball or a cloud (the shells stay sharp
while particles wander along them), along the normal of a flat layer. The sites form the scenario's
cluster, which turns rigidly at ``rotation_deg_per_s`` about ``rotation_axis`` through its centre
while the centre drifts at ``drift_mm_per_s``. The particles feel that cage, a soft repulsion
from any neighbour closer than half the mean nearest-neighbour distance, and the neutral gas:
friction ``damping_per_s`` relative to a gas that moves with the cluster (it is what turns and
carries it) and the matching random kicks, a Langevin thermostat at ``temperature_ev``. In a ball,
a particle now and then hops to the next shell: its site moves radially to the other shell's
radius over ``hop_duration_s``.

In equilibrium each velocity component is Maxwellian with variance ``k_B T / m`` about the gas's
local velocity whatever the forces, so the truth's temperature is ``temperature_ev`` exactly. The
integrator is BAOAB (Leimkuhler & Matthews 2013) with the friction step solved exactly.

The first shot is the scenario itself: the sites are placed a thermal displacement away from the
scenario's positions, so the cluster starts in equilibrium (and a shell is as wide as that
displacement, about 0.16 mm at the defaults, a quarter of the ball's mean NN distance).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from analysis.errors import ParameterError
from analysis.tracking.units import MF_DENSITY_KG_M3, MF_DIAMETER_UM, particle_mass_kg, thermal_speed_mm_s

from .scenarios import Particles, Scenario


@dataclass(frozen=True)
class Motion:
    """How a simulated cluster moves between shots (see the module docstring).

    Defaults: MF particles at 0.004 eV (about 46 K) in weak damping, caged loosely enough that
    they move almost ballistically over one shot interval (cage x interval = 0.2), the cluster
    turning at 2.5 degrees a second about the image's vertical and drifting at 32 um/s, one shot
    a second: in the 150-particle ball a particle moves about 0.15 of the mean nearest-neighbour
    distance per shot (median), a few of them 0.3.
    """

    interval_s: float = 1.0
    temperature_ev: float = 0.004
    damping_per_s: float = 0.02
    cage_per_s: float = 0.2
    rotation_deg_per_s: float = 2.5
    rotation_axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    drift_mm_per_s: tuple[float, float, float] = (0.03, 0.0, 0.01)
    hop_rate_per_s: float = 0.03
    hop_duration_s: float = 6.0
    stiff_ratio: float = 3.0
    particle_diameter_um: float = MF_DIAMETER_UM
    particle_density_kg_m3: float = MF_DENSITY_KG_M3
    substeps: int = 20

    def __post_init__(self) -> None:
        if not (self.interval_s > 0 and self.substeps >= 1 and self.hop_duration_s > 0):
            raise ParameterError("interval_s and hop_duration_s must be positive and substeps at least 1")
        if min(self.temperature_ev, self.damping_per_s, self.cage_per_s, self.hop_rate_per_s) < 0:
            raise ParameterError("temperature, damping, cage frequency and hop rate must not be negative")
        if len(self.rotation_axis) != 3 or not np.any(self.rotation_axis) or len(self.drift_mm_per_s) != 3:
            raise ParameterError("rotation_axis must be a non-zero 3-vector and drift_mm_per_s a 3-vector")

    @property
    def mass_kg(self) -> float:
        return particle_mass_kg(self.particle_diameter_um, self.particle_density_kg_m3)

    @property
    def thermal_speed_mm_s(self) -> float:
        """Standard deviation of one velocity component, mm/s."""
        return thermal_speed_mm_s(self.temperature_ev, self.mass_kg)

    def slowed(self, factor: float) -> Motion:
        """The same motion played ``factor`` times slower: one shot every ``factor * interval_s``
        with the same displacements per shot (rates divided by ``factor``, the temperature by
        ``factor ** 2``, hops lasting ``factor`` times longer), so a camera shooting less often
        still sees steps it can link, and every velocity stays consistent with the clock.

        >>> m = Motion().slowed(4.0)
        >>> (m.interval_s, round(m.temperature_ev, 6), m.rotation_deg_per_s)
        (4.0, 0.00025, 0.625)
        """
        if not factor > 0:
            raise ParameterError(f"factor={factor} must be positive")
        f = float(factor)
        return replace(self, interval_s=self.interval_s * f, temperature_ev=self.temperature_ev / f ** 2,
                       damping_per_s=self.damping_per_s / f, cage_per_s=self.cage_per_s / f,
                       rotation_deg_per_s=self.rotation_deg_per_s / f,
                       drift_mm_per_s=tuple(v / f for v in self.drift_mm_per_s),
                       hop_rate_per_s=self.hop_rate_per_s / f, hop_duration_s=self.hop_duration_s * f)

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["rotation_axis"] = list(self.rotation_axis)
        out["drift_mm_per_s"] = list(self.drift_mm_per_s)
        out["mass_kg"] = self.mass_kg
        return out


@dataclass
class Snapshot:
    """The cluster at one shot: time (s since the first shot), positions and velocities (mm, mm/s,
    camera frame) of every particle of the scenario, and each one's shell (-1 outside a ball)."""

    t_s: float
    xyz_mm: np.ndarray
    velocity_mm_s: np.ndarray
    shell: np.ndarray


class MovingCluster:
    """A scenario's particles moving under :class:`Motion`; :meth:`advance` goes one shot on.

    Parameters
    ----------
    scenario : Scenario
        Its particles are the first shot.
    motion : Motion
    seed : int or sequence of int
        Seeds the thermal kicks, the sites' thermal offsets and the hops.
    """

    def __init__(self, scenario: Scenario, motion: Motion, *, seed: Any) -> None:
        self.scenario = scenario
        self.motion = motion
        self.rng = np.random.default_rng(seed)
        p = scenario.particles
        xyz = np.stack([p.x_mm, p.y_mm, p.z_mm], axis=1).astype(np.float64)
        n = len(xyz)
        self.centre0 = xyz.mean(axis=0) if n else np.zeros(3)
        self.t = 0.0
        self.kt_m = motion.thermal_speed_mm_s ** 2  # k_B T / m in mm^2/s^2
        self.stiff_dir = _stiff_directions(xyz - self.centre0)  # in the cluster's frame
        spread = math.sqrt(self.kt_m) / motion.cage_per_s if motion.cage_per_s > 0 else 0.0
        # The first shot is the scenario itself; each site lies a thermal displacement from it
        # (smaller across the layers), so the cluster starts in equilibrium.
        offset = self.rng.normal(0.0, spread, size=(n, 3))
        along = np.sum(offset * self.stiff_dir, axis=1, keepdims=True) * self.stiff_dir
        self.sites = xyz - self.centre0 - (offset - along) - along / motion.stiff_ratio
        self.xyz = xyz
        self.velocity = self._gas_velocity(xyz, 0.0) + self.rng.normal(0.0, math.sqrt(self.kt_m), size=(n, 3))
        if n > 1:
            d, _ = cKDTree(xyz).query(xyz, k=2)
            self.repulsion_mm = 0.5 * float(d[:, 1].mean())
        else:
            self.repulsion_mm = 0.0
        shells = scenario.parameters.get("shells") if scenario.name == "ball" else None
        self.shell_radii = np.array(sorted(r for r, _ in shells)) if shells else np.empty(0)
        self.hops: list[dict[str, Any]] = []
        self._hopping: dict[int, tuple[float, np.ndarray, np.ndarray]] = {}

    # -- the cluster's frame ----------------------------------------------------------------

    def _rotation(self, t: float) -> np.ndarray:
        axis = np.asarray(self.motion.rotation_axis, float)
        axis = axis / np.linalg.norm(axis)
        angle = math.radians(self.motion.rotation_deg_per_s) * t
        k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)

    def _centre(self, t: float) -> np.ndarray:
        return self.centre0 + np.asarray(self.motion.drift_mm_per_s, float) * t

    def _omega(self) -> np.ndarray:
        axis = np.asarray(self.motion.rotation_axis, float)
        return axis / np.linalg.norm(axis) * math.radians(self.motion.rotation_deg_per_s)

    def _gas_velocity(self, xyz: np.ndarray, t: float) -> np.ndarray:
        """The gas moves (and carries the cluster) as a rigid body: drift plus rotation."""
        return np.asarray(self.motion.drift_mm_per_s, float) + np.cross(self._omega(), xyz - self._centre(t))

    def _sites_at(self, t: float) -> np.ndarray:
        sites = self.sites.copy()
        for i, (start, origin, target) in self._hopping.items():
            f = min(1.0, max(0.0, (t - start) / self.motion.hop_duration_s))
            sites[i] = origin + (target - origin) * 0.5 * (1 - math.cos(math.pi * f))
        return self._centre(t) + sites @ self._rotation(t).T

    def _acceleration(self, xyz: np.ndarray, t: float) -> np.ndarray:
        offset = xyz - self._sites_at(t)
        stiff = self.stiff_dir @ self._rotation(t).T
        across = np.sum(offset * stiff, axis=1, keepdims=True) * stiff
        a = -(self.motion.cage_per_s ** 2) * (offset + (self.motion.stiff_ratio ** 2 - 1) * across)
        if self.repulsion_mm > 0 and len(xyz) > 1:
            pairs = cKDTree(xyz).query_pairs(self.repulsion_mm, output_type="ndarray")
            if len(pairs):
                d = xyz[pairs[:, 0]] - xyz[pairs[:, 1]]
                r = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
                # A stiff spring (4x the cage's stiffness) pushes close pairs apart.
                push = (4 * self.motion.cage_per_s ** 2) * ((self.repulsion_mm - r) / r)[:, None] * d
                np.add.at(a, pairs[:, 0], push)
                np.add.at(a, pairs[:, 1], -push)
        return a

    # -- stepping -----------------------------------------------------------------------------

    def snapshot(self) -> Snapshot:
        return Snapshot(self.t, self.xyz.copy(), self.velocity.copy(), self.shells())

    def shells(self) -> np.ndarray:
        """Each particle's shell (0 innermost) by its site's radius; -1 for a cluster without shells."""
        if not self.shell_radii.size:
            return np.full(len(self.xyz), -1, dtype=np.int64)
        radius = np.linalg.norm(self.xyz - self._centre(self.t), axis=1)
        return np.argmin(np.abs(radius[:, None] - self.shell_radii[None]), axis=1).astype(np.int64)

    def advance(self) -> Snapshot:
        """Move on by one shot interval; returns the new snapshot."""
        m = self.motion
        self._start_hops()
        h = m.interval_s / m.substeps
        fade = math.exp(-m.damping_per_s * h)
        kick = math.sqrt(self.kt_m * (1 - fade * fade))
        x, v, t = self.xyz, self.velocity, self.t
        a = self._acceleration(x, t)
        hop_velocity = self._hop_velocity(t)
        for _ in range(m.substeps):
            # A hopping particle's velocity takes its site's along the hop: it crosses the shell gap
            # with its site instead of ringing in its cage.
            carried = self._hop_velocity(t + 0.5 * h)
            v = v + carried - hop_velocity
            hop_velocity = carried
            v = v + 0.5 * h * a
            x = x + 0.5 * h * v
            gas = self._gas_velocity(x, t + 0.5 * h)
            v = gas + (v - gas) * fade + kick * self.rng.standard_normal(x.shape)
            x = x + 0.5 * h * v
            t = t + h
            a = self._acceleration(x, t)
            v = v + 0.5 * h * a
        self.xyz, self.velocity, self.t = x, v, t
        self._finish_hops()
        return self.snapshot()

    def _hop_velocity(self, t: float) -> np.ndarray:
        """Velocity (mm/s, camera frame) of each hopping particle's site along its hop."""
        out = np.zeros((len(self.sites), 3))
        rotation = self._rotation(t)
        for i, (start, origin, target) in self._hopping.items():
            f = (t - start) / self.motion.hop_duration_s
            if 0.0 <= f <= 1.0:
                rate = 0.5 * math.pi * math.sin(math.pi * f) / self.motion.hop_duration_s
                out[i] = rotation @ ((target - origin) * rate)
        return out

    def _start_hops(self) -> None:
        m = self.motion
        if self.shell_radii.size < 2 or m.hop_rate_per_s <= 0:
            return
        for _ in range(self.rng.poisson(m.hop_rate_per_s * m.interval_s)):
            free = [i for i in range(len(self.sites)) if i not in self._hopping]
            if not free:
                return
            i = int(self.rng.choice(free))
            radius = float(np.linalg.norm(self.sites[i]))
            shell = int(np.argmin(np.abs(self.shell_radii - radius)))
            options = [s for s in (shell - 1, shell + 1) if 0 <= s < self.shell_radii.size]
            to = int(self.rng.choice(options))
            target = self.sites[i] * (self.shell_radii[to] / max(radius, 1e-9))
            self._hopping[i] = (self.t, self.sites[i].copy(), target)
            self.hops.append({"particle": i, "start_s": round(self.t, 6), "from_shell": shell, "to_shell": to,
                              "duration_s": m.hop_duration_s})

    def _finish_hops(self) -> None:
        for i, (start, _, target) in list(self._hopping.items()):
            if self.t - start >= self.motion.hop_duration_s:
                self.sites[i] = target
                del self._hopping[i]


def _stiff_directions(rel: np.ndarray) -> np.ndarray:
    """Per site, the unit direction across the cluster's layers: the normal of a flat cluster,
    else radial from its centre."""
    n = len(rel)
    if n < 3:
        return np.tile([0.0, 0.0, 1.0], (n, 1))
    _, s, vt = np.linalg.svd(rel - rel.mean(axis=0), full_matrices=False)
    if s[-1] < 0.25 * s[0]:
        return np.tile(vt[-1], (n, 1))
    norm = np.linalg.norm(rel, axis=1, keepdims=True)
    return np.where(norm > 1e-9, rel / np.maximum(norm, 1e-9), np.array([0.0, 0.0, 1.0]))


def moved_scenario(scenario: Scenario, snapshot: Snapshot) -> Scenario:
    """The scenario with its particles where the snapshot has them (brightness unchanged)."""
    p = scenario.particles
    xyz = snapshot.xyz_mm
    moved = Particles(xyz[:, 0].copy(), xyz[:, 1].copy(), xyz[:, 2].copy(), p.brightness_dn.copy())
    return Scenario(scenario.name, scenario.seed, moved, scenario.background_dn, scenario.parameters)


def simulate_motion(scenario: Scenario, motion: Motion, count: int, *, seed: Any) -> tuple[list[Snapshot], list[dict]]:
    """``count`` snapshots of the moving cluster, the first being the scenario; and the hops.

    Examples
    --------
    >>> from analysis.simulation.scenarios import make_scenario
    >>> shots, hops = simulate_motion(make_scenario("ball", 1), Motion(), 3, seed=1)
    >>> [round(s.t_s, 3) for s in shots]
    [0.0, 1.0, 2.0]
    """
    cluster = MovingCluster(scenario, motion, seed=seed)
    shots = [cluster.snapshot()]
    for _ in range(count - 1):
        shots.append(cluster.advance())
    return shots, cluster.hops
