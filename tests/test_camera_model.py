"""The metadata camera model against docs/camera-model.md and the real F01 metadata."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from analysis.camera.model import CameraModel, Lattice, green_mask
from analysis.errors import MetadataError


@pytest.fixture()
def real_metadata(real_fixtures):
    return json.loads((real_fixtures / "f01-frame-metadata.json").read_text())


def test_real_metadata_gives_documented_lattice(real_metadata):
    model = CameraModel.from_metadata(real_metadata)
    # exitPupilOffset.z = 10000 in this firmware: taken as telecentric.
    assert model.optics.telecentric
    assert model.lattice.pitch_px == pytest.approx(1.389859962e-05 / 1.4e-06, rel=1e-6)
    assert model.lattice.origin_x == pytest.approx(1640 - 2.714e-06 / 1.4e-06, abs=1e-3)
    assert model.lattice.origin_y == pytest.approx(1640 + 5.66e-07 / 1.4e-06, abs=1e-3)
    ij, xy = model.lattice.centres(model.width, model.height)
    # lytro-f01.md 1.7: about 330 lenses per row and 381 rows.
    rows = np.unique(ij[:, 1]).size
    assert 378 <= rows <= 384
    assert 125_000 <= len(ij) <= 127_000
    assert np.all((xy >= 0) & (xy < 3280))
    assert model.black_level == 168 and model.white_level == 4095


def test_finite_exit_pupil_scales_pitch(real_metadata):
    meta = json.loads(json.dumps(real_metadata))
    meta["devices"]["lens"]["exitPupilOffset"]["z"] = 0.11638
    model = CameraModel.from_metadata(meta)
    assert not model.optics.telecentric
    expected = 1.389859962e-05 * (0.11638 + 2.5e-05) / 0.11638 / 1.4e-06
    assert model.lattice.pitch_px == pytest.approx(expected, rel=1e-6)
    # Thin lens: Z(alpha=1) = 1/(1/f - 1/P).
    f, p = 0.00645, 0.11638
    assert model.optics.focus_distance_mm == pytest.approx(1e3 / (1 / f - 1 / p), rel=1e-5)
    z = model.optics.z_of_alpha(np.array([0.99, 1.0, 1.01]))
    assert np.allclose(model.optics.alpha_of_z(z), [0.99, 1.0, 1.01])


def test_hex_rows_shift_half_a_pitch():
    lat = Lattice(origin_x=100.0, origin_y=50.0, pitch_px=10.0)
    x0, y0 = lat.centre(0, 0)
    x1, y1 = lat.centre(0, 1)
    assert (x0, y0) == (100.0, 50.0)
    assert x1 - x0 == pytest.approx(5.0)
    assert y1 - y0 == pytest.approx(10 * math.sqrt(3) / 2)


def test_nearest_lens_is_really_nearest():
    lat = Lattice(origin_x=1640.3, origin_y=1639.2, pitch_px=9.93, rotation_rad=0.002, scale_y=1.0005)
    rng = np.random.default_rng(1)
    x = rng.uniform(100, 3000, 2000)
    y = rng.uniform(100, 3000, 2000)
    i, j = lat.nearest(x, y)
    cx, cy = lat.centre(i, j)
    d_best = np.hypot(cx - x, cy - y)
    # brute force over the neighbourhood
    for di in range(-2, 3):
        for dj in range(-2, 3):
            ox, oy = lat.centre(i + di, j + dj)
            assert np.all(np.hypot(ox - x, oy - y) >= d_best - 1e-9)
    assert d_best.max() <= 9.93 / math.sqrt(3) + 1e-6


def test_missing_field_is_named(real_metadata):
    del real_metadata["devices"]["mla"]["lensPitch"]
    with pytest.raises(MetadataError, match="devices.mla.lensPitch"):
        CameraModel.from_metadata(real_metadata)


def test_green_mask_is_bggr():
    m = green_mask(2, 4)
    assert m.tolist() == [[False, True, False, True], [True, False, True, False]]
