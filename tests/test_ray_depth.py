"""The raw-pixel forward-model fit against the simulator's ray-traced particles (known depth)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from analysis.calibration.cache import load_calibration
from analysis.camera.model import CameraModel
from analysis.formats.exposure import read_exposure
from analysis.lightfield.table import build_table_from_model
from analysis.formats.particle_table import read_csv
from analysis.pipeline.tables import FIT_TABLE_RIM_PX, get_table
from analysis.cache import Cache
from analysis.depth.footprint import pixel_footprint
from analysis.depth.rayfit import RayFit, aperture_per_lens_plane, fit_rays
from analysis.depth.sample_noise import SampleNoise
from analysis.depth.candidate_kernels import censored_intensity
from analysis.depth.rayfit_kernels import GridPass, _count_inside, _position_offsets, grid_costs
from analysis.depth.render_kernels import lit_fraction
from analysis.depth.table_index import TableIndex
from analysis.lightfield.samples import select_samples
from analysis.simulation.scenarios import Particles
from analysis.simulation.camera import simulated_camera_metadata
from analysis.simulation.render import render_exposure, white_coverage
from analysis.simulation.scenario_files import write_scenario
from line_of_sight_scenes import COARSE, PIPELINE_COARSE, peaks_at
from simulated_case import mean_nn_mm


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("rays")
    write_scenario(folder, "tilted-layer", 7, size=1200)
    exposure = read_exposure(folder / "IMG_0001.lfp")
    calibration = load_calibration(folder / "calibration", exposure.metadata, serial=exposure.serial)
    cache = Cache()
    table = get_table(calibration, cache, rim_px=FIT_TABLE_RIM_PX)
    truth = read_csv(folder / "IMG_0001.truth.csv")
    nn = mean_nn_mm(folder)
    p_m = exposure.model.optics.exit_pupil_m
    s_hat = np.column_stack([truth["X"], truth["Y"]]) * p_m / truth["Z"][:, None]  # metres, shared magnification
    noise = select_samples(exposure.image, get_table(calibration, cache))
    return exposure, calibration, table, truth, nn, s_hat, noise


def depth_error_over_nn(exposure, alpha, truth, nn):
    return (np.asarray(exposure.model.optics.z_of_alpha(alpha)) - truth["Z"]) / nn


def test_fit_recovers_depth_of_defocused_particles_from_a_poor_start(scene):
    exposure, calibration, table, truth, nn, s_hat, noise = scene
    rng = np.random.default_rng(0)
    start_alpha = truth["alpha"] + rng.normal(0, 0.0015, truth["alpha"].size)  # about 2 slices off
    start = s_hat + rng.normal(0, 3e-6, s_hat.shape)  # a fifth of a lens pitch off
    fit = fit_rays(exposure.image, table, start[:, 0], start[:, 1], start_alpha, background=noise.background,
                   aperture_per_lens_plane=aperture_per_lens_plane(calibration.model.optics))
    err = depth_error_over_nn(exposure, fit.alpha, truth, nn)
    err0 = depth_error_over_nn(exposure, start_alpha, truth, nn)
    defocused = truth["blur_pitches"] > 1.0
    assert defocused.sum() >= 3
    assert np.sqrt(np.mean(err[defocused] ** 2)) < 0.05
    assert np.sqrt(np.mean(err**2)) < 0.6 * np.sqrt(np.mean(err0**2))
    pitch = float(np.hypot(*table.basis_m[:, 0]))
    lateral = np.hypot(fit.sx_m - s_hat[:, 0], fit.sy_m - s_hat[:, 1]) / pitch
    # Within its lens cell (a particle lighting one lens is placed nowhere more exactly), and
    # much better on average.
    assert np.all(lateral < 0.6) and np.sqrt(np.mean(lateral**2)) < 0.25
    assert np.all(fit.intensity > 0.5 * truth["brightness"]) and np.all(fit.residual < 0.2)


def test_fit_reports_undetermined_depth_for_a_single_lens(scene):
    """Near focus one lens holds all the light, so any small blur fits; the spread says so."""
    exposure, calibration, table, truth, nn, s_hat, noise = scene
    fit = fit_rays(exposure.image, table, s_hat[:, 0], s_hat[:, 1], truth["alpha"], background=noise.background,
                   aperture_per_lens_plane=aperture_per_lens_plane(calibration.model.optics))
    sharp = truth["blur_pitches"] < 0.3
    blurred = truth["blur_pitches"] > 1.2
    if not (sharp.any() and blurred.any()):
        pytest.skip("this seed has no particle in one of the two groups")
    assert np.median(fit.alpha_spread[sharp]) > np.median(fit.alpha_spread[blurred])


def test_empty_start_list():
    from analysis.lightfield.table import build_table_from_model
    from analysis.camera.model import CameraModel
    from analysis.simulation.camera import simulated_camera_metadata

    table = build_table_from_model(CameraModel.from_metadata(simulated_camera_metadata(size=64)))
    fit = fit_rays(np.zeros((64, 64), np.uint16), table, np.empty(0), np.empty(0), np.empty(0), background=0.0,
                   aperture_per_lens_plane=641.0)
    assert len(fit) == 0


@pytest.mark.parametrize("blur, offset", [(1.1, (0.08, 0.03)), (1.1, (0.0, 0.1)), (1.1, (0.15, 0.0)), (1.0, (0.15, 0.0))])
def test_fit_tells_in_front_of_focus_from_behind(blur, offset):
    """A blur of about one pitch spills a sliver of light into the neighbouring lenses; which side
    of their micro-images it lights flips with the sign of the defocus (the aperture maps onto
    the MLA mirrored), so the fit recovers the sign and size instead of averaging the two."""
    from analysis.camera.model import CameraModel
    from analysis.lightfield.table import build_table_from_model
    from analysis.simulation.scenarios import Particles
    from analysis.simulation.camera import simulated_camera_metadata
    from analysis.simulation.render import particle_truth, render_exposure, white_coverage

    model = CameraModel.from_metadata(simulated_camera_metadata(size=480))
    optics = model.optics
    table = build_table_from_model(model, white_coverage(model), rim_px=FIT_TABLE_RIM_PX)
    s_hat = offset[0] * table.basis_m[:, 0] + offset[1] * table.basis_m[:, 1]  # near the central lens
    for sign in (1.0, -1.0):
        c = sign * blur * optics.lens_pitch_m / optics.aperture_diameter_m  # c = 1 - 1/alpha
        z = float(optics.z_of_alpha(1.0 / (1.0 - c)))
        one = Particles(np.array([s_hat[0] * z / optics.exit_pupil_m]), np.array([s_hat[1] * z / optics.exit_pupil_m]),
                        np.array([z]), np.array([1800.0]))
        assert particle_truth(model, one).blur_pitches[0] == pytest.approx(blur, rel=1e-3)
        image = render_exposure(model, one, seed=3)
        # Start at focus: the brightness of a refocused stack cannot tell the two signs apart.
        fit = fit_rays(image, table, s_hat[:1], s_hat[1:], np.ones(1), background=0.0,
                       aperture_per_lens_plane=aperture_per_lens_plane(optics), coarse=COARSE)
        c_fit = 1.0 - 1.0 / fit.alpha[0]
        # Averaging the two signs' minima gives about 0; the sign and most of the size must come back.
        assert c_fit / c > 0.5, (sign, c_fit, c)


def test_prior_decides_only_where_the_pixels_cannot(scene):
    """A depth prior settles particles that light one lens, and yields to the pixels elsewhere."""
    exposure, calibration, table, truth, nn, s_hat, noise = scene
    ratio = aperture_per_lens_plane(calibration.model.optics)
    args = dict(background=noise.background, aperture_per_lens_plane=ratio)
    sharp = truth["blur_pitches"] < 0.3
    defocused = truth["blur_pitches"] > 1.5
    assert sharp.sum() >= 2 and defocused.sum() >= 2
    free = fit_rays(exposure.image, table, s_hat[:, 0], s_hat[:, 1], truth["alpha"], **args)
    sigma = np.full(truth["alpha"].size, 5e-5)
    right = fit_rays(exposure.image, table, s_hat[:, 0], s_hat[:, 1], truth["alpha"], **args,
                     prior_alpha=truth["alpha"], prior_sigma=sigma)
    err_free = np.abs(free.alpha - truth["alpha"])[sharp]
    err_right = np.abs(right.alpha - truth["alpha"])[sharp]
    assert np.mean(err_right) < 0.5 * np.mean(err_free) + 1e-5
    assert np.all(right.alpha_spread[sharp] < free.alpha_spread[sharp])
    # A confident but wrong prior, 3 mm-equivalent off: the defocused particles' own light wins.
    wrong = fit_rays(exposure.image, table, s_hat[:, 0], s_hat[:, 1], truth["alpha"], **args,
                     prior_alpha=truth["alpha"] + 0.003, prior_sigma=sigma)
    assert np.allclose(wrong.alpha[defocused], free.alpha[defocused], atol=2e-4)


def test_refit_with_neighbours_light_taken_off_keeps_isolated_particles(scene):
    """Deblending adds each particle's own light back: an isolated particle refits to the same place."""
    from analysis.depth.rayfit import render_fits

    exposure, calibration, table, truth, nn, s_hat, noise = scene
    ratio = aperture_per_lens_plane(calibration.model.optics)
    args = dict(background=noise.background, aperture_per_lens_plane=ratio)
    first = fit_rays(exposure.image, table, s_hat[:, 0], s_hat[:, 1], truth["alpha"], **args)
    explained = render_fits(table, first, aperture_per_lens_plane=ratio)
    again = fit_rays(exposure.image, table, first.sx_m, first.sy_m, first.alpha, **args, subtract=explained,
                     own=first)
    gone = fit_rays(exposure.image, table, first.sx_m, first.sy_m, first.alpha, **args, subtract=explained)
    assert np.allclose(again.intensity, first.intensity, rtol=0.1)
    assert np.median(np.abs(again.alpha - first.alpha)) < 1e-4
    # Without adding its own light back, a particle's pixels are (nearly) empty.
    assert np.median(gone.intensity) < 0.3 * np.median(first.intensity)


def _reference_costs(centres, ptr, uv, values, root_w, censored, sx0, sy0, c_lo, c_hi, grid, cells):
    # Weighted least squares: values come multiplied by root_w, as the kernel takes them.
    n_c, half_lat, n_lat, sub = grid.n_depths, grid.half_lateral, grid.n_lateral, grid.footprint
    pitch, r_ap2 = cells.pitch, cells.r_ap2
    costs = []
    sum_v2 = float(np.sum(values[ptr[0]:ptr[-1]] ** 2))
    for ic in range(n_c):
        c = c_lo + (c_hi - c_lo) * ic / max(n_c - 1, 1)
        reach = abs(c) * np.sqrt(r_ap2) + 1.8 * pitch
        for iy in range(n_lat):
            for ix in range(n_lat):
                sx = sx0 - half_lat + 2.0 * half_lat * ix / max(n_lat - 1, 1)
                sy = sy0 - half_lat + 2.0 * half_lat * iy / max(n_lat - 1, 1)
                s_vf = s_ff = 0.0
                for lens in range(centres.shape[0]):
                    if np.hypot(centres[lens, 0] - sx, centres[lens, 1] - sy) > reach:
                        continue
                    for j in range(ptr[lens], ptr[lens + 1]):
                        f = lit_fraction(uv[j, 0], uv[j, 1], centres[lens, 0], centres[lens, 1], sx, sy, c, cells, sub)
                        if f > 0.0:
                            s_vf += values[j] * f * root_w[j]
                            s_ff += (f * root_w[j]) ** 2
                costs.append(sum_v2 - s_vf * s_vf / s_ff if s_ff > 0 and s_vf > 0 else sum_v2)
    return np.array(costs)


@pytest.mark.parametrize("blur, points, rim", [(0.4, 1, 1.0), (1.1, 3, 1.0), (2.5, 3, 1.0), (-1.1, 3, 1.0),
                                               (-2.5, 2, 1.0), (1.1, 3, 0.6), (-2.5, 3, 0.6)])
def test_grid_costs_match_the_model_one_candidate_at_a_time(blur, points, rim):
    """The grid kernel's costs (with its shortcuts) are those of the model one candidate at a time
    (:func:`lit_fraction`), with a flat pixel response and one falling to ``rim`` at the rim."""
    model = CameraModel.from_metadata(simulated_camera_metadata(size=480))
    optics = model.optics
    table = build_table_from_model(model, white_coverage(model), rim_px=FIT_TABLE_RIM_PX)
    idx = TableIndex(table)
    s_hat = 0.13 * table.basis_m[:, 0] + 0.07 * table.basis_m[:, 1]
    c = blur * optics.lens_pitch_m / optics.aperture_diameter_m
    z = float(optics.z_of_alpha(1.0 / (1.0 - c)))
    one = Particles(np.array([s_hat[0] * z / optics.exit_pupil_m]), np.array([s_hat[1] * z / optics.exit_pupil_m]),
                    np.array([z]), np.array([1800.0]))
    image = render_exposure(model, one, seed=3)
    # A grid around a start a little off the truth: positions and depths on both sides of it.
    sx0, sy0 = s_hat[0] + 0.1 * idx.pitch_m, s_hat[1] - 0.05 * idx.pitch_m
    c_lo, c_hi = c - 0.3 * abs(c) - 5e-4, c + 0.25 * abs(c) + 5e-4  # blur +-30 % and +-0.3 pitch
    reach = max(abs(c_lo), abs(c_hi)) * idx.radius_m + 1.6 * idx.pitch_m
    g = idx.gather(np.array([sx0]), np.array([sy0]), np.array([reach]))
    flat = image.reshape(-1)
    values = (flat[table.pixel_index[g.ids]].astype(np.float64) - table.black_level) / idx.weight(g.ids)
    values -= np.median(values)  # the background: most gathered samples see none of the particle
    uv = idx.uv(g.ids)
    # Samples weighted unevenly (here by their white weight, as a read-noise-limited fit would).
    root_w = idx.weight(g.ids)
    values *= root_w
    grid = GridPass(4, 0.3 * idx.pitch_m, 3, pixel_footprint(points, 0.5) * idx.u_per_px, 1.0)
    args = (g.centres, g.sample_ptr, uv, values, root_w, np.zeros(values.size, np.bool_), sx0, sy0, c_lo, c_hi,
            grid, idx.cells(aperture_per_lens_plane(optics), np.log(rim) / table.micro_image_radius_px ** 2))
    n = 4 * 3 * 3
    _, costs, _, _, _ = grid_costs(*args)
    assert costs.size == n
    expected = _reference_costs(*args)
    sum_v2 = float(np.sum(values**2))
    # Most candidates put light on the particle's pixels, some explain them well (the comparison
    # below is not one of empty sums), and they differ.
    assert np.sum(expected < sum_v2) >= n // 2 and expected.min() < 0.5 * sum_v2
    assert np.unique(expected).size >= n // 2
    np.testing.assert_allclose(costs, expected, rtol=1e-12, atol=1e-12 * sum_v2)
    # Unweighted (an empty root_w): every sample counts once.
    plain = (*args[:3], values / root_w, np.empty(0), *args[5:])
    _, costs, _, _, _ = grid_costs(*plain)
    expected = _reference_costs(*plain[:4], np.ones(values.size), *plain[5:])
    assert not np.allclose(costs, _reference_costs(*args))
    np.testing.assert_allclose(costs, expected, rtol=1e-12, atol=1e-12 * float(np.sum(plain[3] ** 2)))


def test_point_counts_skip_only_points_settled_at_every_position():
    """_count_inside counts points inside or beyond a side at every position once: the counts
    must be those of testing every point at every position, also for points at the bounds."""
    rng = np.random.default_rng(5)
    pitch = 1.0
    normals = np.array([[pitch, 0.0], [0.5 * pitch, 0.866 * pitch], [-0.5 * pitch, 0.866 * pitch]])
    half_sq = 0.5 * np.einsum("ij,ij->i", normals, normals)
    half_lat = 0.25 * pitch
    _, _, d0, d1, d2 = _position_offsets(half_lat, 11, normals)
    lat_t = (half_lat * np.abs(normals).sum(axis=1) * (1.0 + 1e-9) + 1e-9 * half_sq)
    # Points everywhere about the cell, and at its sides +- the positions' reach exactly.
    base = rng.uniform(-1.5, 1.5, size=(400, 3)) * half_sq
    edges = np.repeat(half_sq[None, :], 60, axis=0) * rng.choice([-1.0, 1.0], size=(60, 3))
    edges += rng.choice([-1.0, 0.0, 1.0], size=(60, 3)) * lat_t + rng.normal(0.0, 1e-12, size=(60, 3))
    base = np.ascontiguousarray(np.vstack([base, edges]))
    cnt = np.empty(d0.size)
    weight = rng.uniform(0.5, 1.0, size=base.shape[0])  # each point's pixel response
    _count_inside(base, base.shape[0], d0, d1, d2, *half_sq, lat_t, weight, cnt, np.empty(base.shape[0], np.int64))
    shifted = base[:, None, :] + np.stack([d0, d1, d2], axis=-1)[None, :, :]
    inside = np.all(np.abs(shifted) <= half_sq, axis=-1)
    np.testing.assert_allclose(cnt, weight @ inside, rtol=1e-12)
    assert 0 < inside.sum(axis=0).min() and inside.sum(axis=0).max() < base.shape[0]


def test_each_point_of_a_pixel_counts_by_the_response_to_the_aperture_point_it_sees():
    """lit_fraction against its definition: the response-weighted share of a pixel's points whose
    ray enters the lens, over the weights of all that see an aperture (own or, beyond the rim, a
    neighbour's); a pixel wholly lit stays at 1 whatever the response."""
    model = CameraModel.from_metadata(simulated_camera_metadata(size=480))
    table = build_table_from_model(model, white_coverage(model), rim_px=FIT_TABLE_RIM_PX)
    idx = TableIndex(table)
    ratio = aperture_per_lens_plane(model.optics)
    k_px = np.log(0.5) / table.micro_image_radius_px ** 2  # half the centre's response at the rim
    cells = idx.cells(ratio, k_px)
    flat = idx.cells(ratio)
    k = cells.response_k
    assert k == pytest.approx(np.log(0.5) / table.aperture_radius_m ** 2, rel=1e-9)
    sub = pixel_footprint(7, 1.2) * idx.u_per_px
    r_ap = table.aperture_radius_m
    c = 0.02
    checked = 0
    for u0, v0 in [(0.0, 0.0), (0.55 * r_ap, 0.1 * r_ap), (0.93 * r_ap, -0.2 * r_ap), (-0.3 * r_ap, 0.97 * r_ap)]:
        for sx in np.linspace(-0.6, 0.6, 7) * idx.pitch_m:
            sy = 0.2 * idx.pitch_m
            # Brute force: each point sees its own aperture point or, beyond the rim, a neighbour's.
            num = den = 0.0
            for dx, dy in sub:
                a = np.array([u0 + dx, v0 + dy])
                shift = np.zeros(2)
                if a @ a > cells.r_ap2:
                    seen = [nb for nb in range(6) if np.sum((a + cells.neigh_u[nb]) ** 2) <= cells.r_ap2]
                    if not seen:
                        continue
                    a = a + cells.neigh_u[seen[0]]
                    shift = cells.neigh_s[seen[0]]
                ray = np.array([sx, sy]) + c * a - shift
                w = np.exp(k * (a @ a))
                den += w
                num += w * bool(np.all(np.abs(cells.normals @ ray) <= cells.half_sq))
            f = lit_fraction(u0, v0, 0.0, 0.0, sx, sy, c, cells, sub)
            assert f == pytest.approx(num / den, rel=1e-9, abs=1e-12)
            if 0.05 < f < 0.95:  # partly lit: the response changes the share
                assert abs(f - lit_fraction(u0, v0, 0.0, 0.0, sx, sy, c, flat, sub)) > 1e-3
                checked += 1
    assert checked >= 3
    assert lit_fraction(0.1 * r_ap, 0.0, 0.0, 0.0, 0.0, 0.0, 1e-4, cells, sub) == pytest.approx(1.0)


def test_deblending_drops_a_particle_seen_twice(scene):
    """A second fit of one particle's light is left with nothing of its own once the first is refitted."""
    from analysis.depth.deblend import deblend
    from analysis.depth.refine import RayFitter

    exposure, calibration, table, truth, nn, s_hat, noise = scene
    ratio = aperture_per_lens_plane(calibration.model.optics)
    first = fit_rays(exposure.image, table, s_hat[:, 0], s_hat[:, 1], truth["alpha"], background=noise.background,
                     aperture_per_lens_plane=ratio)
    twice = first.take(np.array([0]))
    pitch = float(np.hypot(*table.basis_m[:, 0]))
    twice = dataclasses.replace(twice, sx_m=twice.sx_m + 0.3 * pitch, alpha=twice.alpha + 0.0015)
    fits = RayFit.concat(first, twice)
    grid = table.grid
    peaks = peaks_at(grid, fits)
    fitter = RayFitter(exposure.image, table, grid, background=noise.background, aperture_per_lens_plane=ratio,
                       alpha_half_range=0.004, coarse=PIPELINE_COARSE, min_intensity=8 * noise.sigma,
                       max_residual=0.35, merge_radius_px=1.5, merge_alpha=0.0026)
    kept, fit = deblend(fitter, peaks, fits)
    assert len(kept) == len(first)  # the copy is gone, every particle stays
    assert np.all(kept.track < len(first))
    assert np.allclose(fit.intensity, first.intensity, rtol=0.15)


def _isolated_particles(size, spacing_pitches, blur_pitches, *, camera=None):
    """Noise-free particles on a square grid ``spacing_pitches`` apart (no overlap), blurred over
    ``blur_pitches`` (signed as ``c``: positive in front of focus), each a little off its lens centre:
    model, fit table, lens-plane positions, ``c`` per particle, particles, raw image."""
    model = CameraModel.from_metadata(simulated_camera_metadata(size=size))
    optics = model.optics
    table = build_table_from_model(model, white_coverage(model), rim_px=FIT_TABLE_RIM_PX)
    pitch = float(np.hypot(*table.basis_m[:, 0]))
    n = blur_pitches.size
    side = int(round(np.sqrt(n)))
    half = 0.5 * spacing_pitches * (side - 1)
    gx, gy = np.meshgrid(np.linspace(-half, half, side), np.linspace(-half, half, side))
    s_hat = np.column_stack([gx.ravel(), gy.ravel()]) * pitch + np.linspace(0.0, 0.45, n)[:, None] * pitch
    c = blur_pitches * optics.lens_pitch_m / optics.aperture_diameter_m
    z = np.asarray(optics.z_of_alpha(1.0 / (1.0 - c)))
    particles = Particles(s_hat[:, 0] * z / optics.exit_pupil_m, s_hat[:, 1] * z / optics.exit_pupil_m, z,
                          np.full(n, 1800.0))
    return model, table, s_hat, c, particles, render_exposure(model, particles, seed=5, noise=False, camera=camera)


def test_depth_scale_of_blurred_particles_is_unbiased():
    """The depth of a particle blurred over a few pitches comes from the size of the small patch
    each lens holds (the lens cell seen through the aperture, scaled by 1/c): a pixel model that
    spreads light wider or narrower than the sensor does scales every such depth. On noise-free
    particles, evenly spaced pixel points put them 1.1 % too far from focus."""
    from analysis.depth.refine import FINE_GRID
    from analysis.simulation.render import particle_truth

    blur = np.linspace(2.0, 3.5, 16) * np.tile([1.0, -1.0], 8)  # signed: behind and in front of focus
    model, table, s_hat, c, particles, image = _isolated_particles(640, 12.0, blur)
    optics = model.optics
    assert np.allclose(particle_truth(model, particles).blur_pitches, np.abs(blur), rtol=1e-3)
    fit = fit_rays(image, table, s_hat[:, 0], s_hat[:, 1], 1.0 / (1.0 - c), background=0.0,
                   aperture_per_lens_plane=aperture_per_lens_plane(optics), fine=FINE_GRID)  # as the pipeline does
    ratio = (1.0 - 1.0 / fit.alpha) / c
    assert np.all(np.abs(ratio - 1.0) < 0.03), ratio  # single fits scatter with the grid's depth step
    assert abs(np.mean(ratio) - 1.0) < 0.005, ratio  # evenly spaced pixel points: 0.011


def test_particles_a_second_stop_cuts_keep_their_depth():
    """Toward the corners a second stop cuts the aperture (cat's-eye micro-images); the devignetted
    samples are then light per unit of what passes it, and a model that lets the whole aperture light
    them took noise-free particles there for nearer focus than they are. Modelled, the stop leaves
    their depth scale as unbiased as the centre's."""
    from analysis.depth.refine import FINE_GRID
    from analysis.simulation.camera_effects import CameraEffects
    from analysis.simulation.realism import Realism

    full = CameraModel.from_metadata(simulated_camera_metadata())
    start, size = 3280 - 360, 320  # a window near the corner, beyond the stop's onset
    lat = full.lattice
    model = dataclasses.replace(full, width=size, height=size, lattice=lat.with_changes(
        origin_x=lat.origin_x - start, origin_y=lat.origin_y - start))
    optics = model.optics
    camera = CameraEffects.build(Realism(vignetting_corner_cut=0.3, vignetting_onset=0.45), serial="A202160042")
    stop = camera.second_stop(model)
    table = build_table_from_model(model, white_coverage(model, camera=camera), rim_px=FIT_TABLE_RIM_PX)
    pitch = float(np.hypot(*table.basis_m[:, 0]))
    centre = table.lens_xy_m.mean(axis=0)
    g = (np.arange(3) - 1) * 9.0 * pitch
    s_hat = np.column_stack([np.repeat(g, 3), np.tile(g, 3)]) + centre + np.linspace(0.0, 0.45, 9)[:, None] * pitch
    blur = np.linspace(2.5, 4.0, 9) * np.tile([1.0, -1.0], 5)[:9]
    c = blur * optics.lens_pitch_m / optics.aperture_diameter_m
    z = np.asarray(optics.z_of_alpha(1.0 / (1.0 - c)))
    particles = Particles(s_hat[:, 0] * z / optics.exit_pupil_m, s_hat[:, 1] * z / optics.exit_pupil_m, z,
                          np.full(9, 1800.0))
    image = render_exposure(model, particles, seed=5, noise=False, camera=camera)
    ratios = {}
    for name, modelled in (("modelled", stop), ("whole aperture", None)):
        fit = fit_rays(image, table, s_hat[:, 0], s_hat[:, 1], 1.0 / (1.0 - c), background=0.0,
                       aperture_per_lens_plane=aperture_per_lens_plane(optics), fine=FINE_GRID, second_stop=modelled)
        ratios[name] = (1.0 - 1.0 / fit.alpha) / c
    assert np.all(np.abs(ratios["modelled"] - 1.0) < 0.03), ratios
    assert abs(np.mean(ratios["modelled"]) - 1.0) < 0.005, ratios
    assert np.mean(ratios["whole aperture"]) < np.mean(ratios["modelled"]) - 0.01, ratios  # the bias it removes


@pytest.mark.parametrize("blur", [1.3, 2.5])
def test_a_saturated_particle_keeps_its_depth(blur):
    """Saturated samples are lower bounds (censored), not values: a particle bright enough to clip
    the ADC is fitted close to the depth an unsaturated one gets, and closer than when its clipped
    samples are taken at their word."""
    from analysis.depth.refine import FINE_GRID

    model = CameraModel.from_metadata(simulated_camera_metadata(size=480))
    optics = model.optics
    table = build_table_from_model(model, white_coverage(model), rim_px=FIT_TABLE_RIM_PX)
    pitch = float(np.hypot(*table.basis_m[:, 0]))
    gx, gy = np.meshgrid(np.arange(-12.0, 13.0, 12.0), np.arange(-12.0, 13.0, 12.0))
    s_hat = np.column_stack([gx.ravel(), gy.ravel()]) * pitch + np.linspace(0.0, 0.4, 9)[:, None] * pitch
    c = blur * np.tile([1.0, -1.0, 1.0], 3)[:9] * optics.lens_pitch_m / optics.aperture_diameter_m
    z = np.asarray(optics.z_of_alpha(1.0 / (1.0 - c)))

    def depth_error(brightness: float, saturation: float) -> float:
        particles = Particles(s_hat[:, 0] * z / optics.exit_pupil_m, s_hat[:, 1] * z / optics.exit_pupil_m, z,
                              np.full(9, brightness))
        image = render_exposure(model, particles, seed=11)
        assert (np.count_nonzero(image >= 4095) > 100) == (brightness > 5000)
        fit = fit_rays(image, table, s_hat[:, 0] + 0.1 * pitch, s_hat[:, 1], 1.0 / (1.0 - c) + 0.0008,
                       background=float(np.median(image) - model.black_level),
                       aperture_per_lens_plane=aperture_per_lens_plane(optics), coarse=PIPELINE_COARSE,
                       fine=FINE_GRID, saturation=saturation)
        return float(np.sqrt(np.mean(((1.0 - 1.0 / fit.alpha - c) / c) ** 2)))  # relative error of the blur

    dim, censored, as_values = depth_error(1800.0, 4095.0), depth_error(14000.0, 4095.0), depth_error(14000.0, 1e9)
    assert censored < 2.0 * dim + 0.005 and censored < 0.8 * as_values, (dim, censored, as_values)


def test_censored_intensity_minimises_the_misfit_with_its_bounds():
    """The intensity of a candidate with saturated samples is the minimum of the squared misfit of
    the others plus each bound's shortfall (checked against a dense search), whatever the mix:
    bounds alone, bounds met by the least-squares intensity, dark samples against bright bounds."""
    rng = np.random.default_rng(4)
    for case in range(300):
        n_free, n_cens = rng.integers(0, 6), rng.integers(1, 6)
        f = rng.uniform(0.02, 1.0, n_free)
        v = rng.normal(rng.choice([0.0, 2000.0]), 300.0, n_free)
        cens_f = rng.uniform(0.0, 1.0, n_cens) * (rng.random(n_cens) < 0.8)
        cens_v = np.full(n_cens, 4000.0)
        s_vf, s_ff, sum_v2 = float(v @ f), float(f @ f), float(v @ v)
        cost, inten = censored_intensity(s_vf, s_ff, sum_v2, cens_v, cens_f, np.empty(n_cens, dtype=bool))
        grid = np.linspace(0.0, 1.5 * max(inten, 1.0) + 5e5 * (s_ff == 0), 200001)
        total = ((v[None, :] - grid[:, None] * f[None, :]) ** 2).sum(1) + (
            np.maximum(cens_v[None, :] - grid[:, None] * cens_f[None, :], 0.0) ** 2).sum(1)
        assert cost == pytest.approx(sum_v2 - 2 * inten * s_vf + inten ** 2 * s_ff
                                     + np.sum(np.maximum(cens_v - inten * cens_f, 0.0) ** 2), rel=1e-9, abs=1e-6)
        assert cost <= total.min() * (1 + 1e-9) + 1e-6, (case, cost, total.min())


@pytest.mark.parametrize("brightness", [4500.0, 9000.0])
def test_fits_beside_a_saturated_particle_do_not_take_its_light(brightness):
    """Fits started a few pitches beside a saturated particle in focus, at depths where a stack
    shows ghosts of it, stay faint: they light a few of its clipped samples slightly and dark
    samples fully, which no intensity explains. Before the censored samples' bounds entered the
    intensity's minimisation, a bound alone set it (tens of thousands of DN, at a relative misfit
    like a particle's), and such a ghost's light hid the particle in the deblend screen."""
    from analysis.depth.refine import FINE_GRID, WIDE_FINE_GRID

    model = CameraModel.from_metadata(simulated_camera_metadata(size=320))
    optics = model.optics
    table = build_table_from_model(model, white_coverage(model), rim_px=FIT_TABLE_RIM_PX)
    pitch = float(np.hypot(*table.basis_m[:, 0]))
    z = float(optics.z_of_alpha(1.0005))
    s = np.array([0.3, 0.2]) * pitch
    particle = Particles(np.array([s[0] * z / optics.exit_pupil_m]), np.array([s[1] * z / optics.exit_pupil_m]),
                         np.array([z]), np.array([brightness]))
    image = render_exposure(model, particle, seed=3)
    assert np.count_nonzero(image >= 4095) > 10
    angle = np.linspace(0.0, 2.0 * np.pi, 12, endpoint=False)
    r = np.tile([1.0, 2.0, 3.0], 4) * pitch
    options = dict(background=float(np.median(image) - model.black_level), alpha_half_range=0.006,
                   aperture_per_lens_plane=aperture_per_lens_plane(optics), coarse=PIPELINE_COARSE)
    own = fit_rays(image, table, s[:1], s[1:], np.array([1.0005]), fine=FINE_GRID, **options)
    ghosts = fit_rays(image, table, s[0] + r * np.cos(angle), s[1] + r * np.sin(angle),
                      np.tile([0.975, 1.03, 0.985, 1.02], 3), fine=WIDE_FINE_GRID, **options)
    assert own.intensity[0] > 0.8 * brightness
    assert np.all(ghosts.intensity < 0.2 * own.intensity[0]), ghosts.intensity


def test_recentring_the_fine_pass_reaches_the_depth_of_particles_under_a_wider_blur():
    """Under a 0.8 px blur (told), the coarse pass of pixel centres reads each lens's blurred spot of
    a particle blurred over 5-8 pitches as a larger one, a depth nearer focus, and the fine pass
    searched only about it; run again about its own result (as the deblend refits do), it gets there."""
    from analysis.depth.deblend import DEBLEND_RECENTRE
    from analysis.depth.refine import COARSE_LATERAL_PITCHES, WIDE_FINE_GRID
    from analysis.simulation.camera_effects import CameraEffects
    from analysis.simulation.realism import Realism

    camera = CameraEffects.build(Realism(blur_px=0.8), serial="A202160042")
    model, table, s_hat, c, _, image = _isolated_particles(1280, 30.0, np.linspace(5.0, 8.0, 9), camera=camera)
    error = {}
    for recentre in (0, DEBLEND_RECENTRE):
        fit = fit_rays(image, table, s_hat[:, 0], s_hat[:, 1], 1.0 / (1.0 - c), background=0.0, blur_px=0.8,
                       aperture_per_lens_plane=aperture_per_lens_plane(model.optics),
                       coarse=PIPELINE_COARSE._replace(depths=17, lateral_pitches=COARSE_LATERAL_PITCHES),
                       fine=WIDE_FINE_GRID, recentre=recentre)
        error[recentre] = fit.alpha - 1.0 / (1.0 - c)
    assert np.mean(error[0]) < -1.2e-4, error  # nearer focus
    assert abs(np.mean(error[DEBLEND_RECENTRE])) < 0.8e-4, error
    assert np.sqrt(np.mean(error[DEBLEND_RECENTRE] ** 2)) < 1.2e-4, error


def test_pixel_points_for_a_wider_blur_keep_the_fitted_light_of_strongly_blurred_particles():
    """A particle blurred over 9-12 pitches lights a patch of about a pixel in each lens, which the
    sensor's blur spreads over the pixels around it. The pixel model must reach as far: with the
    ideal optics' 3 x 3 and 5 x 5 points under a 0.8 px blur, the fits of these noise-free particles
    came out 0.78x as bright as under a 0.3 px blur (0.66x at worst), and misfit their light more.
    :func:`points_per_side` gives the last estimate (``sharpen_blurred``) points enough."""
    from analysis.depth.deblend import DEBLEND_RECENTRE
    from analysis.depth.footprint import points_per_side
    from analysis.depth.refine import COARSE_LATERAL_PITCHES, WIDE_FINE_GRID
    from analysis.simulation.camera_effects import CameraEffects
    from analysis.simulation.realism import Realism

    assert points_per_side(5, 0.3) == points_per_side(5, 0.5) == 5  # the ideal optics' as they were
    blur = np.linspace(9.0, 12.0, 9) * np.tile([1.0, -1.0], 5)[:9]
    fits = {}
    for blur_px in (0.3, 0.8):
        camera = CameraEffects.build(Realism(blur_px=blur_px), serial="A202160042")
        model, table, s_hat, c, _, image = _isolated_particles(1024, 30.0, blur, camera=camera)
        fine = WIDE_FINE_GRID._replace(pixel_points=points_per_side(WIDE_FINE_GRID.pixel_points, blur_px))
        fits[blur_px] = fit_rays(image, table, s_hat[:, 0], s_hat[:, 1], 1.0 / (1.0 - c), background=0.0,
                                 blur_px=blur_px, aperture_per_lens_plane=aperture_per_lens_plane(model.optics),
                                 coarse=PIPELINE_COARSE._replace(lateral_pitches=COARSE_LATERAL_PITCHES),
                                 fine=fine, recentre=DEBLEND_RECENTRE)
    brightness = fits[0.8].intensity / fits[0.3].intensity
    assert np.mean(brightness) > 0.84 and np.min(brightness) > 0.75, brightness  # 3 x 3 / 5 x 5: 0.78, 0.66
    assert np.median(fits[0.8].residual) < 0.008, fits[0.8].residual  # 3 x 3 / 5 x 5: 0.0092


def test_a_strongly_blurred_particles_point_pattern_is_rendered_as_wide_as_the_cameras_blur():
    """A particle blurred over 8-12 pitches lights a patch of about a pixel in each lens, which the
    camera's blur spreads over the pixels around it. The pattern test (:func:`point_pattern`) must
    render the point as wide: with the ideal optics' 3 x 3 pixel points under a 0.8 px blur, these
    noise-free particles' points explained 0.52-0.69 of their lenses' light (0.49-0.82 under the
    ideal 0.5 px) and a source spread over a pitch explained more (ratio 0.64-0.88), so real
    particles far from focus looked like compact glints to the extended test."""
    from analysis.depth.rayfit import point_pattern
    from analysis.simulation.camera_effects import CameraEffects
    from analysis.simulation.realism import Realism

    camera = CameraEffects.build(Realism(blur_px=0.8), serial="A202160042")
    blur = np.linspace(8.0, 12.0, 9) * np.tile([1.0, -1.0], 5)[:9]
    model, table, s_hat, c, _, image = _isolated_particles(1024, 30.0, blur, camera=camera)
    fitter, _, fit = _first_fits(model, table, image, s_hat, 1.0 / (1.0 - c), blur_px=0.8)
    shares = point_pattern(image, table, fit, fitter.blur_radius_m(fit.alpha) + 0.5 * fitter.pitch_m,
                           background=0.0, explained=fitter.render(fit), spread_m=fitter.pitch_m, blur_px=0.8,
                           aperture_per_lens_plane=fitter.aperture_per_lens_plane)
    point, spread = shares.T
    assert np.median(point) > 0.7 and point.min() > 0.65, point  # 3 x 3 points: median 0.60
    assert np.median(point / spread) > 0.9, point / spread  # 3 x 3 points: median 0.75


def _first_fits(model, table, image, s_hat, alpha0, **options):
    """A pipeline-like fitter on a noise-free image, its first fits from ``alpha0`` and their peaks."""
    from analysis.depth.refine import COARSE_LATERAL_PITCHES, RayFitter

    fitter = RayFitter(image, table, table.grid, background=0.0,
                       aperture_per_lens_plane=aperture_per_lens_plane(model.optics), alpha_half_range=0.004,
                       coarse=PIPELINE_COARSE._replace(lateral_pitches=COARSE_LATERAL_PITCHES), min_intensity=100.0,
                       max_residual=0.35, merge_radius_px=1.5, merge_alpha=0.0026, **options)
    first = fitter.fit(s_hat[:, 0], s_hat[:, 1], alpha0)
    return fitter, peaks_at(table.grid, first), first


def test_refitting_crowded_blurred_particles_without_their_neighbours_light():
    """Blurred particles 2 pitches apart share most lenses: fitted together with their neighbours'
    light, their depths are off; :func:`refit_blurred` refits each strongly blurred one with the
    others' light (as their first fits put it) taken off, and only those."""
    from analysis.depth.deblend import refit_blurred

    blur = np.array([4.0, 4.5, 5.0, 4.2, 1.0, 4.8, 4.4, 4.6, 5.2])  # disc diameters; the middle one near focus
    model, table, s_hat, c, _, image = _isolated_particles(640, 2.0, blur)
    truth = 1.0 / (1.0 - c)
    fitter, peaks, first = _first_fits(model, table, image, s_hat, truth)
    n = len(first)
    kept, again = refit_blurred(fitter, peaks, first)
    blurred = fitter.strongly_blurred(first.alpha)
    assert len(kept) == n and blurred.sum() >= 7 and not blurred[4]
    assert again.alpha[4] == first.alpha[4] and np.array_equal(kept.alpha, again.alpha)

    def rms(fit):
        return float(np.sqrt(np.mean((fit.alpha - truth)[blurred] ** 2)))

    assert rms(again) < 0.6 * rms(first), (rms(first), rms(again))
    assert np.all(again.residual[blurred] < 0.5 * first.residual[blurred])
    # The same refit with the neighbours' light left in does not get there.
    plain = fitter.fit(first.sx_m, first.sy_m, first.alpha)
    assert rms(again) < 0.6 * rms(plain), (rms(plain), rms(again))


def test_the_last_estimate_of_blurred_particles_is_sharper():
    """Under a 0.8 px blur (told), the fine pass's tempered mean at the deblending temperature stays
    near the centre of its window where the cost is flat: strongly blurred particles are left nearer
    focus. :func:`sharpen_blurred` weighs the candidates more sharply, moves them toward their depth,
    and keeps every fit."""
    from analysis.depth.deblend import refit_blurred, sharpen_blurred
    from analysis.simulation.camera_effects import CameraEffects
    from analysis.simulation.realism import Realism

    camera = CameraEffects.build(Realism(blur_px=0.8), serial="A202160042")
    blur = np.linspace(4.0, 10.0, 16) * np.tile([1.0, -1.0], 8)
    model, table, s_hat, c, _, image = _isolated_particles(1280, 24.0, blur, camera=camera)
    fitter, peaks, first = _first_fits(model, table, image, s_hat, 1.0 / (1.0 - c), blur_px=0.8)
    n = len(first)
    peaks, refit = refit_blurred(fitter, peaks, first)
    kept, sharp = sharpen_blurred(fitter, peaks, refit)
    assert len(kept) == len(sharp) == n

    def scale_error(fit):  # fitted over true blur, less one
        return (1.0 - 1.0 / fit.alpha) / c - 1.0

    before, after = scale_error(refit), scale_error(sharp)
    assert np.mean(before) < -0.005, before  # nearer focus (noise-free: -0.008)
    assert abs(np.mean(after)) < 0.6 * abs(np.mean(before)), (before, after)
    assert np.sqrt(np.mean(after ** 2)) < 0.8 * np.sqrt(np.mean(before ** 2)), (before, after)


def test_the_last_estimate_of_strongly_blurred_particles_is_unbiased_under_a_wide_blur():
    """Under a 1.2 px blur (told), a particle blurred over 10-16 pitches lights a sub-pixel patch per
    lens; the cost rises more slowly toward focus (larger patches) than away from it, and the tempered
    mean of the candidates' depths left these noise-free particles 3.2 % of their blur nearer focus
    (RMS 4.4 %). The last estimate takes the vertex of the depth profile's parabola instead (1.0 %,
    RMS 1.4 %)."""
    from analysis.depth.deblend import refit_blurred, sharpen_blurred
    from analysis.simulation.camera_effects import CameraEffects
    from analysis.simulation.realism import Realism

    camera = CameraEffects.build(Realism(blur_px=1.2), serial="A202160042")
    blur = np.linspace(10.0, 16.0, 16) * np.tile([1.0, -1.0], 8)
    model, _, s_hat, c, _, image = _isolated_particles(1600, 36.0, blur, camera=camera)
    table = build_table_from_model(model, white_coverage(model, camera=camera), rim_px=FIT_TABLE_RIM_PX)
    fitter, peaks, first = _first_fits(model, table, image, s_hat, 1.0 / (1.0 - c), blur_px=1.2)
    peaks, refit = refit_blurred(fitter, peaks, first)
    _, sharp = sharpen_blurred(fitter, peaks, refit)
    error = (1.0 - 1.0 / sharp.alpha) / c - 1.0  # fitted over true blur, less one
    assert len(sharp) == blur.size
    assert abs(np.mean(error)) < 0.016 and np.sqrt(np.mean(error ** 2)) < 0.025, error


def test_a_candidate_faint_in_the_coarse_pass_keeps_its_coarse_fit():
    """``coarse_floor``: a candidate whose coarse pass finds no more light than that skips the fine
    pass (it keeps the coarse result, and stays under the floor); the others fit as before."""
    blur = np.linspace(2.0, 6.0, 9)
    model, table, s_hat, c, particles, _ = _isolated_particles(640, 12.0, blur)
    brightness = np.where(np.arange(blur.size) % 2 == 0, 1800.0, 60.0)  # every other one faint
    image = render_exposure(model, dataclasses.replace(particles, brightness_dn=brightness), seed=5, noise=False)
    options = dict(background=0.0, aperture_per_lens_plane=aperture_per_lens_plane(model.optics))
    full = fit_rays(image, table, s_hat[:, 0], s_hat[:, 1], 1.0 / (1.0 - c), **options)
    floor = 0.5 * float(np.min(full.intensity[brightness > 100]))
    screened = fit_rays(image, table, s_hat[:, 0], s_hat[:, 1], 1.0 / (1.0 - c), coarse_floor=floor, **options)
    faint = brightness < 100
    assert np.all(full.intensity[faint] > 0) and np.all(full.intensity[faint] < floor)
    for name in ("sx_m", "sy_m", "alpha", "intensity", "residual"):
        assert np.array_equal(getattr(screened, name)[~faint], getattr(full, name)[~faint]), name
    assert np.all(screened.intensity[faint] <= floor)
    assert not np.allclose(screened.alpha[faint], full.alpha[faint], rtol=0, atol=1e-7)  # no fine pass


def test_sample_weights_follow_the_noise_of_devignetted_samples():
    """A devignetted sample's noise is its raw noise over its white weight w: with read noise alone
    its weight grows as w^2, with shot noise of the light behind it as w / level; a full-weight
    sample at the typical level counts once, and without a noise model all count alike."""
    w = np.array([1.0, 0.5, 0.1, 1.0])
    level = np.array([40.0, 40.0, 40.0, 160.0])
    read = SampleNoise(read=4.0, shot=0.0, typical_level=40.0).root_weights(w, level)
    np.testing.assert_allclose(read**2, w**2)
    shot = SampleNoise(read=0.0, shot=0.7, typical_level=40.0).root_weights(w, level)
    np.testing.assert_allclose(shot**2, w * 40.0 / level)
    both = SampleNoise(read=4.0, shot=0.7, typical_level=40.0).root_weights(w, level)
    assert both[0] == pytest.approx(1.0) and np.all(np.diff(both[:3]) < 0)
    np.testing.assert_array_equal(SampleNoise(0.0, 0.0, 40.0).root_weights(w, level), np.ones(4))


def test_a_fit_weighed_by_noise_reports_the_unweighted_residual():
    """Weighed by its samples' noise, a fit of one blurred particle lands on its depth as the
    unweighted fit does, and reports the residual as an unweighted fit would at its result (the
    gates on it were chosen so): near the unweighted fit's own, not the smaller weighted one."""
    model = CameraModel.from_metadata(simulated_camera_metadata(size=480))
    optics = model.optics
    table = build_table_from_model(model, white_coverage(model), rim_px=FIT_TABLE_RIM_PX)
    s_hat = 0.13 * table.basis_m[:, 0] + 0.07 * table.basis_m[:, 1]
    c = 3.0 * optics.lens_pitch_m / optics.aperture_diameter_m
    alpha = 1.0 / (1.0 - c)
    z = float(optics.z_of_alpha(alpha))
    one = Particles(np.array([s_hat[0] * z / optics.exit_pupil_m]), np.array([s_hat[1] * z / optics.exit_pupil_m]),
                    np.array([z]), np.array([1800.0]))
    image = render_exposure(model, one, seed=3)
    args = dict(background=0.0, aperture_per_lens_plane=aperture_per_lens_plane(optics))
    start = (np.array([s_hat[0]]), np.array([s_hat[1]]), np.array([alpha * 1.0005]))
    plain = fit_rays(image, table, *start, **args)
    weighed = fit_rays(image, table, *start, **args, noise=SampleNoise(read=4.0, shot=0.7, typical_level=0.0))
    assert abs(weighed.alpha[0] - alpha) < 2e-4 and abs(plain.alpha[0] - alpha) < 2e-4
    assert 0.8 < weighed.residual[0] / plain.residual[0] < 1.25
