"""The cluster's collective motion between two shots: a rigid turn about its centre plus a drift.

Linking predicts each particle's next position with it (so a turning or drifting cluster links
as easily as a still one), and temperatures are measured relative to it (a rotation is not heat).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RigidMotion:
    """Rigid motion at constant rates: the centre moves at ``velocity_mm_s`` and the cluster turns
    about it at ``omega_rad_s`` (rotation vector, right-handed, camera frame).

    ``centre_mm`` is the centre at time ``t_s``.
    """

    centre_mm: np.ndarray
    t_s: float
    velocity_mm_s: np.ndarray
    omega_rad_s: np.ndarray

    @classmethod
    def still(cls, centre_mm: np.ndarray, t_s: float) -> RigidMotion:
        return cls(np.asarray(centre_mm, float), float(t_s), np.zeros(3), np.zeros(3))

    def centre_at(self, t_s: float) -> np.ndarray:
        return self.centre_mm + self.velocity_mm_s * (t_s - self.t_s)

    def predict(self, xyz_mm: np.ndarray, t_from: np.ndarray, t_to: float) -> np.ndarray:
        """Where points seen at times ``t_from`` (n,) are at ``t_to`` if they move with the cluster.

        Parameters
        ----------
        xyz_mm : ndarray of shape (n, 3)
        t_from : ndarray of shape (n,)
        t_to : float

        Returns
        -------
        ndarray of shape (n, 3)
        """
        xyz_mm = np.asarray(xyz_mm, float)
        t_from = np.broadcast_to(np.asarray(t_from, float), (len(xyz_mm),))
        dt = t_to - t_from
        rel = xyz_mm - (self.centre_mm + np.outer(t_from - self.t_s, self.velocity_mm_s))
        turned = rotate(rel, np.outer(dt, self.omega_rad_s))
        return self.centre_at(t_to) + turned


def rotate(vectors: np.ndarray, rotation_vectors: np.ndarray) -> np.ndarray:
    """Rodrigues' rotation of each row of ``vectors`` by the matching row of ``rotation_vectors``
    (axis times angle in radians)."""
    theta = np.linalg.norm(rotation_vectors, axis=-1, keepdims=True)
    safe = np.where(theta > 0, theta, 1.0)
    k = rotation_vectors / safe
    cos, sin = np.cos(theta), np.sin(theta)
    return vectors * cos + np.cross(k, vectors) * sin + k * np.sum(k * vectors, axis=-1, keepdims=True) * (1 - cos)


def kabsch(a: np.ndarray, b: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The rotation ``R`` and translation ``t`` with ``b ~ a @ R.T + t`` in the weighted
    least-squares sense (Kabsch 1976).

    Parameters
    ----------
    a, b : ndarray of shape (n, 3)
    weights : ndarray of shape (n,), optional

    Returns
    -------
    R : ndarray of shape (3, 3)
    t : ndarray of shape (3,)
    """
    w = np.ones(len(a)) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    ca, cb = w @ a, w @ b
    h = ((a - ca) * w[:, None]).T @ (b - cb)
    u, _, vt = np.linalg.svd(h)
    d = math.copysign(1.0, np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cb - ca @ r.T


def rotation_vector(r: np.ndarray) -> np.ndarray:
    """Axis times angle (radians) of a rotation matrix."""
    angle = math.acos(max(-1.0, min(1.0, (np.trace(r) - 1) / 2)))
    if angle < 1e-12:
        return np.zeros(3)
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / (2 * math.sin(angle))
    return axis * angle


def fit_motion(a: np.ndarray, t_a: np.ndarray, b: np.ndarray, t_b: float, *,
               weights: np.ndarray | None = None, turn: bool = True) -> RigidMotion:
    """The rigid motion that carries linked points ``a`` (seen at ``t_a``) to ``b`` (at ``t_b``).

    Points seen at different times (bridged gaps) are weighed by 1 / gap. With fewer than four
    points, or ``turn=False``, only a drift is fitted.
    """
    a, b = np.asarray(a, float), np.asarray(b, float)
    t_a = np.broadcast_to(np.asarray(t_a, float), (len(a),))
    dt = t_b - t_a
    if len(a) == 0 or np.any(dt <= 0):
        centre = b.mean(axis=0) if len(b) else np.zeros(3)
        return RigidMotion.still(centre, t_b)
    w = (1.0 / dt) if weights is None else np.asarray(weights, float) / dt
    typical = float(np.median(dt))
    if len(a) < 4 or not turn:
        velocity = (w @ ((b - a) / dt[:, None])) / w.sum()
        return RigidMotion(w @ b / w.sum(), float(t_b), velocity, np.zeros(3))
    r, _ = kabsch(a, b, w)
    omega = rotation_vector(r) / typical
    centre_b = w @ b / w.sum()
    centre_a = w @ a / w.sum()
    velocity = (centre_b - centre_a) / typical
    return RigidMotion(centre_b, float(t_b), velocity, omega)
