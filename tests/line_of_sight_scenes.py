"""Small scenes for the depth fit's tests: particles on one chief ray (shadowing pairs), glints,
and fits of them as the pipeline's stages make them."""

from __future__ import annotations

import numpy as np

from analysis.camera.model import CameraModel
from analysis.depth.rayfit import FitGrid, aperture_per_lens_plane
from analysis.depth.refine import COARSE_TEMPERATURE
from analysis.lightfield.table import build_table_from_model
from analysis.pipeline.tables import FIT_TABLE_RIM_PX
from analysis.simulation.camera import simulated_camera_metadata
from analysis.simulation.render import render_exposure, white_coverage
from analysis.simulation.scenarios import Particles

# fit_rays' default coarse pass with 17 depths, and the pipeline's (its defaults' 5 positions per side).
COARSE = FitGrid(depths=17, lateral_pitches=0.4, positions=3, pixel_points=1, temperature=COARSE_TEMPERATURE)
PIPELINE_COARSE = COARSE._replace(positions=5)


def peaks_at(grid, fit):
    """Peaks standing for ``fit``'s particles (one track each), at their fitted places."""
    from analysis.detection.curves import Peaks

    n = len(fit)
    x, y = grid.to_pixels(fit.sx_m, fit.sy_m)
    return Peaks(track=np.arange(n), alpha=fit.alpha, x=np.atleast_1d(x).astype(float),
                 y=np.atleast_1d(y).astype(float), peak_height=np.ones(n), peak_width=np.ones(n),
                 residual=fit.residual, prominence=np.ones(n))


def line_of_sight_scene(alphas, brightness, across_pitches=None):
    """Particles on one chief ray (a shadowing pair when two), rendered on a small simulated sensor;
    with ``across_pitches``, each moved that many lens pitches across the rows of lenses from it."""
    model = CameraModel.from_metadata(simulated_camera_metadata(size=320))
    optics = model.optics
    table = build_table_from_model(model, white_coverage(model), rim_px=FIT_TABLE_RIM_PX)
    s_hat = 0.2 * table.basis_m[:, 0] + 0.1 * table.basis_m[:, 1]
    row = table.basis_m[:, 0]
    across = np.array([row[1], -row[0]]) * np.asarray(across_pitches if across_pitches is not None else
                                                      np.zeros(len(alphas)), float)[:, None]
    z = np.array([float(optics.z_of_alpha(a)) for a in alphas])
    ps = Particles((s_hat[0] + across[:, 0]) * z / optics.exit_pupil_m,
                   (s_hat[1] + across[:, 1]) * z / optics.exit_pupil_m, z, np.asarray(brightness, float))
    return model, table, s_hat, render_exposure(model, ps, seed=5)


def one_fit(model, table, s_hat, image, alpha0):
    from analysis.depth.refine import RayFitter

    ratio = aperture_per_lens_plane(model.optics)
    background = float(np.median((image.astype(float) - table.black_level)))
    fitter = RayFitter(image, table, table.grid, background=background, aperture_per_lens_plane=ratio,
                       alpha_half_range=0.004, coarse=PIPELINE_COARSE, min_intensity=100.0,
                       max_residual=0.35, merge_radius_px=1.5, merge_alpha=0.0026)
    fit = fitter.fit(np.array([s_hat[0]]), np.array([s_hat[1]]), np.array([alpha0]))
    return fitter, peaks_at(table.grid, fit), fit


def pair_fits(alphas, truth_alphas, brightness):
    """Two fits started at ``alphas`` on one chief ray, each refitted twice with the other's light
    taken off (as the deblend refits them), on a rendering of particles at ``truth_alphas``."""
    model, table, s_hat, image = line_of_sight_scene(truth_alphas, brightness)
    fitter, _, _ = one_fit(model, table, s_hat, image, alphas[0])
    n = len(alphas)
    fit = fitter.fit(np.full(n, s_hat[0]), np.full(n, s_hat[1]), np.asarray(alphas, float),
                     alpha_half_range=0.0005)
    for _ in range(2):
        fit = fitter.fit(fit.sx_m, fit.sy_m, fit.alpha, subtract=fitter.render(fit), own=fit,
                         alpha_half_range=0.0005)
    return fitter, fit


def glint_image(model, s_hat, alpha, level_dn=3300.0):
    """A glint 0.27 mm across (as held-out seed 10's) on the chief ray ``s_hat``, at the depth of
    ``alpha``, alone on the sensor of :func:`line_of_sight_scene`."""
    from analysis.simulation.chamber import ChamberLight, ExtendedSource

    z = float(model.optics.z_of_alpha(alpha))
    glint = ExtendedSource(kind="glint", z_mm=z, x_mm=s_hat[0] * z / model.optics.exit_pupil_m,
                           y_mm=s_hat[1] * z / model.optics.exit_pupil_m, sigma_mm=0.27, level_dn=level_dn)
    return render_exposure(model, Particles(*(np.zeros(0),) * 4), seed=5, chamber=ChamberLight(sources=(glint,)))
