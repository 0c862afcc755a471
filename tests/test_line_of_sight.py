"""Particles on one line of sight: splitting a fit that holds two, telling a second particle from
one particle's light seen twice, and light that does not converge to a point (glints, reflections)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from line_of_sight_scenes import glint_image, line_of_sight_scene, one_fit, pair_fits, peaks_at


def test_a_fit_holding_two_particles_on_one_line_of_sight_is_split():
    from analysis.depth.deblend import split_shared

    truth = np.array([0.99810, 1.00297])  # a pair one fit took for one particle (shadowing seed 5)
    model, table, s_hat, image = line_of_sight_scene(truth, [1985.0, 1900.0])
    fitter, peaks, fit = one_fit(model, table, s_hat, image, 1.0023)
    assert len(fit) == 1 and fit.intensity[0] > 0
    split, split_fit = split_shared(fitter, peaks, fit, shadow_probe=0.0065, bright=0.5, misfit=0.5)
    assert len(split) == 2
    assert np.allclose(np.sort(split_fit.alpha), truth, atol=4e-4)
    assert np.all(split_fit.residual < fit.residual)


@pytest.mark.parametrize("truth, brightness", [
    ([0.99805, 1.00018], [2116.0, 1446.0]),  # held-out ideal ball 144's lost pair
    ([0.99750, 1.00020], [2500.0, 1200.0]),
])
def test_a_partner_in_focus_that_one_fit_took_in_is_split_off_by_its_own_lens(truth, brightness):
    """One fit of a particle blurred over about a pitch takes in the light of a partner in focus in
    front of it, and fits well: split, the host fits no better (its misfit was low already) and the
    two lie within the merge distance in depth, but the pair explains the partner's lens many times
    better than the one fit did."""
    from analysis.depth.deblend import split_shared

    model, table, s_hat, image = line_of_sight_scene(np.array(truth), brightness)
    fitter, peaks, fit = one_fit(model, table, s_hat, image, truth[0] + 0.0003)
    assert len(fit) == 1 and fit.intensity[0] > brightness[0]  # it holds the partner's light too
    split, split_fit = split_shared(fitter, peaks, fit, shadow_probe=0.0065, bright=0.5, misfit=0.5)
    assert len(split) == 2
    assert np.allclose(np.sort(split_fit.alpha), truth, atol=5e-4)
    assert split_fit.intensity[np.argmax(split_fit.alpha)] > 0.7 * brightness[1]


@pytest.mark.parametrize("alpha, brightness", [(1.0028, 2600.0), (0.9983, 2600.0), (0.9980, 3500.0),
                                               (1.0001, 3000.0)])
def test_a_single_particle_is_not_split(alpha, brightness):
    from analysis.depth.deblend import split_shared

    model, table, s_hat, image = line_of_sight_scene([alpha], [brightness])
    fitter, peaks, fit = one_fit(model, table, s_hat, image, alpha)
    split, _ = split_shared(fitter, peaks, fit, shadow_probe=0.0065, bright=0.5, misfit=0.5)
    assert len(split) == 1


def test_one_particle_fitted_twice_on_its_line_of_sight_is_one():
    """Two fits of one blurred particle at nearly its depth (each refitted with the other's light
    taken off, as deblending does): one fit explains the pixels better than the pair."""
    from analysis.depth.deblend import one_particle

    fitter, fit = pair_fits([1.0116, 1.0128], [1.0122], [2400.0])
    assert np.all(fit.intensity > 0.2 * fit.intensity.sum())  # both hold light of their own
    faint, bright = np.argsort(fit.intensity)
    assert one_particle(fitter, fit, np.array([faint]), np.array([bright])).all()


def test_a_true_pair_on_one_line_of_sight_is_two():
    from analysis.depth.deblend import one_particle

    truth = [0.99810, 1.00297]  # the shadowing pair of the split test
    fitter, fit = pair_fits(truth, truth, [1985.0, 1900.0])
    assert np.allclose(fit.alpha, truth, atol=4e-4)
    faint, bright = np.argsort(fit.intensity)
    assert not one_particle(fitter, fit, np.array([faint]), np.array([bright])).any()


@pytest.mark.parametrize("across, kept", [(1.25, 2), (0.0, 1)])
def test_two_particles_either_side_of_focus_a_pitch_apart_are_not_merged(across, kept):
    """Near focus a fit's place across the line of sight is sharp: two fits of a particle's light each,
    1.25 pitches apart (within the merge distance in the image and in alpha, as ideal ball 153 lost
    one), are two particles; two fits of one particle, started 0.3 pitch either side of it, one."""
    truth, brightness = [0.9988, 1.0010], [1450.0, 1540.0]
    if not across:  # the second particle alone
        truth, brightness = truth[1:], brightness[1:]
    model, table, s_hat, image = line_of_sight_scene(truth, brightness, [0.0, across][-len(truth):])
    fitter, _, _ = one_fit(model, table, s_hat, image, truth[0])
    row = table.basis_m[:, 0] / np.hypot(*table.basis_m[:, 0])
    start = (np.array([0.0, 1.25]) if across else np.array([-0.3, 0.3])) * fitter.pitch_m
    fit = fitter.fit(s_hat[0] + start * row[1], s_hat[1] - start * row[0], np.resize(truth, 2))
    for _ in range(2):  # as deblending refits them
        fit = fitter.fit(fit.sx_m, fit.sy_m, fit.alpha, subtract=fitter.render(fit), own=fit)
    x, y = fitter.grid.to_pixels(fit.sx_m, fit.sy_m)
    assert np.hypot(np.diff(x)[0], np.diff(y)[0]) < fitter.merge_radius_px and abs(np.diff(fit.alpha)[0]) < fitter.merge_alpha
    _, unique = fitter.unique(peaks_at(fitter.grid, fit), fit)
    assert len(unique) == kept
    if kept == 2:
        assert np.allclose(np.sort(unique.alpha), truth, atol=4e-4)


def _refit_pair(alphas, truth_alphas, brightness):
    """:func:`refit_blurred` on two fits on one chief ray (as :func:`pair_fits` makes them)."""
    from analysis.detection.rejections import Rejections
    from analysis.depth.deblend import refit_blurred

    fitter, fit = pair_fits(alphas, truth_alphas, brightness)
    fitter = dataclasses.replace(fitter, rejected=Rejections())
    peaks = peaks_at(fitter.grid, fit)
    assert fitter.strongly_blurred(fit.alpha).all()
    _, kept = refit_blurred(fitter, peaks, fit)
    return fitter, kept


def test_the_last_refit_drops_a_second_fit_of_one_blurred_particle():
    """The last refit moves fits along their lines of sight after deblending's partner test: two fits
    of one particle blurred over 7 pitches leave it as one, the other recorded as seen twice."""
    fitter, kept = _refit_pair([1.0116, 1.0128], [1.0122], [2400.0])
    assert len(kept) == 1 and abs(kept.alpha[0] - 1.0122) < 4e-4, kept.alpha
    assert fitter.rejected.counts() == {"seen_twice": 1}


def test_the_last_refit_keeps_a_blurred_pair_on_one_line_of_sight():
    truth = [1.0100, 1.0160]
    fitter, kept = _refit_pair(truth, truth, [2400.0, 2000.0])
    assert len(kept) == 2 and np.allclose(np.sort(kept.alpha), truth, atol=4e-4), kept.alpha
    assert len(fitter.rejected) == 0


@pytest.mark.parametrize("alpha", [0.967, 1.03])
def test_a_wide_glint_fits_as_a_point_but_shows_no_point_pattern(alpha):
    """A glint 0.27 mm across far out of focus (seed 10's off-focus ball had one 11 mm behind focus,
    which set the end of the depth range the survey found) fits as a blurred point with a small
    misfit; the light in its lenses does not follow that point, while a particle's there does."""
    from analysis.depth.quality import patterned

    model, table, s_hat, particle = line_of_sight_scene([alpha], [1000.0])
    for image, is_point in ((particle, True), (glint_image(model, s_hat, alpha), False)):
        fitter, _, fit = one_fit(model, table, s_hat, image, alpha)
        assert fitter.acceptable(fit, 0.2)[0] and abs(fit.alpha[0] - alpha) < 0.003
        assert patterned(fitter, fit, fitter.render(fit))[0] == is_point


def test_a_faint_partner_in_focus_behind_a_brighter_one_is_kept():
    """A pair on one line of sight, the fainter (a third of the light) in focus, the brighter
    blurred over 1.5 pitches (held-out shadowing seed 11 lost such a partner): the fainter lights
    its lens evenly, so no point pattern can vouch for it, but the pair explains the pixels more
    than 1.3 times better than the brighter one alone."""
    from analysis.depth.deblend import weak_partners

    truth = [0.99480, 1.00030]
    fitter, fit = pair_fits(truth, truth, [2900.0, 950.0])
    assert np.allclose(fit.alpha, truth, atol=4e-4), fit.alpha
    faint = int(np.argmin(fit.intensity))
    assert fit.intensity[faint] < 0.35 * fit.intensity.max()  # less light than a probe needs
    assert not weak_partners(fitter, fit).any()


def _pair_in_a_glints_light(truth, brightness, glint_dn=500.0):
    """:func:`pair_fits` of fits at ``truth`` on a pair (or one particle) at ``truth[:len(brightness)]``
    whose lenses also hold a glint's light out of focus, which no fit models (``glint_dn``, half a
    pitch off their chief ray, at alpha 0.985)."""
    model, table, s_hat, image = line_of_sight_scene(truth[:len(brightness)], brightness)
    glint = glint_image(model, s_hat + 0.5 * table.basis_m[:, 0], 0.985, level_dn=glint_dn)
    image = np.clip(image.astype(float) + glint - float(table.black_level), 0, 4095).astype(np.uint16)
    fitter, _, _ = one_fit(model, table, s_hat, image, truth[0])
    fit = fitter.fit(np.full(2, s_hat[0]), np.full(2, s_hat[1]), np.asarray(truth), alpha_half_range=0.0005)
    for _ in range(2):
        fit = fitter.fit(fit.sx_m, fit.sy_m, fit.alpha, subtract=fitter.render(fit), own=fit, alpha_half_range=0.0005)
    return fitter, fit


@pytest.mark.parametrize("truth, brightness, glint_dn, passes", [
    ([0.99602, 1.0007], [1995.0, 1241.0], 500.0, "light"),  # as fresh shadowing 141's
    ([0.99602, 1.0005], [2400.0, 650.0], 150.0, "misfit"),  # as fresh shadowing 143's
])
def test_a_faint_partner_in_focus_misfit_by_light_others_leave_is_kept(truth, brightness, glint_dn, passes):
    """The fainter of a pair, in focus, behind one blurred over 2.3 pitches, both in a glint's light
    that no fit models: it passes only one of a probe's tests (the glint's disks in its lens raise
    its misfit, or it has under a probe's share of the light), and over the brighter one's many
    lenses the glint's light dilutes the pair's gain under IN_FOCUS_PAIR_GAIN; over its own lens the
    pair explains the pixels several times better than the brighter one alone."""
    from analysis.depth.deblend import IN_FOCUS_PAIR_GAIN, PROBE_FRACTION, PROBE_RESIDUAL, one_particle, weak_partners

    fitter, fit = _pair_in_a_glints_light(truth, brightness, glint_dn)
    faint, bright = np.argsort(fit.intensity)
    assert fitter.acceptable(fit).all()
    light = fit.intensity[faint] >= PROBE_FRACTION * fit.intensity[bright]
    misfit = fit.residual[faint] <= PROBE_RESIDUAL
    assert (light, misfit) == (passes == "light", passes == "misfit")
    pair = (np.array([faint]), np.array([bright]))
    assert one_particle(fitter, fit, *pair, gain=IN_FOCUS_PAIR_GAIN).all()  # over the brighter one's pixels
    assert not one_particle(fitter, fit, *pair, gain=IN_FOCUS_PAIR_GAIN, own_lenses=np.array([True])).any()
    assert not weak_partners(fitter, fit).any()


def test_a_second_fit_in_focus_on_a_blurred_particle_in_a_glints_light_is_dropped():
    """One particle blurred over 1.5 pitches in the same glint's light, and a second fit in focus on
    its line of sight that takes a probe's light of what the model leaves: it is that light seen
    twice, over its own lens as over the particle's."""
    from analysis.depth.deblend import PROBE_FRACTION, weak_partners

    fitter, fit = _pair_in_a_glints_light([0.99740, 1.0003], [1995.0])
    faint, bright = np.argsort(fit.intensity)
    assert fitter.acceptable(fit).all() and fit.intensity[faint] > PROBE_FRACTION * fit.intensity[bright]
    assert list(weak_partners(fitter, fit)) == [faint == 0, faint == 1]


def test_a_strongly_blurred_particle_converges_clearly_a_wide_glint_does_not():
    """Blurred over 6 pitches, a lone particle's light is explained no better by its point pattern
    than by the same light spread over a pitch (the ratio test fails it), but its pattern explains
    most of the light's variation in its lenses; a wide glint's explains almost none."""
    from analysis.depth.quality import converges

    alpha = 1.02
    model, table, s_hat, particle = line_of_sight_scene([alpha], [600.0])
    for image, clearly in ((particle, True), (glint_image(model, s_hat, alpha), False)):
        fitter, _, fit = one_fit(model, table, s_hat, image, alpha)
        explained = fitter.render(fit)
        assert not converges(fitter, fit, explained)[0]
        assert converges(fitter, fit, explained, clear=True)[0] == clearly


def test_a_blurred_particle_in_a_glints_light_is_kept_where_its_light_clearly_converges():
    """Far from focus, real particles in crowds sit in light nothing explains (missed neighbours',
    a glint's): the extended test then asks whether their own light converges to a point. A lone
    particle blurred over 6 pitches beside an in-focus glint fails the ratio test there, but its
    pattern clearly explains its lenses' light, so it is kept."""
    from analysis.depth.quality import converges, drop_extended, leftover_fraction

    alpha = 1.02
    model, table, s_hat, particle = line_of_sight_scene([alpha], [600.0])
    glint = glint_image(model, s_hat + 4.0 * table.basis_m[:, 0], 1.0, level_dn=100.0)
    image = np.clip(particle.astype(float) + glint - float(table.black_level), 0, 4095).astype(np.uint16)
    fitter, peaks, fit = one_fit(model, table, s_hat, image, alpha)
    assert abs(fit.alpha[0] - alpha) < 0.002
    explained = fitter.render(fit)
    assert leftover_fraction(fitter, fit, explained)[0] > 0.5  # the glint's light is around it ...
    assert leftover_fraction(fitter, fit, explained, reach_pitches=0.5)[0] > 0.4  # ... and on it
    assert not converges(fitter, fit, explained)[0]
    kept, _, _ = drop_extended(fitter, peaks, fit)
    assert len(kept) == 1


@pytest.mark.parametrize("alpha, brightness", [(1.02, 300.0), (0.975, 600.0)])
def test_light_even_within_its_lenses_is_dropped_as_extended_though_a_fit_explains_it(alpha, brightness):
    """The same light per lens as a blurred particle's, but spread evenly over each micro-image
    (light that does not converge, as a reflection's edge the background model misses): a fit
    there explains most of the light around it, so its shares pass, yet neither its point pattern
    nor the same fit spread over a pitch follows that light. It is dropped; the particle is kept."""
    import dataclasses

    from analysis.depth.quality import drop_extended, leftover_fraction
    from analysis.detection.rejections import Rejections

    model, table, s_hat, particle = line_of_sight_scene([alpha], [brightness])
    raw = particle.astype(np.float64).reshape(-1)
    light = (raw[table.pixel_index] - table.black_level) / table.weight
    per_lens = np.bincount(table.lens, light) / np.bincount(table.lens)
    even = raw.copy()
    even[table.pixel_index] = (table.black_level + per_lens[table.lens] * table.weight
                               + np.random.default_rng(1).normal(0.0, 2.0, table.pixel_index.size))
    even = np.clip(np.round(even), 0, 4095).astype(np.uint16).reshape(particle.shape)
    for image, is_point in ((particle, True), (even, False)):
        fitter, peaks, fit = one_fit(model, table, s_hat, image, alpha)
        fitter = dataclasses.replace(fitter, rejected=Rejections())
        assert leftover_fraction(fitter, fit)[0] < 0.3  # the shares alone would keep it
        kept, _, _ = drop_extended(fitter, peaks, fit)
        assert len(kept) == int(is_point)
        assert fitter.rejected.counts() == ({} if is_point else {"extended": 1})


def test_pattern_overlap_tells_one_particle_fitted_twice_from_a_pair_on_its_line_of_sight():
    """Two fits of one particle blurred over 7 pitches, 0.0002 apart in alpha after the refits, light
    their lenses alike: a fainter one there, with little evidence of its own, is the other's light
    seen twice (a slightly wrong model leaves light that such a fit takes). True pairs on one line
    of sight at other depths put their spots elsewhere in each lens."""
    from analysis.depth.deblend import SAME_PATTERN
    from analysis.depth.rayfit import pattern_overlap

    def overlap(fitter, fit, rows, other):
        return pattern_overlap(fitter.table, fit.take(rows), fit.take(other),
                               fitter.blur_radius_m(fit.alpha[rows]) + 0.5 * fitter.pitch_m,
                               aperture_per_lens_plane=fitter.aperture_per_lens_plane, blur_px=fitter.blur_px)

    fitter, fit = pair_fits([1.0116, 1.0128], [1.0122], [2400.0])
    assert overlap(fitter, fit, np.array([0, 1, 0]), np.array([1, 0, 0])) == pytest.approx([0.9, 0.9, 1.0], abs=0.08)
    for truth, brightness in (([1.0100, 1.0160], [2400.0, 2000.0]), ([0.99480, 1.00030], [2900.0, 950.0])):
        fitter, fit = pair_fits(truth, truth, brightness)
        faint, bright = np.argsort(fit.intensity)
        assert overlap(fitter, fit, np.array([faint]), np.array([bright]))[0] < 0.5 * SAME_PATTERN
