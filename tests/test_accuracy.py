"""What the exposure can tell: particles whose pixels leave the depth open, and the floor they set."""

from __future__ import annotations

import numpy as np

from analysis.simulation.scoring import (depth_floor, floor_errors, floor_split, match, pixel_limited_alpha,
                                         single_lens)
from analysis.camera.model import CameraModel
from analysis.simulation.scenarios import Particles
from analysis.simulation.camera import simulated_camera_metadata
from analysis.simulation.render import particle_truth, render_exposure


def model(size: int = 160) -> CameraModel:
    return CameraModel.from_metadata(simulated_camera_metadata(size=size))


def particle_on_lens(m: CameraModel, alpha: float, offset_px: tuple[float, float] = (0.0, 0.0)) -> Particles:
    """One particle whose chief ray meets the MLA at the centre lens (+ offset), sharp at ``alpha``."""
    lat, optics = m.lattice, m.optics
    i, j = lat.nearest(np.array([m.width / 2]), np.array([m.height / 2]))
    cx, cy = lat.centre(i, j)
    z = float(optics.z_of_alpha(alpha))
    scale = optics.exit_pupil_m / z * optics.projection_factor / optics.pixel_pitch_m  # px per mm of X
    x_mm = (cx[0] + offset_px[0] - lat.origin_x) / scale
    y_mm = (cy[0] + offset_px[1] - lat.origin_y) / scale
    return Particles(np.array([x_mm]), np.array([y_mm]), np.array([z]), np.array([1500.0]))


def blur_alpha(m: CameraModel, blur_pitches: float, sign: float) -> float:
    """The alpha at which a particle's blur disk is ``blur_pitches`` across, in front of or behind focus."""
    c = sign * blur_pitches * m.optics.lens_pitch_m / m.optics.aperture_diameter_m  # c = 1 - 1/alpha
    return 1.0 / (1.0 - c)


def test_blur_inside_one_lens_looks_the_same_in_front_of_and_behind_focus():
    """The claim behind the floor: the raw pixels of such a particle do not depend on its depth."""
    m = model()
    images = [render_exposure(m, particle_on_lens(m, blur_alpha(m, 0.6, s)), seed=1, noise=False)
              for s in (-1.0, 1.0)]
    sharp = render_exposure(m, particle_on_lens(m, 1.0), seed=1, noise=False)
    lit = sharp > np.median(sharp) + 50
    assert lit.sum() > 40  # one micro-image
    for image in images:
        assert np.abs(image.astype(int) - sharp.astype(int)).max() <= 2  # rounding of the ray sampling
    # A blur of 1.6 pitches spills into the neighbours: the pixels do tell, and the check can fail.
    wide = render_exposure(m, particle_on_lens(m, blur_alpha(m, 1.6, 1.0)), seed=1, noise=False)
    assert np.abs(wide.astype(int) - sharp.astype(int)).max() > 100


def test_single_lens_follows_position_and_blur():
    m = model()
    cases = [((0.0, 0.0), 0.6, True), ((0.0, 0.0), 1.2, False), ((4.0, 0.0), 0.3, False), ((2.0, 0.0), 0.3, True)]
    for offset, blur, expected in cases:
        p = particle_on_lens(m, blur_alpha(m, blur, 1.0), offset)
        t = particle_truth(m, p)
        truth = {"x": t.x_px, "y": t.y_px, "blur_pitches": t.blur_pitches}
        assert bool(single_lens(truth, m.lattice)[0]) is expected, (offset, blur)


def truth_of(m: CameraModel, cases: list[tuple[float, float, tuple[float, float]]]) -> tuple[dict, Particles]:
    """Truth columns of particles ``(blur_pitches, sign of the defocus, offset_px from the lens centre)``."""
    ps = [particle_on_lens(m, blur_alpha(m, b, s), off) for b, s, off in cases]
    p = Particles(*(np.concatenate([getattr(q, f) for q in ps]) for f in ("x_mm", "y_mm", "z_mm", "brightness_dn")))
    t = particle_truth(m, p)
    return {"x": t.x_px, "y": t.y_px, "blur_pitches": t.blur_pitches, "alpha": t.alpha, "Z": p.z_mm}, p


def test_pixels_pin_the_depth_only_where_the_blur_spans_a_cell():
    m = model()
    truth, _ = truth_of(m, [(0.6, 1.0, (0, 0)), (0.6, -1.0, (0, 0)),     # inside one cell
                            (1.3, 1.0, (0, 0)), (1.3, -1.0, (0, 0)),     # over all six corners
                            (0.2, 1.0, (4.5, 0)), (0.2, -1.0, (4.5, 0))])  # over one edge
    c_true = 1 - 1 / truth["alpha"]
    c_best = 1 - 1 / pixel_limited_alpha(truth, m.lattice)
    # Inside one cell: both signs and every size alike, so the middle (focus).
    assert np.all(np.abs(c_best[:2]) < 0.05 * np.abs(c_true[:2]))
    # Six corners in the disk: pinned (to the radius grid's step).
    assert np.allclose(c_best[2:4], c_true[2:4], rtol=0.03)
    # One edge: the side of focus is known (the chord's side), but a particle nearer the edge and
    # sharper lays the same chord, and so does one farther in and more blurred, up to where the
    # disk meets the next edges: the best estimate lies well beyond this particle's own blur.
    assert np.all(np.sign(c_best[4:]) == np.sign(c_true[4:]))
    assert np.all(np.abs(c_best[4:]) > 1.5 * np.abs(c_true[4:]))


def test_depth_floor_is_the_error_of_the_best_estimate():
    m = model()
    truth, p = truth_of(m, [(0.6, 1.0, (0, 0)), (0.6, -1.0, (0, 0)), (3.0, 1.0, (0, 0)), (0.2, 1.0, (4.5, 0))])
    count, floor = depth_floor(truth, m.lattice, nn_mm=1.0)
    assert count == 2  # the edge-crossing one lights two lenses
    slope = np.polyfit(truth["alpha"], p.z_mm, 1)[0]
    err = (pixel_limited_alpha(truth, m.lattice) - truth["alpha"]) * slope
    assert err[2] == 0.0  # wide blurs are pinned
    assert np.isclose(floor, np.sqrt(np.mean(err**2)))
    # The edge-crossing one adds its own share to the one-lens particles' (placed at focus).
    assert abs(err[3]) > 0.5 * abs(truth["alpha"][3] - 1.0) * slope
    one_lens = (truth["alpha"][:2] - 1.0) * slope
    assert floor > np.sqrt(np.sum(one_lens**2) / 4)


def test_floor_split_judges_one_lens_particles_by_their_floor_and_the_others_apart():
    m = model()
    truth, p = truth_of(m, [(0.6, 1.0, (0, 0)), (3.0, -1.0, (0, 0)), (0.2, 1.0, (4.5, 0))])
    truth.update(X=p.x_mm, Y=p.y_mm)
    floor = floor_errors(truth, m.lattice)
    assert floor[0] != 0.0 and floor[1] == 0.0  # the wide one is pinned
    assert 0.01 < abs(floor[2]) < 0.1  # the one over a cell edge is open, by 1-10 % of a 1 mm NN
    # Found: the one-lens particle twice as far from its truth as its best estimate, the wide one
    # 0.01 mm off, the edge-crossing one 0.02 mm.
    dz = np.array([-2.0 * floor[0], 0.01, 0.02])
    found = {"X": p.x_mm, "Y": p.y_mm, "Z": p.z_mm + dz}
    s = floor_split(found, truth, m.lattice, nn_mm=1.0)
    assert (s.n_one_lens, s.n_rest, s.n_open) == (1, 2, 1)
    assert np.isclose(s.floor_ss, floor[0] ** 2)
    assert np.isclose(s.one_lens_ss, 4.0 * floor[0] ** 2)
    assert np.isclose(s.rest_ss, 1e-4 + 4e-4)
    assert np.isclose(s.open_ss, 4e-4) and np.isclose(s.open_floor_ss, floor[2] ** 2)
    # Whether a floor error counts as open is judged in NN: with a 10 mm NN it is pinned.
    assert floor_split(found, truth, m.lattice, nn_mm=10.0).n_open == 0


def test_a_particle_found_at_its_floor_beyond_the_match_is_counted_apart():
    m = model()
    truth, p = truth_of(m, [(0.6, 1.0, (0, 0)), (3.0, -1.0, (0, 0))])
    truth.update(X=p.x_mm, Y=p.y_mm)
    floor = floor_errors(truth, m.lattice)
    nn = abs(floor[0])  # the one-lens particle's best estimate lies beyond the match (0.5 NN)
    # Found where its pixels put it (its floor), and the pinned one as far off: both beyond the
    # match, only the first at its floor.
    found = {"X": p.x_mm, "Y": p.y_mm, "Z": p.z_mm + np.array([floor[0], floor[0]])}
    assert match(found, truth, nn_mm=nn)[0].size == 0
    assert floor_split(found, truth, m.lattice, nn_mm=nn).n_at_floor == 1
    # Twice its floor's error, or across from it by more than the match allows: not at its floor.
    assert floor_split({**found, "Z": p.z_mm + 2.0 * floor[0]}, truth, m.lattice, nn_mm=nn).n_at_floor == 0
    assert floor_split({**found, "X": p.x_mm + nn}, truth, m.lattice, nn_mm=nn).n_at_floor == 0
