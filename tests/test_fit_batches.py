"""The depth stages' batching: rendering skips only dark samples, fits in chunks and by blur width
give what one call of the fit gives."""

from __future__ import annotations

import numpy as np
import pytest

import analysis.depth.refine as refine
from analysis.camera.model import CameraModel
from analysis.lightfield.table import build_table_from_model
from analysis.pipeline.tables import FIT_TABLE_RIM_PX
from analysis.depth.deblend import seen_twice
from analysis.depth.footprint import pixel_footprint
from analysis.depth.rayfit import RENDER_POINTS, FitGrid, RayFit, aperture_per_lens_plane, fit_rays, render_fits
from analysis.depth.render_kernels import lit_fraction
from analysis.depth.refine import COARSE_TEMPERATURE, FINE_GRID, WIDE_FINE_GRID, RayFitter
from analysis.depth.table_index import TableIndex
from analysis.simulation.scenarios import Particles
from analysis.simulation.camera import simulated_camera_metadata
from analysis.simulation.render import render_exposure, white_coverage

# The pipeline's coarse pass (analysis.pipeline.process builds it from PipelineParams' defaults).
COARSE = FitGrid(depths=17, lateral_pitches=0.4, positions=5, pixel_points=1, temperature=COARSE_TEMPERATURE)
# Blurs (radius on the MLA, lens pitches; negative: behind focus) from one lens to a wide disk.
BLURS = np.array([0.3, -0.8, 1.4, -2.6, 3.5, 6.0])


@pytest.fixture(scope="module")
def scene():
    model = CameraModel.from_metadata(simulated_camera_metadata(size=480))
    optics = model.optics
    table = build_table_from_model(model, white_coverage(model), rim_px=FIT_TABLE_RIM_PX)
    idx = TableIndex(table)
    # Spread out along a line through the centre, off the lens centres.
    t = np.linspace(-0.6, 0.6, BLURS.size)
    s_hat = np.column_stack([t * 40 * idx.pitch_m + 0.13 * idx.pitch_m, 0.3 * t * 40 * idx.pitch_m - 0.07 * idx.pitch_m])
    c = BLURS * optics.lens_pitch_m / (0.5 * optics.aperture_diameter_m)
    z = np.array([float(optics.z_of_alpha(1.0 / (1.0 - ci))) for ci in c])
    particles = Particles(s_hat[:, 0] * z / optics.exit_pupil_m, s_hat[:, 1] * z / optics.exit_pupil_m, z,
                          np.full(BLURS.size, 1800.0))
    image = render_exposure(model, particles, seed=5)
    alpha = 1.0 / (1.0 - c)
    return model, table, image, s_hat, alpha


def test_render_matches_the_model_sample_by_sample(scene):
    model, table, _, s_hat, alpha = scene
    ratio = aperture_per_lens_plane(model.optics)
    idx = TableIndex(table)
    fit = RayFit(sx_m=s_hat[:, 0], sy_m=s_hat[:, 1], alpha=alpha, intensity=np.linspace(500.0, 900.0, alpha.size),
                 n_lit=np.zeros(alpha.size, np.int64), residual=np.zeros(alpha.size), alpha_spread=np.zeros(alpha.size))
    out = render_fits(table, fit, aperture_per_lens_plane=ratio)
    # Every sample within reach of each particle, through the model one sample at a time.
    reach = np.abs(1.0 - 1.0 / alpha) * idx.radius_m + 1.8 * idx.pitch_m
    g = idx.gather(fit.sx_m, fit.sy_m, reach)
    lens_ptr, sample_ptr, ids, centres = g.lens_ptr, g.sample_ptr, g.ids, g.centres
    uv = idx.uv(ids)
    sub = pixel_footprint(RENDER_POINTS, 0.5) * idx.u_per_px
    cells = idx.cells(ratio)
    expected = np.zeros(table.n_samples, dtype=np.float32)
    for p in range(len(fit)):
        c = 1.0 - 1.0 / alpha[p]
        for lens in range(lens_ptr[p], lens_ptr[p + 1]):
            for j in range(sample_ptr[lens], sample_ptr[lens + 1]):
                f = lit_fraction(uv[j, 0], uv[j, 1], centres[lens, 0], centres[lens, 1], fit.sx_m[p], fit.sy_m[p], c,
                                 cells, sub)
                if f > 0.0:
                    expected[ids[j]] += fit.intensity[p] * f
    # Each particle lights about a micro-image's worth of samples, rim samples (crosstalk) included.
    assert np.count_nonzero(expected) > 20 * alpha.size
    np.testing.assert_array_equal(out, expected)


def _fitter(model, table, image) -> RayFitter:
    return RayFitter(image, table, table.grid, background=0.0, aperture_per_lens_plane=aperture_per_lens_plane(model.optics),
                     alpha_half_range=0.004, coarse=COARSE, min_intensity=10.0, max_residual=0.35,
                     merge_radius_px=1.5, merge_alpha=0.0026)


def _same(a: RayFit, b: RayFit) -> None:
    for name in RayFit.__dataclass_fields__:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_fits_in_chunks_and_by_blur_equal_single_calls(scene, monkeypatch):
    model, table, image, s_hat, alpha = scene
    fitter = _fitter(model, table, image)
    pitch = float(np.hypot(*table.basis_m[:, 0]))
    # Starts a little off the truth; wide blurs interleaved with narrow ones, so the rows must be put back in order.
    sx, sy, a = s_hat[:, 0] + 0.1 * pitch, s_hat[:, 1] - 0.05 * pitch, alpha + 0.0007
    monkeypatch.setattr(refine, "FIT_CHUNK", 2)
    got = fitter.fit(sx, sy, a)
    wide = np.abs(BLURS) > refine.WIDE_BLUR_PITCHES  # the start's 0.0007 in alpha moves a blur by ~0.2 pitch
    assert wide.any() and (~wide).any()
    args = dict(background=0.0, aperture_per_lens_plane=fitter.aperture_per_lens_plane, alpha_half_range=0.004,
                coarse=COARSE)
    for rows, grid in ((np.flatnonzero(~wide), FINE_GRID), (np.flatnonzero(wide), WIDE_FINE_GRID)):
        one = fit_rays(image, table, sx[rows], sy[rows], a[rows], fine=grid, **args)
        _same(got.take(rows), one)
    # The fits found the particles (the comparison is not one of empty fits).
    assert np.all(got.intensity > 100.0)
    # An explicit grid applies to all, in chunks too.
    _same(fitter.fit(sx, sy, a, fine=FINE_GRID), fit_rays(image, table, sx, sy, a, fine=FINE_GRID, **args))


def test_render_in_chunks_equals_one_call(scene, monkeypatch):
    model, table, image, s_hat, alpha = scene
    fitter = _fitter(model, table, image)
    fit = fitter.fit(s_hat[:, 0], s_hat[:, 1], alpha)
    whole = render_fits(table, fit, aperture_per_lens_plane=fitter.aperture_per_lens_plane)
    monkeypatch.setattr(refine, "FIT_CHUNK", 4)
    np.testing.assert_array_equal(fitter.render(fit), whole)
    assert np.count_nonzero(whole) > 20 * len(fit)


def test_the_fitter_fits_and_renders_with_its_blur(scene):
    """``RayFitter.blur_px`` (the calibration's estimate) reaches every fit and render it makes."""
    from dataclasses import replace

    model, table, image, s_hat, alpha = scene
    fitter = replace(_fitter(model, table, image), blur_px=1.1)
    args = dict(background=0.0, aperture_per_lens_plane=fitter.aperture_per_lens_plane, alpha_half_range=0.004,
                coarse=COARSE, fine=FINE_GRID)
    got = fitter.fit(s_hat[:, 0], s_hat[:, 1], alpha, fine=FINE_GRID)
    _same(got, fit_rays(image, table, s_hat[:, 0], s_hat[:, 1], alpha, blur_px=1.1, **args))
    assert not np.array_equal(got.alpha, fit_rays(image, table, s_hat[:, 0], s_hat[:, 1], alpha, **args).alpha)
    np.testing.assert_array_equal(fitter.render(got), render_fits(table, got, blur_px=1.1,
                                                                  aperture_per_lens_plane=fitter.aperture_per_lens_plane))
    assert not np.array_equal(fitter.render(got), render_fits(table, got,
                                                              aperture_per_lens_plane=fitter.aperture_per_lens_plane))


def test_screen_drops_a_second_fit_of_one_particle_and_only_what_the_full_refit_drops(scene):
    model, table, image, s_hat, alpha = scene
    fitter = _fitter(model, table, image)
    fit = fitter.fit(s_hat[:, 0], s_hat[:, 1], alpha)
    assert np.all(fit.intensity > 100.0)
    pitch = float(np.hypot(*table.basis_m[:, 0]))
    for k in (2, BLURS.size - 1):  # a blur of about a pitch, and the widest
        copy = fit.take(np.array([k]))
        copy = RayFit(**{**{n: getattr(copy, n) for n in RayFit.__dataclass_fields__},
                         "sx_m": copy.sx_m + 0.3 * pitch, "alpha": copy.alpha + 0.0015})
        both = RayFit.concat(fit, copy)
        twice = seen_twice(fitter, both)
        full = fitter.fit(both.sx_m, both.sy_m, both.alpha, subtract=fitter.render(both), own=both)
        kept = (full.intensity > fitter.min_intensity) & (full.residual <= fitter.max_residual)
        assert not (twice & kept).any(), (k, twice, kept)
        if k == 2:
            assert twice[-1] and not twice[:-1].any(), twice


def test_a_refit_keeps_the_depth_prior_its_fit_was_made_with(scene):
    """Where one lens holds a particle's light its depth comes from its prior; the refits after the
    prior stage (a second deblending round, the last sharpening at the profile's vertex) refit that
    fit and must keep its prior, not fall back on the pixels alone."""
    model, table, image, s_hat, alpha = scene
    fitter = _fitter(model, table, image)
    free = fitter.fit(s_hat[:, 0], s_hat[:, 1], alpha)
    prior_alpha, prior_sigma = np.full(alpha.size, np.nan), np.full(alpha.size, np.nan)
    # The first particle is blurred over 0.3 lens pitches: half that blur, on the same side of
    # focus, fits its pixels as well; a narrow prior there decides.
    prior_alpha[0], prior_sigma[0] = 1.0 / (1.0 - 0.5 * (1.0 - 1.0 / alpha[0])), 2e-5
    off = abs(free.alpha[0] - prior_alpha[0])
    assert off > 10 * prior_sigma[0]
    fit = fitter.fit(s_hat[:, 0], s_hat[:, 1], alpha, prior_alpha=prior_alpha, prior_sigma=prior_sigma)
    assert abs(fit.alpha[0] - prior_alpha[0]) < 0.2 * off
    for fine in (FINE_GRID, FINE_GRID._replace(vertex=True)):
        again = fitter.fit(fit.sx_m, fit.sy_m, fit.alpha, subtract=fitter.render(fit), own=fit, fine=fine)
        np.testing.assert_array_equal(again.prior_alpha, prior_alpha)
        np.testing.assert_array_equal(again.prior_sigma, prior_sigma)
        assert abs(again.alpha[0] - prior_alpha[0]) < 0.2 * off, fine
