"""The pipeline on exposures with what a real camera in a real chamber adds (small sensor crops)."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from analysis.cache import Cache
from analysis.calibration.calibrate import calibrate
from analysis.camera.model import CameraModel
from analysis.formats.exposure import Exposure
from analysis.depth.refine import WIDE_BLUR_PITCHES
from analysis.formats.whites import WhiteImage
from analysis.pipeline.depth_range import FIT_MARGIN_STEPS
from analysis.pipeline.params import PipelineParams
from analysis.pipeline.process import process
from analysis.simulation.camera import simulated_camera_metadata, simulated_private_metadata
from analysis.simulation.chamber import ChamberLight, ExtendedSource
from analysis.simulation.render import in_view, particle_truth, render_exposure, render_white_image
from analysis.simulation.scenarios import Particles, make_scenario
from analysis.simulation.scoring import match, mean_nn_distance, score

SIZE = 1024


def _process(particles: Particles, *, chamber: ChamberLight | None = None, params: PipelineParams | None = None,
             seed: int = 1, noise: bool = True):
    """Render ``particles`` (and ``chamber``'s light) on a centred crop, calibrate from its white
    image, process with the defaults; the truth of the particles in view."""
    meta = simulated_camera_metadata(size=SIZE)
    model = CameraModel.from_metadata(meta)
    private = simulated_private_metadata()
    white = WhiteImage.from_image("MOD_0001", render_white_image(model, seed=seed + 100), meta, private)
    calibration = calibrate(white)
    image = render_exposure(model, particles, seed=seed, background_dn=40.0, chamber=chamber, noise=noise)
    result = process(Exposure(image, meta, private), calibration, params, cache=Cache())
    truth = particle_truth(model, particles)
    shown = in_view(model, truth)
    columns = {"X": particles.x_mm[shown], "Y": particles.y_mm[shown], "Z": particles.z_mm[shown],
               "alpha": truth.alpha[shown], "x": truth.x_px[shown], "y": truth.y_px[shown],
               "blur_pitches": truth.blur_pitches[shown]}
    return result, columns, model


def _all_real(result, particles: Particles, *, within_mm: float = 0.5) -> bool:
    """Whether every particle found lies within ``within_mm`` of one of ``particles``."""
    true = np.column_stack([particles.x_mm, particles.y_mm, particles.z_mm])
    found = np.column_stack([result.particles["X"], result.particles["Y"], result.particles["Z"]])
    return all(np.min(np.linalg.norm(true - f, axis=1)) < within_mm for f in found)


def test_a_reflected_laser_band_yields_no_particle_and_hides_none():
    """A band of laser light reflected by an electrode 6 mm behind focus, out of focus, across the
    layer's image: no particle on it, the particles in front of it still found."""
    layer = make_scenario("tilted-layer", 3).particles
    band = ExtendedSource(kind="band", z_mm=66.0, x_mm=0.0, y_mm=0.4, sigma_mm=0.2, level_dn=2000.0,
                          angle_rad=0.02, amplitude=0.25, period_mm=2.5)
    result, truth, model = _process(layer, chamber=ChamberLight(sources=(band,)))
    # The band does reach this crop, far above the glow.
    cx, cy, reach = band.footprint_px(model)
    assert 0 < cy < SIZE and truth["X"].size >= 6
    s = score(result.particles, truth, nn_mm=mean_nn_distance(truth["X"], truth["Y"], truth["Z"]))
    assert s.recall >= 0.95, s
    # Every particle found is a particle of the layer (some partly off the crop: not in the truth).
    assert _all_real(result, layer)
    assert np.all(result.particles["leftover"] < 0.5)
    # The band's shot noise makes candidates; they are dropped before any fit, for the noise, and
    # all of them lie on the band.
    noise = result.rejected["reason"] == "noise"
    assert noise.sum() >= 10
    where = particle_truth(model, Particles(*(result.rejected[c][noise] for c in "XYZ"), np.zeros(noise.sum())))
    assert np.all(ChamberLight(sources=(band,)).on_reflection(model, where.x_px, where.y_px))
    # Each is listed once, though the second pass finds many of them again.
    where = np.column_stack([result.rejected[c][noise] for c in ("x", "y", "alpha")])
    assert len(np.unique(where, axis=0)) == len(where)


def test_particles_beyond_the_papers_alpha_range_are_found_by_default():
    """A 7 mm ball at focus reaches beyond 0.987 ... 1.013 in alpha: found by default (the range comes
    from the exposure), lost and reported when the user fixes that range."""
    ball = make_scenario("ball", 2).particles
    scale = 7.0 / 4.0  # the scenario's 4 mm ball, grown to 7 mm about its centre
    centre = np.array([ball.x_mm.mean(), ball.y_mm.mean(), ball.z_mm.mean()])
    grown = Particles(centre[0] + (ball.x_mm - centre[0]) * scale, centre[1] + (ball.y_mm - centre[1]) * scale,
                      centre[2] + (ball.z_mm - centre[2]) * scale, ball.brightness_dn)
    result, truth, _ = _process(grown)
    outside = (truth["alpha"] < 0.987) | (truth["alpha"] > 1.013)
    assert outside.sum() >= 3
    nn = mean_nn_distance(truth["X"], truth["Y"], truth["Z"])
    s = score(result.particles, truth, nn_mm=nn)
    assert s.recall >= 0.95 and _all_real(result, grown), s
    # Each particle outside the old range has a found particle within 0.5 mm.
    found = np.column_stack([result.particles["X"], result.particles["Y"], result.particles["Z"]])
    for x, y, z in zip(truth["X"][outside], truth["Y"][outside], truth["Z"][outside]):
        assert np.min(np.linalg.norm(found - [x, y, z], axis=1)) < 0.5
    fixed, _, _ = _process(grown, params=PipelineParams(alpha_min=0.987, alpha_max=1.013))
    assert len(fixed) < len(result)
    assert np.count_nonzero(fixed.rejected["reason"] == "edge_of_range") >= 1


def test_particles_beside_a_glint_are_kept_and_the_glint_yields_none():
    """Bright out-of-focus glints 5 mm behind the particles, each 0.2 mm beside one of them: the
    glints' light fills the margin around those particles but not their own blur disks, so they are
    no extended light; no particle is made of a glint's light."""
    gx, gy = np.meshgrid([-1.2, 0.0, 1.2], [-1.2, 0.0, 1.2])
    z = 59.0 + np.random.default_rng(2).uniform(-1.5, 1.5, gx.size)
    grid = Particles(gx.ravel(), gy.ravel(), z, np.full(gx.size, 1800.0))
    glints = tuple(ExtendedSource(kind="glint", z_mm=64.0, x_mm=float(x + 0.2), y_mm=float(y), sigma_mm=0.1,
                                  level_dn=2500.0) for x, y in zip(gx.ravel()[::2], gy.ravel()[::2]))
    result, truth, _ = _process(grid, chamber=ChamberLight(sources=glints))
    assert truth["X"].size == 9
    s = score(result.particles, truth, nn_mm=mean_nn_distance(truth["X"], truth["Y"], truth["Z"]))
    # Judged by the light around them alone, four of the nine were dropped with the glints.
    assert s.n_matched >= 7 and _all_real(result, grid), s
    assert np.count_nonzero(result.rejected["reason"] == "extended") > 0


@pytest.mark.parametrize("z_mm, at_least", [(59.0, 9), (57.5, 7)])
def test_particles_on_compact_glints_are_kept_and_the_glints_yield_none(z_mm, at_least):
    """Compact glints (0.1 mm) 5-6 mm behind the particles, each on one particle's line of sight:
    the glint's light fills the particle's own blur disk, so the light there is not all explained,
    but within its lenses it follows the particle's point pattern (1.8-9 times better than the
    same light spread over a source a pitch across). The glints' own fits follow a pitch-wide source
    at least as well as a point and stay dropped. Before, judged by the unexplained shares alone, 3
    of the 9 particles at 59 mm were kept and none at 57.5 mm."""
    gx, gy = np.meshgrid([-1.2, 0.0, 1.2], [-1.2, 0.0, 1.2])
    z = z_mm + np.random.default_rng(2).uniform(-0.5, 0.5, gx.size)
    grid = Particles(gx.ravel(), gy.ravel(), z, np.full(gx.size, 1500.0))
    glints = tuple(ExtendedSource(kind="glint", z_mm=64.0, x_mm=float(x * 64.0 / zz), y_mm=float(y * 64.0 / zz),
                                  sigma_mm=0.1, level_dn=2500.0) for x, y, zz in zip(gx.ravel(), gy.ravel(), z))
    result, truth, _ = _process(grid, chamber=ChamberLight(sources=glints))
    assert truth["X"].size == 9
    s = score(result.particles, truth, nn_mm=mean_nn_distance(truth["X"], truth["Y"], truth["Z"]))
    assert s.n_matched >= at_least and _all_real(result, grid), s
    assert np.count_nonzero(result.rejected["reason"] == "extended") >= 9


@pytest.mark.parametrize("glints", [True, False])
def test_a_compact_glint_far_in_front_of_the_particles_yields_no_particle(glints):
    """A compact glint (0.08 mm) 8 mm in front of particles 1-2 mm in front of focus, as held-out
    cloud seed 21 had: its blurred disk covers the particles' range of depths and was tiled by
    point fits at depths beyond that range (14 here), each leaving too little of its light
    unexplained to count as extended. It is now found and taken off first; without that
    (``glints=False``), fits may leave the range found from the exposure by a few steps only."""
    gx, gy = np.meshgrid([-1.2, 0.0, 1.2], [-1.2, 0.0, 1.2])
    z = 57.5 + np.random.default_rng(2).uniform(-1.0, 1.0, gx.size)
    grid = Particles(gx.ravel(), gy.ravel(), z, np.full(gx.size, 1500.0))
    glint = ExtendedSource(kind="glint", z_mm=49.8, x_mm=0.6, y_mm=0.6, sigma_mm=0.08, level_dn=2400.0)
    result, truth, model = _process(grid, chamber=ChamberLight(sources=(glint,)), params=PipelineParams(glints=glints))
    assert truth["X"].size == 9
    assert float(model.optics.alpha_of_z(49.8)) > result.alphas[-1] + 0.02  # far beyond the range
    s = score(result.particles, truth, nn_mm=mean_nn_distance(truth["X"], truth["Y"], truth["Z"]))
    assert s.n_matched >= 8 and _all_real(result, grid), s
    if glints:
        taken = [w for w in result.warnings if "glint(s) far out of focus" in w]
        assert len(taken) == 1 and taken[0].startswith("1 glint")
        alpha = float(taken[0].split("alpha ")[1].split(")")[0])
        assert abs(alpha - float(model.optics.alpha_of_z(49.8))) < 0.01
    else:
        assert np.count_nonzero(result.rejected["reason"] == "outside_range") > 0
    # No stage after the first fits (deblending, the refits of blurred particles) takes a fit
    # farther out: held-out seed 26 kept three of a glint's tiling fits that they moved.
    margin = FIT_MARGIN_STEPS * float(result.alphas[1] - result.alphas[0])
    assert np.all(np.abs(result.particles["alpha"] - np.clip(result.particles["alpha"], result.alphas[0],
                                                               result.alphas[-1])) <= margin + 1e-12)


def test_a_compact_glint_far_behind_a_cluster_does_not_set_the_range_and_yields_no_particle():
    """A compact glint (0.09 mm) 6 mm behind 16 particles, within the survey's reach, fits as a point
    there (fresh seed 108): taken as the range's end, it tiled into four false particles. It lies
    far in depth from all the particles, so it is left out of the range and reported."""
    gx, gy = np.meshgrid(np.linspace(-1.5, 1.5, 4), np.linspace(-1.5, 1.5, 4))
    z = 59.5 + np.random.default_rng(3).uniform(-0.7, 0.7, gx.size)
    grid = Particles(gx.ravel(), gy.ravel(), z, np.full(gx.size, 1500.0))
    glint = ExtendedSource(kind="glint", z_mm=66.0, x_mm=0.5, y_mm=0.5, sigma_mm=0.09, level_dn=2300.0)
    result, truth, model = _process(grid, chamber=ChamberLight(sources=(glint,)))
    assert truth["X"].size == 16
    s = score(result.particles, truth, nn_mm=mean_nn_distance(truth["X"], truth["Y"], truth["Z"]))
    assert s.n_matched == 16 and _all_real(result, grid), s
    lone = result.rejected["alpha"][result.rejected["reason"] == "apart"]
    glint_alpha = float(model.optics.alpha_of_z(66.0))
    assert lone.size == 1 and abs(lone[0] - glint_alpha) < 0.003
    assert result.alphas[0] > glint_alpha + 0.01
    assert any("left out of the range" in w for w in result.warnings)


def _pairs_on_lines_of_sight(seed: int, partner_dn: float, *, centre_mm: float = 59.5,
                             apart_mm: tuple[float, float] = (1.0, 2.0), in_front: bool = False):
    """Nine pairs on one line of sight each, ``apart_mm`` apart in depth (the partner on either
    side, or ``in_front``), the bright one of 5000 DN about ``centre_mm`` and its partner of
    ``partner_dn``, processed: the pairs, their score."""
    gx, gy = np.meshgrid([-1.2, 0.0, 1.2], [-1.2, 0.0, 1.2])
    rng = np.random.default_rng(seed)
    z1 = centre_mm + rng.uniform(-0.5, 0.5, gx.size)
    side = -1.0 if in_front else rng.choice([-1, 1], gx.size)
    z2 = z1 + rng.uniform(*apart_mm, gx.size) * side
    x1, y1 = gx.ravel(), gy.ravel()
    pairs = Particles(np.r_[x1, x1 * z2 / z1], np.r_[y1, y1 * z2 / z1], np.r_[z1, z2],
                      np.r_[np.full(9, 5000.0), np.full(9, partner_dn)])
    result, truth, _ = _process(pairs)
    assert truth["X"].size == 18
    return pairs, result, score(result.particles, truth, nn_mm=mean_nn_distance(truth["X"], truth["Y"], truth["Z"]))


def test_a_faint_partner_on_a_bright_particles_line_of_sight_is_found():
    """Nine pairs on one line of sight each, the partner with 0.3 of the light (brightness spreads
    10x and more): its tight fit, far brighter than what the bright one's model leaves unexplained,
    is evidence of a particle, though it is under a probe's share of the light."""
    pairs, result, s = _pairs_on_lines_of_sight(3, 1500.0)
    # With a fixed share of the brighter one's light as the only evidence: 9 of 18.
    assert s.n_matched >= 15 and _all_real(result, pairs), s


def test_a_partner_with_a_seventh_of_the_light_is_found_where_its_light_converges():
    """As above with 0.15 of the light: too faint to outshine the bright one's left-over light,
    but its own light follows a point's pattern within the lenses
    (:func:`analysis.depth.quality.converges`), which that left-over light does not. 12 of 18
    found by the earlier tests alone (seeds 3-5 of this scene: 11-12), with this one 15 (14-15);
    never a false one."""
    pairs, result, s = _pairs_on_lines_of_sight(4, 750.0)
    assert s.n_matched >= 14 and _all_real(result, pairs), s


def test_a_faint_blurred_partner_is_found_where_its_light_converges_as_a_point_more_than_spread():
    """Partners with 0.12 of the light, 2-3 mm in front (blurred over 8-10 pitches): blurred that
    wide, a point's pattern and the same light spread over a pitch look alike, and real partners'
    light follows the point only a little better (on realistic shadowing scenes 1.1-1.4 times).
    Held to the 1.5 times asked of a fit on extended light, 14 of 18 were found."""
    pairs, result, s = _pairs_on_lines_of_sight(4, 600.0, centre_mm=59.8, apart_mm=(2.0, 3.0), in_front=True)
    assert s.n_matched >= 16 and _all_real(result, pairs), s


@functools.lru_cache(maxsize=1)
def _blurred_camera():
    """The camera of the blurred cloud's crops (0.8 px blur), its calibration, and one cache of
    look-up tables for all of them (the crops share the calibration)."""
    from analysis.simulation.camera_effects import CameraEffects
    from analysis.simulation.realism import Realism

    meta = simulated_camera_metadata(size=SIZE)
    model = CameraModel.from_metadata(meta)
    private = simulated_private_metadata()
    camera = CameraEffects.build(Realism(blur_px=0.8), serial="A202160042")
    white = WhiteImage.from_image("MOD_0001", render_white_image(model, seed=101, camera=camera), meta, private)
    return meta, private, model, camera, calibrate(white), Cache()


@functools.lru_cache(maxsize=None)
def _blurred_cloud(seed: int) -> tuple[Exposure, dict[str, np.ndarray], float, Particles]:
    """A crop of the 400-particle cloud in front of focus through a 0.8 px blur with a 10x brightness
    spread: the exposure, the true particles in view, their spacing, and every particle of the
    cloud (those just outside the crop light its edge)."""
    meta, private, model, camera, _, _ = _blurred_camera()
    particles = make_scenario("cloud", seed, brightness_spread=10.0).particles
    image = render_exposure(model, particles, seed=seed, background_dn=40.0, camera=camera)
    shown = in_view(model, particle_truth(model, particles))
    columns = {"X": particles.x_mm[shown], "Y": particles.y_mm[shown], "Z": particles.z_mm[shown]}
    return (Exposure(image, meta, private), columns, mean_nn_distance(columns["X"], columns["Y"], columns["Z"]),
            particles)


def _found_and_false(seed: int, params: PipelineParams | None = None) -> tuple[int, int]:
    """On the blurred cloud's crop ``seed``: particles in view that were found, and found particles
    that are none of the cloud's (in view or not): on a crop, a particle just outside it lights its
    edge, and finding it is no error (on these crops those are nearly all the particles that match
    none in view)."""
    exposure, in_view_, nn, everyone = _blurred_cloud(seed)
    _, _, _, _, calibration, cache = _blurred_camera()
    found = process(exposure, calibration, params, cache=cache).particles
    every = {"X": everyone.x_mm, "Y": everyone.y_mm, "Z": everyone.z_mm}
    return score(found, in_view_, nn_mm=nn).n_matched, len(found["X"]) - match(found, every, nn_mm=nn)[0].size


@functools.lru_cache(maxsize=None)
def _found_and_false_by_default(seed: int) -> tuple[int, int]:
    """:func:`_found_and_false` with every default, run once per crop for the tests that compare a
    rule with its default (call it only while the rules are at their defaults)."""
    return _found_and_false(seed)


@pytest.mark.parametrize("seed", [6, 8])
def test_the_late_pass_finds_blurred_particles_the_first_passes_missed(seed):
    """The blurred cloud's faint particles blurred over many pitches among brighter ones make no
    peak of their own at first. The pass after deblending finds some (7-10 more on these crops),
    and its new fits are deblended with the rest, so few false ones come with them (one each; at
    most one per three real ones asserted). Seed 6 also once stopped the first fits (a point whose
    last gathered lens had no sample)."""
    without, false_without = _found_and_false(seed, PipelineParams(late_pass=False))
    with_late, false_with = _found_and_false_by_default(seed)
    gained = with_late - without
    assert gained >= 2, (with_late, without)
    assert false_with <= false_without + gained // 3, (false_with, false_without, gained)


@pytest.mark.parametrize("seed", [3, 8])
def test_the_late_pass_keeps_blurred_particles_whose_pattern_the_noise_hides(seed, monkeypatch):
    """The late pass's new fits blurred over many pitches that fit well need not show a point's
    pattern within their lenses (:data:`analysis.pipeline.passes.THIN_PATTERN_PITCHES`): on these
    crops of the blurred cloud that keeps 6-7 more real particles (asserted: 2), with up to two
    false ones more (asserted: one per three real at most). Measured with the rule and with it
    turned off."""
    from analysis.pipeline import passes

    with_rule, false_with = _found_and_false_by_default(seed)
    monkeypatch.setattr(passes, "THIN_PATTERN_PITCHES", np.inf)
    without, false_without = _found_and_false(seed)
    gained = with_rule - without
    assert gained >= 2, (with_rule, without)
    # A wrong particle is worse than a missing one: at most one false one more per three real ones.
    assert false_with <= false_without + gained // 3, (false_with, false_without, gained)


def test_the_late_pass_finds_faint_blurred_particles_under_the_first_cut(monkeypatch):
    """Where the fits' light is taken off, the late pass cuts the residual's samples at one noise
    sigma, not three (:data:`analysis.pipeline.passes.RESIDUAL_NOISE_SIGMAS`): a faint particle
    blurred over many pitches puts a few DN in each lens, and only so do its lenses' samples reach
    its refocused spot. On these crops of the blurred cloud that finds 4 more real particles (3 and
    1), with one false one more (asserted: 3 more real, at most one false per three). Measured with
    the cut and with the usual one. (Before the lenses lit by particles stopped setting the
    background sample by sample, the first passes found fewer of these and the cut added 10.)"""
    from analysis.pipeline import passes

    gained = more_false = 0
    for seed in (3, 6):
        lower, false_lower = _found_and_false_by_default(seed)
        monkeypatch.setattr(passes, "RESIDUAL_NOISE_SIGMAS", PipelineParams().noise_sigmas)
        usual, false_usual = _found_and_false(seed)
        monkeypatch.undo()
        gained += lower - usual
        more_false += false_lower - false_usual
    assert gained >= 3 and more_false <= gained // 3, (gained, more_false)


def test_noise_weights_refit_the_blurred_particles_and_keep_every_one():
    """``weigh_noise``: the last refit of the strongly blurred particles weighs each sample by its
    noise. Through ideal optics it keeps every real particle, adds none, and moves the blurred
    ones' depths, for a depth error no worse than the unweighted one's. (Unweighted, one strongly
    blurred particle of a shadowing pair here gets a third fit between the partners.)"""
    ball = make_scenario("ball", 3).particles
    off = Particles(ball.x_mm, ball.y_mm, ball.z_mm - ball.z_mm.mean() + 57.4, ball.brightness_dn)
    plain, truth, _ = _process(off)
    weighed, _, _ = _process(off, params=PipelineParams(weigh_noise=True))
    nn = mean_nn_distance(truth["X"], truth["Y"], truth["Z"])
    s_plain, s_weighed = score(plain.particles, truth, nn_mm=nn), score(weighed.particles, truth, nn_mm=nn)
    assert s_plain.n_true >= 20 and s_weighed.n_matched == s_plain.n_matched == s_plain.n_true
    assert len(weighed) <= len(plain)
    # The same true particle's depth in both, by the truth's order.
    (rows_p, cols_p), (rows_w, cols_w) = (match(r.particles, truth, nn_mm=nn) for r in (plain, weighed))
    z_plain, z_weighed = np.empty(cols_p.size), np.empty(cols_w.size)
    z_plain[cols_p], z_weighed[cols_w] = plain.particles["Z"][rows_p], weighed.particles["Z"][rows_w]
    moved = np.abs(z_weighed - z_plain) > 1e-3
    # Strongly blurred before the refit (its radius over WIDE_BLUR_PITCHES; the refit moves it a little).
    blur = np.empty(cols_p.size)
    blur[cols_p] = plain.particles["blur_pitches"][rows_p]
    blurred = blur > 0.9 * 2 * WIDE_BLUR_PITCHES
    assert moved.sum() >= 3 and not np.any(moved & ~blurred)
    assert s_weighed.depth_abs_rms_over_nn <= s_plain.depth_abs_rms_over_nn


def test_isolated_particles_blurred_over_eleven_pitches_are_not_split():
    """Nine particles 1.2 mm apart, blurred over 10-12 pitches, through ideal optics, noise-free:
    nine found. With renders of 3 x 3 points per pixel, the one at (0, -1.2) got a second fit
    0.43 mm nearer with a fifth of its light and five times the others' misfit, which the
    line-of-sight tests kept: the coarse render of its sub-pixel patches left light that a second
    fit explained (the split particles of ideal optics)."""
    gx, gy = np.meshgrid([-1.2, 0.0, 1.2], [-1.2, 0.0, 1.2])
    grid = Particles(gx.ravel(), gy.ravel(), 56.0 + np.linspace(-0.2, 0.2, 9), np.full(9, 1500.0))
    result, truth, _ = _process(grid, noise=False)
    assert truth["X"].size == 9
    s = score(result.particles, truth, nn_mm=mean_nn_distance(truth["X"], truth["Y"], truth["Z"]))
    assert s.n_matched == 9 and len(result) == 9, s


def _blur_and_rim_camera():
    """A crop's metadata, model and private metadata, and a camera with a 0.8 px blur and a response
    falling to 0.75 at the micro-image rims, calibrated from its own white image."""
    from analysis.simulation.camera_effects import CameraEffects
    from analysis.simulation.realism import Realism

    meta = simulated_camera_metadata(size=SIZE)
    model = CameraModel.from_metadata(meta)
    private = simulated_private_metadata()
    camera = CameraEffects.build(Realism(blur_px=0.8, rim_response=0.75), serial="A202160042")
    calibration = calibrate(WhiteImage.from_image("MOD_0001", render_white_image(model, seed=101, camera=camera),
                                                  meta, private))
    return meta, model, private, camera, calibration


def test_a_pixel_response_falling_toward_the_rim_under_a_wide_blur_biases_no_depth():
    """Nine isolated particles, noise-free, blurred over 4-6 pitches through a 0.8 px blur and a
    response falling to 0.75 at the micro-image rims: the depth fit models the response the white
    image shows, so their depths come out as unbiased as through ideal optics. Counting a pixel's
    points alike put them 15-17 um (+2 % of a cloud's spacing) too far from focus."""
    meta, model, private, camera, calibration = _blur_and_rim_camera()
    assert calibration.profile is not None and calibration.profile.rim_response == pytest.approx(0.75, abs=0.02)
    gx, gy = np.meshgrid([-1.2, 0.0, 1.2], [-1.2, 0.0, 1.2])
    errors = []
    for z in (57.0, 58.0):
        grid = Particles(gx.ravel(), gy.ravel(), z + np.linspace(-0.2, 0.2, 9), np.full(9, 1500.0))
        image = render_exposure(model, grid, seed=1, background_dn=40.0, camera=camera, noise=False)
        found = process(Exposure(image, meta, private), calibration, cache=Cache()).particles
        assert len(found["X"]) == 9
        for x, y, z_true in zip(grid.x_mm, grid.y_mm, grid.z_mm):
            k = np.argmin(np.hypot(found["X"] - x, found["Y"] - y))
            assert np.hypot(found["X"][k] - x, found["Y"][k] - y) < 0.05
            errors.append(found["Z"][k] - z_true)
    assert abs(np.mean(errors)) < 0.008, np.mean(errors)  # mm


def test_the_layers_prior_also_refits_particles_whose_pixels_pin_their_depth_as_well():
    """A tilted layer near focus through a 0.8 px blur with the rim response and a 12x brightness
    spread: a particle whose light spills from one lens into the next knows its depth about as
    well as its neighbours' surface does, and weighing both must beat the pixels alone. Refitted
    only where the prior was the narrower, such a particle of this crop stayed 0.125 NN off
    (depth RMS 4.2 % of NN; with both, 6 % and 2.3 %)."""
    from analysis.simulation.scoring import single_lens

    meta, model, private, camera, calibration = _blur_and_rim_camera()
    particles = make_scenario("tilted-layer", 1, varied=True, brightness_spread=12.0).particles
    image = render_exposure(model, particles, seed=1, background_dn=40.0, camera=camera)
    truth = particle_truth(model, particles)
    shown = in_view(model, truth)
    columns = {"X": particles.x_mm[shown], "Y": particles.y_mm[shown], "Z": particles.z_mm[shown],
               "x": truth.x_px[shown], "y": truth.y_px[shown], "blur_pitches": truth.blur_pitches[shown]}
    nn = mean_nn_distance(columns["X"], columns["Y"], columns["Z"])
    found = process(Exposure(image, meta, private), calibration, cache=Cache()).particles
    rows, cols = match(found, columns, nn_mm=nn)
    assert cols.size == shown.sum() >= 12
    dz = (np.asarray(found["Z"])[rows] - columns["Z"][cols]) / nn
    more_lenses = ~single_lens(columns, model.lattice)[cols]
    assert more_lenses.sum() >= 10
    assert np.sqrt(np.mean(dz**2)) < 0.03
    assert np.max(np.abs(dz[more_lenses])) < 0.09
    # The table tells which depths leaned on the neighbours' surface: on a layer, most of them.
    prior_std = np.asarray(found["prior_std"])
    assert np.mean(np.isfinite(prior_std)) > 0.5 and np.all(prior_std[np.isfinite(prior_std)] > 0)
