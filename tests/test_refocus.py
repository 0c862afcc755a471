"""Refocus stack, sub-aperture image and products against ray-traced point sources and the
numpy reference."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from analysis.lightfield.reference import refocus_reference
from analysis.camera.model import CameraModel
from analysis.errors import ParameterError
from analysis.lightfield.table import build_table_from_model, load_table, save_table
from analysis.cache import Cache
from analysis.lightfield.refocus import (_gaussian_blur, alphas_for_depth_range, default_alphas,
    normalisation, prepare_normalisations, products, refocus_stack, subaperture_image)
from analysis.lightfield.samples import select_samples
from analysis.simulation.scenarios import Particles
from analysis.simulation.camera import simulated_camera_metadata
from analysis.simulation.render import particle_truth, render_exposure, render_white_image

BLACK = 168.0


@pytest.fixture(scope="module")
def model() -> CameraModel:
    return CameraModel.from_metadata(simulated_camera_metadata(size=320))


@pytest.fixture(scope="module")
def table(model):
    return build_table_from_model(model)


def point_source_exposure(model: CameraModel, alpha_true: float, s_hat_m: tuple[float, float], *,
                          peak_dn: float = 800.0, noise_dn: float = 2.0, seed: int = 0) -> np.ndarray:
    """Raw image of a point source traced ray by ray through the forward model of
    docs/camera-model.md (independent of the look-up table).

    The point is placed so that it is sharp at ``alpha_true`` and lands at ``s_hat_m``.
    """
    o = model.optics
    p = o.exit_pupil_m
    fp = alpha_true * p
    z = 1.0 / (1.0 / o.focal_length_m - 1.0 / fp)
    x, y = s_hat_m[0] * z / p, s_hat_m[1] * z / p
    img = np.array([x, y]) * fp / z
    r_ap = o.aperture_diameter_m / 2
    n = 301
    g = (np.arange(n) + 0.5) / n * 2 - 1
    uu, vv = np.meshgrid(g * r_ap, g * r_ap)
    disk = uu ** 2 + vv ** 2 <= r_ap ** 2
    u = np.stack([uu[disk], vv[disk]], axis=1)
    s = u + (img - u) * p / fp                                   # step 1: meets the MLA
    k = o.projection_factor / o.pixel_pitch_m
    i, j = model.lattice.nearest(model.lattice.origin_x + s[:, 0] * k, model.lattice.origin_y + s[:, 1] * k)
    cx, cy = model.lens_plane_position_m(i, j)                    # step 2: its lens
    c = np.stack([cx, cy], axis=1)
    q = c + (c - u) * o.mla_to_sensor_m / p                       # step 3: lands on the sensor
    col = np.floor(model.lattice.origin_x + q[:, 0] / o.pixel_pitch_m).astype(int)
    row = np.floor(model.lattice.origin_y + q[:, 1] / o.pixel_pitch_m).astype(int)
    cos2 = p * p / (p * p + ((s - u) ** 2).sum(axis=1))
    on = (col >= 0) & (col < model.width) & (row >= 0) & (row < model.height)
    expected = np.zeros((model.height, model.width))
    np.add.at(expected, (row[on], col[on]), (cos2 * cos2)[on])
    expected *= peak_dn / expected.max()
    rng = np.random.default_rng(seed)
    raw = BLACK + expected + rng.normal(0.0, noise_dn, expected.shape)
    return np.clip(np.rint(raw), 0, 4095).astype(np.uint16)


def sparse_random_exposure(model: CameraModel, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    raw = BLACK + rng.normal(0, 2.0, (model.height, model.width))
    spots = rng.random((model.height, model.width)) < 0.02
    raw[spots] += rng.uniform(20, 500, spots.sum())
    return np.clip(np.rint(raw), 0, 4095).astype(np.uint16)


def peak_position(image: np.ndarray, half: int = 2) -> tuple[float, float]:
    """Intensity-weighted centroid (col, row) in a small window around the maximum."""
    r, c = np.unravel_index(np.argmax(image), image.shape)
    win = image[r - half:r + half + 1, c - half:c + half + 1].astype(np.float64)
    win = np.clip(win - win.min(), 0, None)
    rr, cc = np.mgrid[r - half:r + half + 1, c - half:c + half + 1]
    return float((win * cc).sum() / win.sum()), float((win * rr).sum() / win.sum())


@pytest.mark.parametrize("method", ["bilinear", "triangles"])
@pytest.mark.parametrize("noise_sigmas", [None, 3.0])
def test_numba_matches_reference(model, table, noise_sigmas, method):
    image = sparse_random_exposure(model, seed=3)
    alphas = np.array([0.987, 0.9991, 1.0, 1.0042, 1.013])
    samples = select_samples(image, table, noise_sigmas=noise_sigmas)
    fast = refocus_stack(image, table, alphas, samples=samples, method=method)
    ref = refocus_reference(image, table, alphas, table.grid, black=BLACK, background=samples.background,
                            threshold=samples.threshold, min_coverage=0.25, method=method)
    assert fast.dtype == np.float32
    scale = np.abs(ref).max()
    assert np.abs(fast - ref).max() <= 2e-4 * scale


def test_sparse_selection_keeps_only_samples_above_noise(model, table):
    image = sparse_random_exposure(model, seed=4)
    samples = select_samples(image, table, noise_sigmas=3.0)
    assert samples.sigma == pytest.approx(2.0, rel=0.1)
    raw = (image.reshape(-1)[table.pixel_index].astype(np.float64) - BLACK
           - samples.background * table.weight.astype(np.float64))
    assert np.array_equal(samples.ids, np.flatnonzero(raw > samples.threshold))
    assert np.allclose(samples.values, raw[samples.ids])
    dense = select_samples(image, table, noise_sigmas=None)
    assert dense.ids.size == table.n_samples


@pytest.mark.parametrize("method", ["bilinear", "triangles"])
def test_point_source_is_sharpest_at_its_alpha_and_lands_at_s_hat(model, table, method):
    alphas = default_alphas()
    alpha_true = 1.0047
    s_hat = (0.11e-3, -0.07e-3)
    image = point_source_exposure(model, alpha_true, s_hat)
    stack = refocus_stack(image, table, alphas, method=method)
    sub = subaperture_image(image, table, fraction=0.3, blur_sigma_px=1.0, method=method)
    prod = products(stack, sub)
    peaks = prod.reshape(alphas.size, -1).max(axis=1)
    step = alphas[1] - alphas[0]
    best = int(np.argmax(peaks))
    assert abs(alphas[best] - alpha_true) <= 1.5 * step
    # Sub-step estimate: centroid of the peak curve above half its maximum.
    top = peaks > 0.5 * peaks.max()
    centroid = float((alphas[top] * peaks[top]).sum() / peaks[top].sum())
    assert abs(centroid - alpha_true) <= 0.5 * step
    col, row = peak_position(stack[best])
    expected_col, expected_row = table.grid.to_pixels(*s_hat)
    # Within half a lens pitch (the LOT knows only the lens, not where in it a ray entered).
    assert np.hypot(col - expected_col, row - expected_row) < 0.5


@pytest.mark.parametrize("method", ["bilinear", "triangles"])
def test_defocused_point_is_narrower_in_the_sub_aperture_image(model, table, method):
    alpha_true = 1.010
    s_hat = (0.0, 0.0)
    image = point_source_exposure(model, alpha_true, s_hat, noise_dn=0.0)
    full = refocus_stack(image, table, np.array([1.0]), method=method)[0]
    sub = subaperture_image(image, table, fraction=0.3, blur_sigma_px=0.0, method=method)

    def rms_radius(img):
        cols, rows = np.meshgrid(np.arange(img.shape[1]), np.arange(img.shape[0]))
        w = np.clip(img, 0, None)
        cx, cy = (w * cols).sum() / w.sum(), (w * rows).sum() / w.sum()
        return np.sqrt((w * ((cols - cx) ** 2 + (rows - cy) ** 2)).sum() / w.sum())

    # Blur radius on the lens plane is R * |1/alpha - 1|: about 2.8 lens pitches at full aperture.
    assert rms_radius(sub) < 0.6 * rms_radius(full)
    assert sub.dtype == np.float32 and sub.min() >= 0


@pytest.mark.parametrize("method", ["bilinear", "triangles"])
def test_white_scene_gives_flat_slices(model, method):
    """Normalisation by the light each site could receive: no lattice pattern, cos^4 once."""
    white = render_white_image(model, noise=False)
    dev = (white.astype(np.float32) - BLACK) / (4095.0 - BLACK)
    table = build_table_from_model(model, dev)
    alphas = np.array([0.987, 0.995, 1.0, 1.0071, 1.013])
    stack = refocus_stack(white, table, alphas, background=0.0, noise_sigmas=None, method=method)
    inner = stack[:, 6:-6, 6:-6]
    assert np.all(inner > 0)
    assert inner.std() / inner.mean() < 1e-3
    # Without a white image the weights are the thin-lens cos^4: flat to a few per cent.
    cos4_table = build_table_from_model(model)
    stack = refocus_stack(white, cos4_table, alphas, background=0.0, noise_sigmas=None, method=method)
    inner = stack[:, 6:-6, 6:-6]
    assert inner.std() / inner.mean() < 0.03


@pytest.mark.parametrize("method", ["bilinear", "triangles"])
def test_empty_frame_gives_zeros(model, table, method):
    image = np.full((model.height, model.width), int(BLACK), dtype=np.uint16)
    stack = refocus_stack(image, table, default_alphas(5), method=method)
    assert stack.dtype == np.float32 and not np.isnan(stack).any() and not stack.any()
    # Dense: every sample is used, the estimated background is (nearly) 0.
    stack = refocus_stack(image, table, default_alphas(5), noise_sigmas=None, method=method)
    assert not np.isnan(stack).any() and np.abs(stack).max() < 0.05
    sub = subaperture_image(image, table, method=method)
    assert not np.isnan(sub).any() and not sub.any()


def test_normalisation_is_cached_per_alpha_and_bounded(model):
    table = build_table_from_model(model)
    cache = Cache()
    a = normalisation(table, default_alphas(4), cache=cache)
    assert len(list(cache.entries("normalisation", table.uid))) == 4
    np.testing.assert_array_equal(normalisation(table, default_alphas(4), cache=cache), a)
    # A stack over other alphas takes the slices it shares from the cache, to the last bit.
    both = normalisation(table, np.r_[default_alphas(4)[1:3], 1.002], cache=cache)
    np.testing.assert_array_equal(both[:2], a[1:3])
    assert len(list(cache.entries("normalisation", table.uid))) == 5
    alone = normalisation(table, np.array([1.002]))                     # no cache: worked out afresh
    np.testing.assert_array_equal(alone[0], both[2])                    # the same, whatever came before
    # A budget of 8 slices: the least recently used go first.
    cache.max_bytes = 8 * a[0].nbytes + sum(v.nbytes for k, v in cache.entries("refocus", table.uid))
    for n in range(6, 12):
        normalisation(table, default_alphas(4), cache=cache)          # kept: used most recently
        normalisation(table, default_alphas(n), cache=cache)
    assert cache.nbytes <= cache.max_bytes
    assert all(cache.get(key) is not None for key in [k for k, _ in cache.entries("normalisation", table.uid)][-4:])


def test_out_argument_and_finer_grid(model, table):
    image = point_source_exposure(model, 1.0, (0.05e-3, 0.02e-3))
    alphas = default_alphas(3)
    out = np.empty((3, *table.grid.shape), dtype=np.float32)
    assert refocus_stack(image, table, alphas, out=out) is out
    fine = table.grid.scaled(2)
    stack = refocus_stack(image, table, alphas, grid=fine)
    assert stack.shape == (3, *fine.shape)
    # "auto" takes the lens triangles on a finer grid: no holes even at alpha = 1.
    inner = stack[:, 10:-10, 10:-10]
    dense = refocus_stack(image, table, alphas, grid=fine, noise_sigmas=None)[:, 10:-10, 10:-10]
    assert np.count_nonzero(dense == 0) == 0
    holes = refocus_stack(image, table, alphas, grid=fine, noise_sigmas=None, method="bilinear")[1, 10:-10, 10:-10]
    assert np.count_nonzero(holes == 0) > 0.05 * holes.size
    assert inner.max() > 0
    # Same image, sampled twice as densely: the peak lands at the same lens-plane place.
    x1, y1 = table.grid.to_lens_plane(*peak_position(out[1]))
    x2, y2 = fine.to_lens_plane(*peak_position(stack[1], half=4))
    assert np.hypot(x1 - x2, y1 - y2) < 0.25 * table.grid.step_m
    with pytest.raises(ParameterError, match="out"):
        refocus_stack(image, table, alphas, out=np.empty((2, 3, 4), np.float32))


def test_wrong_image_or_alphas_are_refused(table):
    with pytest.raises(ParameterError, match="look-up table"):
        refocus_stack(np.zeros((10, 10), np.uint16), table)
    image = np.zeros((table.height, table.width), np.uint16)
    with pytest.raises(ParameterError, match="alphas"):
        refocus_stack(image, table, np.array([1.0, -1.0]))
    with pytest.raises(ParameterError, match="fraction"):
        subaperture_image(image, table, fraction=0.0)
    with pytest.raises(ParameterError, match="method"):
        refocus_stack(image, table, method="nearest")
    with pytest.raises(ParameterError, match="raw image or the samples"):
        refocus_stack(None, table)
    with pytest.raises(ParameterError, match="raw image or the samples"):
        subaperture_image(None, table)


@pytest.mark.parametrize("method", ["bilinear", "triangles"])
def test_selected_samples_stand_for_the_image(model, table, method):
    # The look-again pass lets its residual image go once its samples are selected.
    image = sparse_random_exposure(model, seed=5)
    samples = select_samples(image, table)
    alphas = np.array([0.995, 1.0, 1.007])
    assert np.array_equal(refocus_stack(None, table, alphas, samples=samples, method=method),
                          refocus_stack(image, table, alphas, method=method))
    assert np.array_equal(subaperture_image(None, table, samples=samples, method=method),
                          subaperture_image(image, table, method=method))


def test_alphas_for_depth_range_round_trip(model):
    alphas = alphas_for_depth_range(55.0, 65.0, 11, model.optics)
    assert np.all(np.diff(alphas) > 0)
    z = model.optics.z_of_alpha(alphas)
    assert z[0] == pytest.approx(65.0) and z[-1] == pytest.approx(55.0)
    with pytest.raises(ParameterError):
        alphas_for_depth_range(65.0, 55.0, 11, model.optics)


def test_diffuse_glow_is_estimated_and_removed(model):
    """Plasma glow lights the sensor like the white image: subtracted in proportion to weight."""
    white = render_white_image(model, noise=False)
    table = build_table_from_model(model, (white.astype(np.float32) - BLACK) / (4095.0 - BLACK))
    glow = render_white_image(model, level=40.0, seed=5)
    samples = select_samples(glow, table, noise_sigmas=None)
    kept = refocus_stack(glow, table, default_alphas(3), background=0.0, noise_sigmas=None)[:, 6:-6, 6:-6]
    assert samples.background == pytest.approx(kept.mean(), rel=0.02)
    removed = refocus_stack(glow, table, default_alphas(3), samples=samples)[:, 6:-6, 6:-6]
    assert abs(removed.mean()) < 0.01 * samples.background
    # Sparse: what is left of pure glow is a few faint noise spikes, never below zero.
    sparse = refocus_stack(glow, table, default_alphas(3))[:, 6:-6, 6:-6]
    assert sparse.min() >= 0 and sparse.max() < 0.05 * samples.background
    assert np.count_nonzero(sparse) < 0.3 * sparse.size


def test_prepared_normalisations_travel_with_the_saved_table(tmp_path, model):
    table = build_table_from_model(model)
    alphas = default_alphas(6)
    cache = Cache()
    prepare_normalisations(table, alphas, fraction=0.25, cache=cache)
    fresh = Cache()
    back = load_table(save_table(table, tmp_path / "lot.npz", cache=cache), cache=fresh)
    assert back.uid == table.uid and len(fresh) == 6 + 1   # a slice each, and the sub-aperture image
    image = point_source_exposure(model, 1.004, (0.0, 0.0))
    assert np.array_equal(refocus_stack(image, back, alphas, cache=fresh), refocus_stack(image, table, alphas))
    assert np.array_equal(subaperture_image(image, back, fraction=0.25, cache=fresh),
                          subaperture_image(image, table, fraction=0.25))
    assert len(list(fresh.entries("normalisation", back.uid))) == 7   # nothing recomputed


def test_simulated_particles_are_sharp_at_their_true_alpha_and_place(model):
    """Ground truth from the simulator (its own ray tracer, blur, glow and noise).

    Depths are at least 1.5 steps of alpha away from 1: within about ``|1/alpha - 1| < pitch /
    (2 R)`` (here +-0.0017) a particle's blur fits inside one lens and its micro-image is the
    same at every such depth, so no refocus can tell them apart (ray_depth handles those).
    """
    white = render_white_image(model, noise=False)
    table = build_table_from_model(model, (white.astype(np.float32) - BLACK) / (4095.0 - BLACK))
    o = model.optics
    alphas_true = np.array([0.992, 0.996, 1.0035, 1.006, 1.0085])
    s_true = np.array([(-0.12e-3, -0.10e-3), (-0.1e-3, 0.1e-3), (0.02e-3, 0.11e-3), (0.1e-3, 0.1e-3),
                       (0.13e-3, -0.04e-3)])
    z = np.asarray(o.z_of_alpha(alphas_true))
    particles = Particles(s_true[:, 0] * z / o.exit_pupil_m, s_true[:, 1] * z / o.exit_pupil_m, z,
                          np.full(len(z), 1500.0))
    truth = particle_truth(model, particles)
    assert np.allclose(truth.alpha, alphas_true)
    raw = render_exposure(model, particles, seed=7, background_dn=40.0)
    alphas = default_alphas()
    stack = refocus_stack(raw, table, alphas)
    step = alphas[1] - alphas[0]
    for n in range(len(z)):
        col, row = table.grid.to_pixels(*s_true[n])
        r, c = int(round(float(row))), int(round(float(col)))
        peaks = stack[:, r - 2:r + 3, c - 2:c + 3].reshape(alphas.size, -1).max(axis=1)
        # (The curve is lopsided toward alpha = 1, where blur disks shrink onto lens centres,
        # so its maximum, not its centroid, marks the depth.)
        best = int(np.argmax(peaks))
        assert abs(alphas[best] - alphas_true[n]) <= 1.5 * step
        window = stack[best, r - 4:r + 5, c - 4:c + 5]
        pc, pr = peak_position(window)
        assert np.hypot(pc + c - 4 - col, pr + r - 4 - row) < 0.5


def test_blur_is_a_normalised_gaussian():
    rng = np.random.default_rng(2)
    image = rng.random((40, 50)).astype(np.float32)
    ours = _gaussian_blur(image, 1.3)
    theirs = cv2.GaussianBlur(image, (0, 0), sigmaX=1.3, sigmaY=1.3, borderType=cv2.BORDER_CONSTANT)
    assert ours.dtype == np.float32
    assert np.abs(ours - theirs)[6:-6, 6:-6].max() < 2e-3
    point = np.zeros((21, 21), np.float32)
    point[10, 10] = 1.0
    blurred = _gaussian_blur(point, 2.0)
    assert blurred.sum() == pytest.approx(1.0, abs=1e-4)
    cols = np.arange(21) - 10
    assert np.sqrt((blurred.sum(axis=0) * cols ** 2).sum()) == pytest.approx(2.0, rel=0.02)
