"""Glints far out of focus: found at their depth, taken off the raw image, the particles' light kept."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from analysis.camera.model import CameraModel
from analysis.depth.quality import patterned
from analysis.detection.rejections import Rejections
from analysis.lightfield.background import estimate_background
from analysis.lightfield.glints import MIN_SIGMA_PITCHES, find_glints, without_glints
from analysis.lightfield.samples import background_and_noise
from analysis.lightfield.table import build_table_from_model
from analysis.pipeline.hidden_glints import glints_behind, refit_in_glints
from analysis.pipeline.tables import FIT_TABLE_RIM_PX
from analysis.simulation.camera import simulated_camera_metadata
from analysis.simulation.chamber import ChamberLight, ExtendedSource
from analysis.simulation.render import render_exposure, white_coverage
from analysis.simulation.scenarios import Particles

from line_of_sight_scenes import line_of_sight_scene, one_fit, peaks_at

GLINT_ALPHA = 1.04
#: The particles' range in c = 1 - 1/alpha: about focus, the glint well beyond it.
PARTICLE_C = (1 - 1 / 0.995, 1 - 1 / 1.005)


@pytest.fixture(scope="module")
def scene():
    """A particle near focus in the disk of a glint (0.15 mm, 2500 DN) far in front of it, and the
    same particle alone, on a 512 px crop of the simulated F01."""
    model = CameraModel.from_metadata(simulated_camera_metadata(size=512))
    optics = model.optics
    table = build_table_from_model(model, white_coverage(model), rim_px=FIT_TABLE_RIM_PX)
    glint = ExtendedSource(kind="glint", z_mm=float(optics.z_of_alpha(GLINT_ALPHA)), x_mm=0.2, y_mm=-0.1,
                           sigma_mm=0.15, level_dn=2500.0)
    particle = Particles(np.array([0.1]), np.array([0.05]), np.array([float(optics.z_of_alpha(1.0005))]),
                         np.array([2000.0]))
    with_glint = render_exposure(model, particle, seed=5, chamber=ChamberLight(sources=(glint,)))
    alone = render_exposure(model, particle, seed=5)
    return table, with_glint, alone


def _glints(table, image, particle_c=PARTICLE_C):
    noise = background_and_noise(image, table)[1]
    level = estimate_background(image, table, noise_dn=noise).per_lens(table)
    return find_glints(image, table, level, particle_c=particle_c, saturation=4095.0)


def test_a_glint_far_out_of_focus_is_found_and_taken_off_and_the_particle_kept(scene):
    table, image, alone = scene
    glints = _glints(table, image)
    assert len(glints) == 1
    pitch = float(np.hypot(*table.basis_m[:, 0]))
    assert abs(glints[0].alpha - GLINT_ALPHA) < 0.002
    assert glints[0].sigma_m >= MIN_SIGMA_PITCHES * pitch
    clean = without_glints(image, table, glints, saturation=4095.0).astype(float)
    glint_light = image.astype(float) - alone
    lit = glint_light > 20
    before = np.sqrt(np.mean(glint_light[lit] ** 2))
    after = np.sqrt(np.mean((clean - alone)[lit] ** 2))
    assert after < 0.25 * before
    # The particle's own light stays (none of it is taken for the glint's), and of the glint's
    # light on its pixels less than half is left.
    particle = alone - np.median(alone) > 200
    assert particle.sum() > 20
    left = np.sum(clean[particle] - alone[particle])
    assert -0.02 * np.sum(alone[particle] - np.median(alone)) < left < 0.5 * np.sum(glint_light[particle])


def test_no_glint_is_found_where_there_is_none_or_within_the_particles_range(scene):
    table, image, alone = scene
    assert _glints(table, alone) == []
    c = 1 - 1 / GLINT_ALPHA
    assert _glints(table, image, particle_c=(PARTICLE_C[0], c + 0.01)) == []


def test_a_glint_seen_through_the_fits_is_found_there_and_its_false_fit_dropped():
    """A compact glint (held-out seed 148's: 0.16 mm, 1425 DN, at alpha 1.043) beyond the
    particles' range, seen where the glint map would show a crowd's light: a fit started on the glint's
    light at the particles' depth is blurred thin and shows no point's pattern; the glint search
    started there finds the glint, and refitted with the glint's light taken off, the false fit
    goes (as ``glint``) and the particle beside it is found where it is."""
    model = CameraModel.from_metadata(simulated_camera_metadata(size=512))
    optics = model.optics
    table = build_table_from_model(model, white_coverage(model), rim_px=FIT_TABLE_RIM_PX)
    pitch = float(np.hypot(*table.basis_m[:, 0]))
    glint_s = np.array([-2.0, 1.0]) * pitch
    z_glint = float(optics.z_of_alpha(1.043))
    glint = ExtendedSource(kind="glint", z_mm=z_glint, x_mm=glint_s[0] * z_glint / optics.exit_pupil_m,
                           y_mm=glint_s[1] * z_glint / optics.exit_pupil_m, sigma_mm=0.16, level_dn=1425.0)
    particle_s = glint_s + np.array([6.0, -3.0]) * pitch
    z = float(optics.z_of_alpha(1.02))
    particle = Particles(np.array([particle_s[0] * z / optics.exit_pupil_m]),
                         np.array([particle_s[1] * z / optics.exit_pupil_m]), np.array([z]), np.array([1500.0]))
    image = render_exposure(model, particle, seed=7, chamber=ChamberLight(sources=(glint,)))
    # The particle's fit and one on the glint's light at the particles' depth, each with the
    # other's light taken off, over the glow as the pipeline estimates it.
    noise = background_and_noise(image, table)[1]
    glow = estimate_background(image, table, noise_dn=noise)
    level = glow.per_lens(table)
    fitter = dataclasses.replace(one_fit(model, table, particle_s, image, 1.02)[0], background=glow.per_sample(table))
    both = fitter.fit(np.array([particle_s[0], glint_s[0]]), np.array([particle_s[1], glint_s[1]]), np.full(2, 1.02))
    both = fitter.fit(both.sx_m, both.sy_m, both.alpha, subtract=fitter.render(both), own=both)
    assert fitter.acceptable(both).all()
    assert not patterned(fitter, both, fitter.render(both))[1]

    limits = (0.995, 1.025)
    found = glints_behind(fitter, both, level, limits, [])
    assert len(found) == 1 and abs(found[0].alpha - 1.043) < 0.003
    assert glints_behind(fitter, both, level, limits, found) == []  # a glint already known is not found again

    rejected = Rejections()
    clean = without_glints(image, table, found, saturation=4095.0)
    # As the pipeline does: the glow behind the fits estimated again without the glint's light.
    background = estimate_background(clean, table, noise_dn=noise).per_sample(table)
    fitter = dataclasses.replace(fitter, image=clean, background=background, rejected=rejected)
    peaks, kept = refit_in_glints(fitter, peaks_at(table.grid, both), both, found, max_residual=0.25)
    assert len(kept) == 1 and abs(kept.alpha[0] - 1.02) < 0.001
    assert np.hypot(kept.sx_m[0] - particle_s[0], kept.sy_m[0] - particle_s[1]) < 0.2 * pitch
    assert rejected.table()["reason"].tolist() == ["glint"]


def test_no_glint_is_found_behind_a_blurred_particle_alone():
    model, table, s_hat, image = line_of_sight_scene([1.02], [1500.0])
    fitter, _, fit = one_fit(model, table, s_hat, image, 1.02)
    noise = background_and_noise(image, table)[1]
    level = estimate_background(image, table, noise_dn=noise).per_lens(table)
    assert glints_behind(fitter, fit, level, (0.995, 1.025), []) == []
