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
``cloud``
    A 3D cloud of 400 particles filling an ellipsoid 10 x 7 x 4 mm (X, Y, Z) with a hard core of
    0.5 mm between them, its centre 2.6 mm in front of the focus (alpha 1.003 ... 1.023), so
    every particle's blur is about a lens pitch or more.

``varied=True`` draws each cluster's size, shape, tilt and placement from wide ranges (a stream
of its own of the seed), so that scenes are not the ones the pipeline was developed on; a given
``centre_z_mm`` is kept. ``brightness_spread`` draws brightness log-uniform over that ratio
about the median (another stream), leaving positions as they are.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from analysis.errors import ParameterError
from .camera import DEFAULT_LENS

SCENARIO_NAMES = ("tilted-layer", "shadowing", "ball", "cloud")

#: How far in front of the focus the cloud's centre lies by default, mm.
CLOUD_IN_FRONT_MM = 2.6


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


def make_scenario(name: str, seed: int, *, centre_z_mm: float | None = None, brightness_dn: float = 1800.0,
                  background_dn: float = 40.0, varied: bool = False, brightness_spread: float | None = None
                  ) -> Scenario:
    """Build a scenario's particles, deterministically from ``seed``.

    Parameters
    ----------
    name : {"tilted-layer", "shadowing", "ball", "cloud"}
    seed : int
    centre_z_mm : float, optional
        Depth of the cluster centre; by default the simulated lens's focus distance (the cloud:
        2.6 mm in front of it) plus a seed-dependent offset of up to 0.3 mm (up to 1 mm, varied).
    brightness_dn : float
        Median particle brightness (raw DN above black of a fully lit green pixel).
    background_dn : float
        Plasma glow: a uniform diffuse background, in the same units.
    varied : bool
        Draw the cluster's size, shape, tilt and placement from wide ranges (`vary_geometry`).
    brightness_spread : float, optional
        Ratio of the brightest to the faintest particle: brightness log-uniform over it about
        ``brightness_dn``. By default a narrow log-normal spread (about 15 %).

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
    if brightness_spread is not None and not (1.0 <= brightness_spread <= 1000.0):
        raise ParameterError(f"brightness_spread={brightness_spread}: give a ratio of 1 ... 1000")
    rng = np.random.default_rng(seed)
    geometry = vary_geometry(name, np.random.default_rng([seed, 0x5CE7E])) if varied else {}
    nominal_z = DEFAULT_LENS.focus_distance_mm - (CLOUD_IN_FRONT_MM if name == "cloud" else 0.0)
    if centre_z_mm is None:
        centre_z_mm = nominal_z + rng.uniform(-0.3, 0.3) + geometry.pop("centre_dz_mm", 0.0)
    geometry.pop("centre_dz_mm", None)
    lateral = geometry.pop("centre_lateral_mm", 0.3)
    centre = np.array([*rng.uniform(-lateral, lateral, size=2), centre_z_mm])
    partners = {k: geometry.pop(k) for k in ("fraction", "depth_range_mm", "max_depth_mm") if k in geometry}
    if name == "ball":
        local, params = _ball(rng, **geometry)
        spread = 0.12
    elif name == "cloud":
        local, params = _cloud(rng, **geometry)
        spread = 0.15
    else:
        local, params = _tilted_layer(rng, **geometry)
        spread = 0.15
    x, y, z = local + centre[:, None]
    if name == "shadowing":
        x, y, z, pairs = _add_shadowing_partners(x, y, z, rng, centre_z_mm, **partners)
        params["shadowing_pairs"] = pairs
        params.update({k: v for k, v in partners.items()})
    brightness = brightness_dn * np.exp(rng.normal(0.0, spread, size=x.size))
    if brightness_spread is not None:
        exponent = np.random.default_rng([seed, 0xB1]).uniform(-0.5, 0.5, size=x.size)
        brightness = brightness_dn * brightness_spread ** exponent
        params["brightness_spread"] = float(brightness_spread)
    if varied:
        params["varied"] = True
    params["centre_mm"] = [float(v) for v in centre]
    particles = Particles(x, y, z, brightness)
    return Scenario(name=name, seed=int(seed), particles=particles, background_dn=float(background_dn),
                    parameters=params)


def vary_geometry(name: str, rng: np.random.Generator) -> dict[str, Any]:
    """Cluster geometry drawn from wide ranges, for ``make_scenario(..., varied=True)``.

    Layers: 11 ... 16 mm across, 45 ... 80 particles, tilted 6 ... 20 degrees about an axis up to
    30 degrees from X. Shadowing partners: 15 ... 30 % of the particles, 0.6 ... 3 mm from their
    host. Balls: 3.4 ... 7 mm across, flattened in Y by up to 20 %. Clouds: each axis 0.8 ... 1.25
    times the nominal. The centre: up to 1 mm off in depth and laterally.
    """
    out: dict[str, Any] = {"centre_dz_mm": float(rng.uniform(-1.0, 1.0)),
                           "centre_lateral_mm": float(rng.uniform(0.3, 1.0))}
    if name in ("tilted-layer", "shadowing"):
        out.update(diameter_mm=float(rng.uniform(11.0, 16.0)), count=int(rng.integers(45, 81)),
                   tilt_deg=float(rng.uniform(6.0, 20.0)), tilt_axis_deg=float(rng.uniform(-30.0, 30.0)))
        if name == "shadowing":
            out.update(fraction=float(rng.uniform(0.15, 0.3)),
                       depth_range_mm=(float(rng.uniform(0.6, 1.0)), float(rng.uniform(2.0, 3.0))),
                       max_depth_mm=float(rng.uniform(1.9, 2.5)))
    elif name == "ball":
        out.update(scale=float(rng.uniform(0.85, 1.75)), flattening=float(rng.uniform(0.8, 1.0)))
    elif name == "cloud":
        out.update(semi_axes_mm=tuple(float(a * rng.uniform(0.8, 1.25)) for a in _CLOUD_SEMI_AXES_MM))
    return out


def _tilted_layer(rng: np.random.Generator, *, diameter_mm: float = 14.0, count: int = 60,
                  tilt_deg: float = 13.0, tilt_axis_deg: float = 0.0) -> tuple[np.ndarray, dict]:
    """A monolayer crystal: jittered hexagonal lattice in a disk, tilted about X (turned by
    ``tilt_axis_deg`` about Z)."""
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
    if tilt_axis_deg:
        turn = math.radians(tilt_axis_deg)
        x, y = x * math.cos(turn) - y * math.sin(turn), x * math.sin(turn) + y * math.cos(turn)
        params["tilt_axis_deg"] = tilt_axis_deg
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


def _ball(rng: np.random.Generator, *, shells: tuple[tuple[float, int], ...] = ((2.0, 90), (1.3, 45), (0.6, 15)),
          scale: float = 1.0, flattening: float = 1.0) -> tuple[np.ndarray, dict]:
    """A Yukawa ball: particles spread evenly (Fibonacci spiral) on nested shells, each shell
    turned at random, positions jittered; radii times ``scale``, ``Y`` times ``flattening``."""
    shells = tuple((r * scale, c) for r, c in shells)
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
    if flattening != 1.0:
        xyz[1] *= flattening
        params["flattening"] = flattening
    return xyz, params


_CLOUD_SEMI_AXES_MM = (5.0, 3.5, 2.0)


def _cloud(rng: np.random.Generator, *, count: int = 400, semi_axes_mm: tuple[float, float, float] = _CLOUD_SEMI_AXES_MM,
           hard_core_mm: float = 0.5) -> tuple[np.ndarray, dict]:
    """A liquid-like cloud: ``count`` points uniform in an ellipsoid, none closer than ``hard_core_mm``
    (random sequential addition)."""
    axes = np.asarray(semi_axes_mm, dtype=np.float64)
    accepted = np.empty((0, 3))
    tries = 0
    while accepted.shape[0] < count:
        tries += 1
        if tries > 200:
            raise ParameterError(f"cannot place {count} particles {hard_core_mm} mm apart in a {2 * axes} mm "
                                 "ellipsoid; make it larger or the hard core smaller")
        batch = rng.uniform(-1.0, 1.0, size=(4 * count, 3))
        batch = batch[np.sum(batch ** 2, axis=1) <= 1.0] * axes
        for point in batch:
            if accepted.shape[0] >= count:
                break
            if accepted.shape[0] == 0 or np.min(np.sum((accepted - point) ** 2, axis=1)) >= hard_core_mm ** 2:
                accepted = np.vstack([accepted, point])
    params = {"semi_axes_mm": [float(a) for a in axes], "hard_core_mm": hard_core_mm, "count": count}
    return accepted.T.copy(), params


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q
