"""Glints far out of focus: found at their depth, taken off the raw image, the particles' light kept."""

from __future__ import annotations

import numpy as np
import pytest

from analysis.camera.model import CameraModel
from analysis.lightfield.background import estimate_background
from analysis.lightfield.glints import MIN_SIGMA_PITCHES, find_glints, without_glints
from analysis.lightfield.samples import background_and_noise
from analysis.lightfield.table import build_table_from_model
from analysis.pipeline.tables import FIT_TABLE_RIM_PX
from analysis.simulation.camera import simulated_camera_metadata
from analysis.simulation.chamber import ChamberLight, ExtendedSource
from analysis.simulation.render import render_exposure, white_coverage
from analysis.simulation.scenarios import Particles

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
