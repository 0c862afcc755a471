"""Extended light behind the samples, the noise about it, and the depth fit's table of a drifted
lattice, against slow numpy versions of the same rules on a realistic crop (glow gradient, a
reflection band, hot pixels, a drifted lattice), and against the simulated camera's noise."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.ndimage import median_filter

from analysis.cache import Cache
from analysis.calibration.cache import load_calibration
from analysis.calibration.drift import LatticeDrift
from analysis.errors import ParameterError
from analysis.formats.exposure import read_exposure
from analysis.calibration.calibrate import calibrate
from analysis.camera.model import CameraModel
from analysis.formats.whites import WhiteImage
from analysis.lightfield.background import CENTRAL_FRACTION, BackgroundMap, estimate_background, local_noise
from analysis.lightfield.samples import background_and_noise, select_samples
from analysis.order_statistics import median_of_5
from analysis.pipeline.tables import DRIFTED_TABLES_KEPT, FIT_TABLE_RIM_PX, drifted_fit_table, get_table
from analysis.simulation.camera import (ELECTRONS_PER_DN, READ_NOISE_DN, simulated_camera_metadata,
                                        simulated_private_metadata)
from analysis.simulation.camera_effects import CameraEffects
from analysis.simulation.chamber import ChamberLight, ExtendedSource
from analysis.simulation.realism import Realism
from analysis.simulation.render import render_exposure, render_white_image
from analysis.simulation.scenario_files import write_scenario
from analysis.simulation.scenarios import Particles


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    folder = tmp_path_factory.mktemp("background")
    files = write_scenario(folder, "tilted-layer", 3, size=1024, realism=Realism.typical())
    exposure = read_exposure(files.lfp[0])
    calibration = load_calibration(files.calibration_dir, exposure.metadata, serial=exposure.serial)
    # Out-of-focus light from a glint: smooth, lighting micro-images as the white image does.
    rows, cols = np.mgrid[0:1024, 0:1024]
    glint = 600.0 * np.exp(-((rows - 400.0) ** 2 + (cols - 600.0) ** 2) / (2 * 90.0 ** 2)) * calibration.devignetting
    image = np.clip(exposure.image + np.rint(glint), 0, 4095).astype(np.uint16)
    cache = Cache()
    return image, calibration, get_table(calibration, cache), get_table(calibration, cache, rim_px=FIT_TABLE_RIM_PX)


def _per_sample_reference(background: BackgroundMap, table) -> np.ndarray:
    # Each sample: its lens's level, or the value of its pixel where that was taken one by one.
    out = background.per_lens(table).astype(np.float32)[table.lens]
    if background.pixels.size:
        order = np.argsort(background.pixels)
        pixels, values = background.pixels[order], background.values[order]
        at = np.clip(np.searchsorted(pixels, table.pixel_index), 0, pixels.size - 1)
        hit = pixels[at] == table.pixel_index
        out[hit] = values[at[hit]]
    return out


def test_per_sample_background_is_the_lens_level_or_the_samples_own(case):
    image, _, refocus, fit = case
    noise = background_and_noise(image, refocus)[1]
    background = estimate_background(image, fit, noise_dn=noise)
    assert background.pixels.size > 1000, "the glint's light should be taken sample by sample"
    for table in (fit, refocus):
        got = background.per_sample(table)
        assert got.dtype == np.float32 and np.array_equal(got, _per_sample_reference(background, table))
    # Each lens's samples listed together, ascending, where `first` says.
    n_i = background.level.shape[1]
    cells = np.repeat(np.arange(background.first.size - 1), np.diff(background.first))
    assert np.all(np.diff(cells * image.size + background.pixels) > 0)
    j, i = np.divmod(cells, n_i)
    lens_of = dict(zip(map(tuple, fit.lens_ij), range(fit.n_lenses)))
    k = np.array([lens_of[(a + background.i0, b + background.j0)] for a, b in zip(i, j)])
    assert np.array_equal(np.isin(background.pixels, fit.pixel_index[np.isin(fit.lens, k)]), np.ones(k.size, bool))
    uniform = BackgroundMap.uniform(7.5).per_sample(refocus)
    assert uniform.dtype == np.float32 and np.all(uniform == 7.5)


def test_level_is_the_median_over_neighbouring_lenses(case):
    image, _, refocus, fit = case
    background = estimate_background(image, fit, noise_dn=background_and_noise(image, refocus)[1])
    # The level map is its own 5 x 5 median's fixed point only where it is flat; compare instead with
    # SciPy's median of the same float32 grid, which the OpenCV median must equal exactly.
    grid = background.level.astype(np.float32).astype(np.float64)
    assert np.array_equal(grid, background.level)  # float32 values, so the float32 median is exact
    assert np.array_equal(cv2.medianBlur(grid.astype(np.float32), 5).astype(np.float64),
                          median_filter(grid, size=5, mode="nearest"))


def test_local_noise_is_the_lower_percentiles_of_each_lens_then_the_median_of_its_neighbours(case):
    image, _, refocus, fit = case
    background = estimate_background(image, fit, noise_dn=background_and_noise(image, refocus)[1])
    per_sample = background.per_sample(refocus)
    got_offset, got_spread = local_noise(image, refocus, per_sample).per_lens(refocus)
    # Per lens: the 10th and 30th percentiles of its central samples about the background, read
    # as a normal distribution's; then the 5 x 5 median over the lattice indices.
    residual = (image.reshape(-1)[refocus.pixel_index].astype(np.float64) - refocus.black_level
                - per_sample * refocus.weight).astype(np.float32)
    central = refocus.u_m * refocus.u_m + refocus.v_m * refocus.v_m <= (CENTRAL_FRACTION * refocus.aperture_radius_m) ** 2
    lens_values = [residual[a:b][central[a:b]].astype(np.float64)
                   for a, b in zip(refocus.lens_start[:-1], refocus.lens_start[1:])]
    q10, q30 = (np.array([np.quantile(v, q) if v.size >= 2 else np.nan for v in lens_values]) for q in (0.1, 0.3))
    z10, z30 = -1.2815515655446004, -0.5244005127080407
    spread = (q30 - q10) / (z30 - z10)
    offset = q30 - z30 * spread
    i0, j0 = refocus.lens_ij.min(axis=0)
    shape = tuple(refocus.lens_ij.max(axis=0)[::-1] - (j0, i0) + 1)
    for values, got in ((offset, got_offset), (spread, got_spread)):
        # Cells without a lens, and lenses with fewer than two central samples, take the typical value.
        values = np.where(np.isfinite(values), values, np.nanmedian(values))
        grid = np.full(shape, np.float32(np.median(values)), dtype=np.float32)
        grid[refocus.lens_ij[:, 1] - j0, refocus.lens_ij[:, 0] - i0] = values
        want = median_filter(grid, size=5, mode="nearest")[refocus.lens_ij[:, 1] - j0, refocus.lens_ij[:, 0] - i0]
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-3)


@pytest.fixture(scope="module")
def faint_beside_a_reflection():
    """A realistic camera (wider blur, micro-image response, vignetting, a drifted lattice), a
    reflected laser band across part of the crop, and a faint particle blurred over 8 lens pitches
    over the glow beside it: its expected image, the noisy exposure, tables and background."""
    meta = simulated_camera_metadata(size=512)
    model = CameraModel.from_metadata(meta)
    camera = CameraEffects.build(Realism.only("blur", "micro-images", "vignetting", "drift"), serial="A202160042")
    white = WhiteImage.from_image("MOD_0001", render_white_image(model, seed=7, camera=camera), meta,
                                  simulated_private_metadata())
    calibration = calibrate(white)
    cache = Cache()
    refocus, fit = get_table(calibration, cache), get_table(calibration, cache, rim_px=FIT_TABLE_RIM_PX)
    faint = Particles(np.array([-0.3]), np.array([-0.3]), np.array([57.0]), np.array([500.0]))
    band = ExtendedSource(kind="band", z_mm=66.0, x_mm=0.0, y_mm=0.9, sigma_mm=0.2, level_dn=2000.0,
                          angle_rad=0.02, amplitude=0.25, period_mm=2.5)
    clean = render_exposure(model, faint, seed=3, noise=False, camera=camera).astype(np.float64) - model.black_level
    image = render_exposure(model, faint, seed=3, background_dn=40.0, chamber=ChamberLight(sources=(band,)),
                            camera=camera)
    background = estimate_background(image, fit, noise_dn=background_and_noise(image, refocus)[1])
    return clean, image, refocus, background


def test_local_noise_is_the_cameras_over_glow_and_more_over_a_reflection(faint_beside_a_reflection):
    _, image, refocus, background = faint_beside_a_reflection
    _, spread = local_noise(image, refocus, background.per_sample(refocus)).per_lens(refocus)
    level = background.per_lens(refocus)
    typical = np.median(level)
    glow, band = level < 1.2 * typical, level > 5 * typical
    assert glow.sum() > 500 and band.sum() > 200
    shot_and_read = np.sqrt(READ_NOISE_DN ** 2 + level[glow] / ELECTRONS_PER_DN)
    assert np.median(spread[glow] / shot_and_read) == pytest.approx(1.0, abs=0.15)
    assert np.median(spread[band]) > 5 * np.median(spread[glow])


def test_a_faint_blurred_particles_samples_pass_beside_a_reflection(faint_beside_a_reflection):
    """Each lens's own noise sets its cut: the particle's samples expected 5 shot-noise sigmas above
    the glow all pass. One noise model for the frame follows the band's light and cuts half of them."""
    clean, image, refocus, background = faint_beside_a_reflection
    lit = np.flatnonzero(clean.reshape(-1)[refocus.pixel_index] > 25.0)
    assert lit.size > 50
    local = select_samples(image, refocus, background=background)
    frame_wide = select_samples(image, refocus, background=background, local=False)
    assert np.isin(lit, local.ids).mean() >= 0.95
    assert np.isin(lit, frame_wide.ids).mean() < 0.7
    assert local.threshold < frame_wide.threshold


def test_median_of_5_is_the_median():
    rng = np.random.default_rng(3)
    for _ in range(2000):
        v = rng.integers(0, 5, 5).astype(np.float32)  # ties included
        assert median_of_5(*v) == np.median(v)


def test_the_cache_keeps_one_drifted_table_per_calibration(case):
    _, calibration, _, _ = case
    cache = Cache()
    first = drifted_fit_table(calibration, cache, LatticeDrift((0.2, -0.1), 0.0, 0.01, 100))
    assert drifted_fit_table(calibration, cache, LatticeDrift((0.2001, -0.1), 0.0, 0.01, 100)) is first  # same step
    second = drifted_fit_table(calibration, cache, LatticeDrift((0.3, -0.1), 0.0, 0.01, 100))
    assert second is not first
    base = get_table(calibration, cache, rim_px=FIT_TABLE_RIM_PX)
    assert [value[1] for _, value in cache.entries("drifted_table", base.uid)] == [second]
    assert drifted_fit_table(calibration, cache, None) is base


def test_a_cache_directory_keeps_the_latest_drifted_tables_mapped_and_rebuilds_a_broken_one(case, tmp_path):
    _, calibration, _, _ = case
    drift = LatticeDrift((0.2, -0.1), 0.0, 0.01, 100)
    made = drifted_fit_table(calibration, Cache(directory=tmp_path), drift)
    files = sorted(tmp_path.rglob("*.drift.*.npz"))
    assert len(files) == 1
    # A new process reads it back, mapped from the file (its pages can be given back), not derived again.
    read = drifted_fit_table(calibration, Cache(directory=tmp_path), drift)
    assert read.uid == made.uid and not read.weight.flags.owndata
    for name in ("pixel_index", "lens", "u_m", "v_m", "weight"):
        np.testing.assert_array_equal(getattr(read, name), getattr(made, name))
    # Broken on disk (replaced, as every cache file is written: the tables above keep their map):
    # derived again, the same table, the file written anew.
    broken = tmp_path / "broken"
    broken.write_bytes(files[0].read_bytes()[:1000])
    broken.replace(files[0])
    again = drifted_fit_table(calibration, Cache(directory=tmp_path), drift)
    np.testing.assert_array_equal(again.weight, made.weight)
    assert again.uid != made.uid
    # Only the most recently used ones stay.
    for k in range(DRIFTED_TABLES_KEPT + 2):
        drifted_fit_table(calibration, Cache(directory=tmp_path), LatticeDrift((0.3 + 0.05 * k, -0.1), 0.0, 0.01, 100))
    assert len(list(tmp_path.rglob("*.drift.*.npz"))) == DRIFTED_TABLES_KEPT


def test_released_pages_of_a_mapped_map_read_back_the_same(tmp_path):
    from analysis.formats.mapped_npz import release_pages

    data = np.arange(1 << 20, dtype=np.float32)
    np.save(tmp_path / "map.npy", data)
    mapped = np.load(tmp_path / "map.npy", mmap_mode="r").view(np.ndarray)
    assert float(mapped.sum(dtype=np.float64)) == float(data.sum(dtype=np.float64))
    release_pages(mapped)
    assert np.array_equal(mapped, data)  # read back from the file
    release_pages(data)  # in memory: nothing to do
    assert data[12] == 12.0


def test_a_lower_cut_in_some_lenses_keeps_their_fainter_samples_and_no_others(faint_beside_a_reflection):
    """``lens_sigmas``: in the lenses the particle lights, cut at one sigma, the samples it lifts
    2-8 DN above the glow (under a sigma or so of its noise) pass many times more often than at
    three; every other lens keeps exactly the samples of the three-sigma cut."""
    clean, image, refocus, background = faint_beside_a_reflection
    expected = clean.reshape(-1)[refocus.pixel_index]
    lenses = np.zeros(refocus.n_lenses, dtype=bool)
    lenses[refocus.lens[expected > 2.0]] = True
    faint = np.flatnonzero((expected > 2.0) & (expected < 8.0))
    three = select_samples(image, refocus, background=background, noise_sigmas=3.0)
    mixed = select_samples(image, refocus, background=background, noise_sigmas=3.0,
                           lens_sigmas=np.where(lenses, 1.0, 3.0))
    kept_three, kept_mixed = np.isin(faint, three.ids).sum(), np.isin(faint, mixed.ids).sum()
    assert faint.size > 50 and kept_mixed >= 0.2 * faint.size and kept_mixed > 4 * max(kept_three, 1)
    inside = lenses[refocus.lens[mixed.ids]]
    assert np.array_equal(mixed.ids[~inside], three.ids[~lenses[refocus.lens[three.ids]]])
    with pytest.raises(ParameterError, match="lens_sigmas"):
        select_samples(image, refocus, background=background, local=False, lens_sigmas=np.ones(refocus.n_lenses))
    with pytest.raises(ParameterError, match="lens_sigmas"):
        select_samples(image, refocus, background=background, lens_sigmas=np.ones(3))


def test_the_residual_is_cut_lower_only_in_the_lenses_the_fits_reach(case):
    from analysis.pipeline.passes import RESIDUAL_NOISE_SIGMAS, residual_cut

    image, _, refocus, _ = case
    residual = image.copy()
    residual[500:520, 300:330] -= 1  # the light of a fit taken off
    sigmas = residual_cut(refocus, image, residual, 3.0)
    touched = np.zeros(image.shape, dtype=bool)
    touched[500:520, 300:330] = True
    reached = np.unique(refocus.lens[touched.reshape(-1)[refocus.pixel_index]])
    assert reached.size > 3
    assert np.all(sigmas[reached] == RESIDUAL_NOISE_SIGMAS)
    assert np.sum(sigmas == RESIDUAL_NOISE_SIGMAS) == reached.size and np.all(np.delete(sigmas, reached) == 3.0)
    assert residual_cut(refocus, image, residual, None) is None
    assert residual_cut(refocus, image, residual, RESIDUAL_NOISE_SIGMAS) is None


def test_particles_crowding_lenses_do_not_set_a_background_sample_by_sample():
    """Nine bright particles blurred over 6.7 lens pitches, their disks overlapping: their spots
    light a good part of each lens's samples and raise its median, but not its lower percentile,
    which extended light raises with all the others. So no lens takes its background sample by
    sample, whose medians over neighbouring lenses would take much of the light of the particles
    blurred over many pitches (marked by their lens medians, 27 785 samples were)."""
    meta = simulated_camera_metadata(size=512)
    model = CameraModel.from_metadata(meta)
    camera = CameraEffects.build(Realism.only("blur"), serial="A202160042")
    white = WhiteImage.from_image("MOD_0001", render_white_image(model, seed=7, camera=camera), meta,
                                  simulated_private_metadata())
    cache = Cache()
    calibration = calibrate(white)
    refocus, fit = get_table(calibration, cache), get_table(calibration, cache, rim_px=FIT_TABLE_RIM_PX)
    gx, gy = np.meshgrid([-0.4, 0.0, 0.4], [-0.4, 0.0, 0.4])
    crowd = Particles(gx.ravel(), gy.ravel(), np.full(9, 57.5), np.full(9, 8000.0))
    image = render_exposure(model, crowd, seed=3, background_dn=40.0, camera=camera)
    background = estimate_background(image, fit, noise_dn=background_and_noise(image, refocus)[1])
    assert background.pixels.size == 0
