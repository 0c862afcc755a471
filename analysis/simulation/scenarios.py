"""Particle clusters with known 3D truth for the simulator.

Coordinates are millimetres in the camera frame of camera-model.md: origin at the main lens,
``Z`` along the optical axis toward the scene, ``X`` right and ``Y`` down in the upright image.
Clusters are centred on the simulated camera's focus distance, so their ``alpha`` lies inside the
default refocus range 0.987 ... 1.013 (see :mod:`analysis.simulation.camera` for the optics).

Scenarios
---------
``tilted-layer``
    The paper's test: one layer of about 60 particles on a jittered hexagonal lattice, 14 mm
    across, its normal tilted 13 degrees from the optical axis (about ``X``).
``shadowing``
    The same layer plus partners on (nearly) the same line of sight as some layer particles,
    1 to 2.5 mm nearer or farther, so their images overlap and ``B(alpha)`` shows two peaks.
``ball``
    A 3D "Yukawa ball" of 150 particles on three nested shells, 4 mm across.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from analysis.errors import ParameterError
from .camera import DEFAULT_LENS

SCENARIO_NAMES = ("tilted-layer", "shadowing", "ball")


@dataclass(frozen=True)
class Particles:
    """Point particles: positions in mm (camera frame) and brightness.

    ``brightness_dn`` is the raw value above black that a fully lit green pixel of an
    on-axis micro-image receives from the particle (its light spread over the aperture).
    """

    x_mm: np.ndarray
    y_mm: np.ndarray
    z_mm: np.ndarray
    brightness_dn: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.x_mm)
        if not (len(self.y_mm) == len(self.z_mm) == len(self.brightness_dn) == n):
            raise ParameterError("particle arrays x_mm, y_mm, z_mm, brightness_dn must have equal lengths")
        if n and np.min(self.z_mm) <= 0:
            raise ParameterError("particles must lie in front of the camera (z_mm > 0)")

    def __len__(self) -> int:
        return len(self.x_mm)

    def subset(self, keep: np.ndarray) -> "Particles":
        return Particles(self.x_mm[keep], self.y_mm[keep], self.z_mm[keep], self.brightness_dn[keep])


@dataclass(frozen=True)
class Scenario:
    """A named cluster with its truth and the scene's background (plasma glow)."""

    name: str
    seed: int
    particles: Particles
    background_dn: float
    parameters: dict[str, Any] = field(default_factory=dict)

    def jittered(self, rng: np.random.Generator, *, sigma_mm: float = 0.02) -> "Scenario":
        """The same cluster a moment later: each particle moved by a Gaussian step (thermal motion)."""
        p = self.particles
        n = len(p)
        step = rng.normal(0.0, sigma_mm, size=(3, n))
        moved = Particles(p.x_mm + step[0], p.y_mm + step[1], p.z_mm + step[2], p.brightness_dn.copy())
        return replace(self, particles=moved)


def make_scenario(name: str, seed: int, *, centre_z_mm: float | None = None, brightness_dn: float = 1800.0,
                  background_dn: float = 40.0) -> Scenario:
    """Build a scenario's particles, deterministically from ``seed``.

    Parameters
    ----------
    name : {"tilted-layer", "shadowing", "ball"}
    seed : int
    centre_z_mm : float, optional
        Depth of the cluster centre; by default the simulated lens's focus distance plus a
        seed-dependent offset of up to 0.3 mm.
    brightness_dn : float
        Median particle brightness (raw DN above black of a fully lit green pixel).
    background_dn : float
        Plasma glow: a uniform diffuse background, in the same units.

    Returns
    -------
    Scenario

    Examples
    --------
    >>> len(make_scenario("ball", 1).particles)
    150
    """
    if name not in SCENARIO_NAMES:
        raise ParameterError(f"unknown scenario {name!r}; choose one of {', '.join(SCENARIO_NAMES)}")
    if brightness_dn <= 0 or background_dn < 0:
        raise ParameterError("brightness_dn must be positive and background_dn not negative")
    rng = np.random.default_rng(seed)
    if centre_z_mm is None:
        centre_z_mm = DEFAULT_LENS.focus_distance_mm + rng.uniform(-0.3, 0.3)
    centre = np.array([*rng.uniform(-0.3, 0.3, size=2), centre_z_mm])
    if name == "ball":
        local, params = _ball(rng)
        spread = 0.12
    else:
        local, params = _tilted_layer(rng)
        spread = 0.15
    x, y, z = local + centre[:, None]
    if name == "shadowing":
        x, y, z, pairs = _add_shadowing_partners(x, y, z, rng, centre_z_mm)
        params["shadowing_pairs"] = pairs
    brightness = brightness_dn * np.exp(rng.normal(0.0, spread, size=x.size))
    params["centre_mm"] = [float(v) for v in centre]
    particles = Particles(x, y, z, brightness)
    return Scenario(name=name, seed=int(seed), particles=particles, background_dn=float(background_dn),
                    parameters=params)


def _tilted_layer(rng: np.random.Generator, *, diameter_mm: float = 14.0, count: int = 60,
                  tilt_deg: float = 13.0) -> tuple[np.ndarray, dict]:
    """A monolayer crystal: jittered hexagonal lattice in a disk, tilted about X."""
    radius = diameter_mm / 2
    # Hexagonal density 2 / (sqrt(3) a^2) puts ``count`` particles in the disk.
    spacing = math.sqrt(2 * math.pi * radius ** 2 / (math.sqrt(3) * count))
    n = int(radius / spacing) + 3
    ii, jj = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1), indexing="ij")
    a = (ii + 0.5 * jj).ravel() * spacing
    b = (jj * math.sqrt(3) / 2).ravel() * spacing
    phi = rng.uniform(0, math.pi / 3)
    shift = rng.uniform(-0.5, 0.5, size=2) * spacing
    a, b = (a * math.cos(phi) - b * math.sin(phi) + shift[0],
            a * math.sin(phi) + b * math.cos(phi) + shift[1])
    inside = a ** 2 + b ** 2 <= radius ** 2
    a, b = a[inside], b[inside]
    a = a + rng.normal(0, 0.04 * spacing, a.size)
    b = b + rng.normal(0, 0.04 * spacing, b.size)
    c = rng.normal(0, 0.005, a.size)  # a monolayer is flat to a few micrometres
    t = math.radians(tilt_deg)
    # Rotate the layer (a, b, c) about X: its normal leaves the optical axis by ``tilt_deg``.
    x = a
    y = b * math.cos(t) - c * math.sin(t)
    z = b * math.sin(t) + c * math.cos(t)
    params = {"tilt_deg": tilt_deg, "diameter_mm": diameter_mm, "spacing_mm": spacing}
    return np.stack([x, y, z]), params


def _add_shadowing_partners(x: np.ndarray, y: np.ndarray, z: np.ndarray, rng: np.random.Generator,
                            centre_z_mm: float, *, fraction: float = 0.2,
                            depth_range_mm: tuple[float, float] = (1.0, 2.5), max_depth_mm: float = 1.9
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[list[int]]]:
    """Add a partner on (nearly) the line of sight of a fraction of the particles.

    Each partner is 1 to 2.5 mm nearer or farther than its host, within ``max_depth_mm`` of the
    cluster's mid-depth (so it stays inside the refocus range), and its image lies within about
    one lens pitch of its host's. Returns the new coordinates and ``[host, partner]`` index pairs.
    """
    n = x.size
    hosts = np.sort(rng.choice(n, size=max(2, int(round(fraction * n))), replace=False))
    px, py, pz, pairs = [], [], [], []
    for host in hosts:
        dz = rng.uniform(*depth_range_mm)
        sign = rng.choice([-1.0, 1.0])
        if abs(z[host] + sign * dz - centre_z_mm) > max_depth_mm:
            sign = -sign  # the other side stays inside the depth range
        zk = float(np.clip(z[host] + sign * dz, centre_z_mm - max_depth_mm, centre_z_mm + max_depth_mm))
        offset = rng.normal(0.0, 0.02, size=2)
        # Same direction from the lens as the host: X/Z and Y/Z equal, up to the offset.
        px.append(x[host] * zk / z[host] + offset[0])
        py.append(y[host] * zk / z[host] + offset[1])
        pz.append(zk)
        pairs.append([int(host), n + len(pairs)])
    return (np.concatenate([x, px]), np.concatenate([y, py]), np.concatenate([z, pz]), pairs)


def _ball(rng: np.random.Generator, *, shells: tuple[tuple[float, int], ...] = ((2.0, 90), (1.3, 45), (0.6, 15))
          ) -> tuple[np.ndarray, dict]:
    """A Yukawa ball: particles spread evenly (Fibonacci spiral) on nested shells, each shell
    turned at random, positions jittered."""
    points = []
    for radius, count in shells:
        k = np.arange(count) + 0.5
        polar = np.arccos(1 - 2 * k / count)
        azimuth = math.pi * (1 + math.sqrt(5)) * k
        p = radius * np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)])
        points.append(_random_rotation(rng) @ p)
    xyz = np.concatenate(points, axis=1)
    xyz += rng.normal(0, 0.03, xyz.shape)
    params = {"diameter_mm": 2 * shells[0][0], "shells": [[r, c] for r, c in shells]}
    return xyz, params


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q
