"""The simulator against the camera model it must obey (camera-model.md)."""

from __future__ import annotations

import numpy as np
import pytest

from analysis.camera_model import CameraModel
from analysis.sim_camera import WHITE_RESPONSE, simulated_camera_metadata
from analysis.simulate import channel_response_map, render_white_image


def small_model(size: int = 256) -> CameraModel:
    return CameraModel.from_metadata(simulated_camera_metadata(size=size))


def micro_image_centroids(image: np.ndarray, model: CameraModel, *, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Intensity centroid of each micro-image fully on the sensor, and the model's centre."""
    radius = model.optics.micro_image_radius_px
    _, centres = model.lattice.centres(model.width, model.height, margin_px=margin)
    rows, cols = np.mgrid[0:model.height, 0:model.width]
    found = []
    for cx, cy in centres:
        c0, c1 = int(cx - radius - 1), int(cx + radius + 2)
        r0, r1 = int(cy - radius - 1), int(cy + radius + 2)
        patch = image[r0:r1, c0:c1]
        xs = cols[r0:r1, c0:c1] + 0.5
        ys = rows[r0:r1, c0:c1] + 0.5
        inside = (xs - cx) ** 2 + (ys - cy) ** 2 <= (radius + 1.0) ** 2
        w = np.where(inside, patch, 0.0)
        found.append((np.sum(w * xs) / w.sum(), np.sum(w * ys) / w.sum()))
    return np.array(found), centres


def test_white_micro_images_centred_on_model_lattice():
    model = small_model(256)
    raw = render_white_image(model, level=2400.0, noise=False).astype(np.float64)
    # Undo black and the Bayer responses so each micro-image is the plain disk it should be.
    signal = (raw - model.black_level) / channel_response_map(model.height, model.width, WHITE_RESPONSE)
    found, centres = micro_image_centroids(signal, model, margin=8.0)
    err = np.hypot(*(found - centres).T)
    assert len(centres) > 400
    assert err.mean() < 0.05
    assert err.max() < 0.1


def test_white_noisy_green_centroids_and_level():
    model = small_model(256)
    raw = render_white_image(model, level=2400.0, seed=3).astype(np.float64)
    green = (np.add.outer(np.arange(model.height), np.arange(model.width)) % 2) == 1
    signal = np.where(green, raw - model.black_level, 0.0)
    found, centres = micro_image_centroids(signal, model, margin=8.0)
    assert np.hypot(*(found - centres).T).mean() < 0.15
    # Fully lit green pixels at the micro-image centres carry the requested level (cos^4 ~ 1 here).
    cx = np.floor(centres[:, 0]).astype(int)
    cy = np.floor(centres[:, 1]).astype(int)
    cx += (cx + cy) % 2 == 0  # step onto a green site
    assert np.median(raw[cy, cx] - model.black_level) == pytest.approx(2400.0, rel=0.02)


def test_white_image_deterministic_per_seed():
    model = small_model(128)
    a = render_white_image(model, seed=7)
    assert a.dtype == np.uint16
    assert np.array_equal(a, render_white_image(model, seed=7))
    assert not np.array_equal(a, render_white_image(model, seed=8))
