"""The neighbours' depth prior: a plane where neighbours form a surface, nothing where they do not."""

from __future__ import annotations

import numpy as np

from analysis.depth.prior import neighbour_prior


def hex_layer(rng, n_side=9, spacing=40.0):
    i, j = np.meshgrid(np.arange(n_side), np.arange(n_side))
    x = spacing * (i + 0.5 * (j % 2)).ravel() + rng.normal(0, 2, i.size)
    y = spacing * 0.866 * j.ravel() + rng.normal(0, 2, i.size)
    return x, y


def test_layer_gives_a_narrow_prior_on_its_plane():
    rng = np.random.default_rng(1)
    x, y = hex_layer(rng)
    plane = 1.0 + 2e-5 * x - 3e-5 * y
    noise = 1e-4
    alpha = plane + rng.normal(0, noise, x.size)
    prior = neighbour_prior(x, y, alpha, np.full(x.size, noise))
    assert np.all(np.isfinite(prior.alpha))
    z = (prior.alpha - plane) / prior.sigma
    assert np.sqrt(np.mean(z**2)) < 2.0  # the width is honest
    assert np.median(np.abs(prior.alpha - plane)) < noise  # better than one measurement
    assert np.median(prior.sigma) < 2.5 * noise


def test_particles_off_the_surface_do_not_tilt_it():
    """Shadowing partners (another depth, same place in the image) among the neighbours."""
    rng = np.random.default_rng(2)
    x, y = hex_layer(rng)
    noise = 1e-4
    alpha = 1.0 + 2e-5 * x + rng.normal(0, noise, x.size)
    hosts = rng.choice(x.size, size=16, replace=False)
    px, py = x[hosts] + 3.0, y[hosts] + 3.0
    pa = alpha[hosts] + rng.choice([-1, 1], hosts.size) * 0.008  # far off the layer, precisely measured
    xs, ys, alphas = np.r_[x, px], np.r_[y, py], np.r_[alpha, pa]
    prior = neighbour_prior(xs, ys, alphas, np.full(xs.size, noise))
    layer = np.arange(x.size)
    plane = 1.0 + 2e-5 * x
    # Where partners fill a third of a particle's neighbours it gets no prior: too few agree.
    has = np.isfinite(prior.alpha[layer])
    assert has.mean() > 0.9
    assert np.median(np.abs(prior.alpha[layer][has] - plane[has])) < 1.5 * noise
    assert np.percentile(prior.sigma[layer][has], 90) < 5 * noise


def test_a_3d_crowd_gives_a_wide_prior():
    rng = np.random.default_rng(3)
    n = 150
    x, y = rng.uniform(0, 400, n), rng.uniform(0, 400, n)
    alpha = 1.0 + rng.uniform(-0.006, 0.006, n)  # no surface: depths independent of position
    prior = neighbour_prior(x, y, alpha, np.full(n, 1e-4))
    # Mostly no prior at all; where a few neighbours happen to line up, a wide one.
    assert np.mean(np.isnan(prior.sigma)) > 0.9
    assert np.all(np.nan_to_num(prior.sigma, nan=1.0) > 2e-4)


def test_ambiguous_neighbours_hardly_count():
    rng = np.random.default_rng(4)
    x, y = hex_layer(rng)
    alpha = np.full(x.size, 1.002)
    std = np.full(x.size, 1e-4)
    lost = rng.choice(x.size, size=20, replace=False)
    alpha[lost] = 1.0  # the middle of an ambiguous range, far from the truth
    std[lost] = 1e-3
    prior = neighbour_prior(x, y, alpha, std)
    keep = np.setdiff1d(np.arange(x.size), lost)
    assert np.median(np.abs(prior.alpha[keep] - 1.002)) < 1e-4


def test_too_few_particles_give_no_prior():
    prior = neighbour_prior(np.arange(5.0), np.zeros(5), np.ones(5), np.full(5, 1e-4))
    assert np.all(np.isnan(prior.alpha)) and np.all(np.isnan(prior.sigma))
