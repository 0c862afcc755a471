"""Calibration from white images: lattice fit against the simulator's truth, white-image choice,
devignetting map and the on-disk cache."""

from __future__ import annotations

import logging
import math
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from analysis.calibration.calibrate import Calibration
from analysis.calibration.cache import CACHE_VERSION, cache_path, load_calibration, read_calibration, save_calibration
from analysis.calibration.white_choice import select_white_image
from analysis.camera.model import CameraModel, Lattice
from analysis.errors import CalibrationError, CameraMismatchError, NoWhiteImageError
from analysis.formats.mapped_npz import is_mapped
from analysis.calibration.lattice_fit import balance_channels, fit_lattice, lens_centroids
from analysis.simulation.camera import SimulatedLens, simulated_camera_metadata, simulated_private_metadata
from analysis.simulation.render import render_white_image
from analysis.formats.whites import WhiteImage, write_white_pair

SIZE = 800
SERIAL = "A202160042"


def _truth_model(size: int = SIZE) -> CameraModel:
    """Metadata model whose rendered lattice differs from the metadata (as a real one does)."""
    model = CameraModel.from_metadata(simulated_camera_metadata(size=size))
    lat = model.lattice
    return model.with_lattice(lat.with_changes(origin_x=lat.origin_x + 0.37, origin_y=lat.origin_y - 0.21,
                                               rotation_rad=0.0031, scale_y=1.0007))


def _mean_centre_error(fitted: Lattice, truth: Lattice, size: int) -> float:
    ij, xy = truth.centres(size, size)
    fx, fy = fitted.centre(ij[:, 0], ij[:, 1])
    return float(np.mean(np.hypot(fx - xy[:, 0], fy - xy[:, 1])))


@pytest.fixture(scope="module")
def truth_model() -> CameraModel:
    return _truth_model()


@pytest.fixture(scope="module")
def white_800(truth_model) -> np.ndarray:
    return render_white_image(truth_model, seed=11)


# --- lattice fit ---------------------------------------------------------------------------

@pytest.mark.parametrize("dx, dy, pitch_rel, rot_rad", [
    (2.7, -1.9, 0.002, -0.001),
    (-3.8, 1.2, -0.002, 0.001),
    (0.4, 3.5, 0.004, 0.0),
])
def test_fit_recovers_lattice_from_perturbed_seed(truth_model, white_800, dx, dy, pitch_rel, rot_rad):
    truth = truth_model.lattice
    seed = truth.with_changes(origin_x=truth.origin_x + dx, origin_y=truth.origin_y + dy,
                              pitch_px=truth.pitch_px * (1 + pitch_rel),
                              rotation_rad=truth.rotation_rad + rot_rad, scale_y=1.0)
    fit = fit_lattice(white_800, seed, black_level=truth_model.black_level)
    got = fit.lattice
    assert _mean_centre_error(got, truth, SIZE) < 0.05
    assert got.origin_x == pytest.approx(truth.origin_x, abs=0.03)
    assert got.origin_y == pytest.approx(truth.origin_y, abs=0.03)
    assert got.pitch_px == pytest.approx(truth.pitch_px, rel=2e-5)
    assert got.rotation_rad == pytest.approx(truth.rotation_rad, abs=1e-4)
    assert got.scale_y == pytest.approx(truth.scale_y, abs=1e-4)
    assert got.scale_x == seed.scale_x
    assert isinstance(got.pitch_px, float)
    # Centroids scatter around the fitted centres without bias; nearly all lenses are measured.
    assert fit.n_lenses > 0.95 * len(truth.lens_indices(SIZE, SIZE, margin_px=truth.pitch_px))
    assert fit.centroid_rms_px < 0.2
    assert np.hypot(*fit.centroid_bias_px) < 0.01
    assert fit.rms_px < 0.05


def test_fit_ignores_bayer_gains(truth_model):
    white = render_white_image(truth_model, seed=5, responses={"r": 0.3, "g": 1.0, "b": 0.55})
    truth = truth_model.lattice
    seed = truth.with_changes(origin_x=truth.origin_x - 2.0, pitch_px=truth.pitch_px * 1.002)
    fit = fit_lattice(white, seed)
    assert _mean_centre_error(fit.lattice, truth, SIZE) < 0.05


def test_origin_is_the_lens_nearest_the_seed_origin(truth_model, white_800):
    # A seed one lens step (plus a little) away labels that lens (0, 0).
    truth = truth_model.lattice
    bx, by = truth.centre(1, 0)
    seed = truth.with_changes(origin_x=bx + 1.0, origin_y=by - 0.8)
    got = fit_lattice(white_800, seed).lattice
    assert (got.origin_x, got.origin_y) == pytest.approx((bx, by), abs=0.03)
    assert _mean_centre_error(got.with_changes(origin_x=truth.origin_x, origin_y=truth.origin_y),
                              truth, SIZE) < 0.05


def test_fit_refuses_an_image_without_micro_images(truth_model):
    rng = np.random.default_rng(0)
    flat = (168 + rng.poisson(1500, size=(SIZE, SIZE))).astype(np.uint16)
    with pytest.raises(CalibrationError, match="no micro-image pattern"):
        fit_lattice(flat, truth_model.lattice)


def test_fit_refuses_a_seed_of_another_pitch(truth_model, white_800):
    seed = truth_model.lattice.with_changes(pitch_px=truth_model.lattice.pitch_px * 1.4)
    with pytest.raises(CalibrationError):
        fit_lattice(white_800, seed)


def test_fit_refuses_a_tiny_image(truth_model):
    with pytest.raises(CalibrationError, match="too small"):
        fit_lattice(np.zeros((64, 64), np.uint16), truth_model.lattice)


def test_centroids_sit_on_the_true_centres(truth_model, white_800):
    image = balance_channels(white_800, black_level=truth_model.black_level)
    assert image.dtype == np.float32
    _, predicted, measured = lens_centroids(image, truth_model.lattice)
    d = np.hypot(*(measured - predicted).T)
    assert np.median(d) < 0.1
    assert np.abs((measured - predicted).mean(axis=0)).max() < 0.01


@pytest.mark.slow
def test_full_size_fit():
    model = _truth_model(3280)
    white = render_white_image(model, seed=2)
    truth = model.lattice
    seed = truth.with_changes(origin_x=truth.origin_x + 3.0, origin_y=truth.origin_y - 2.0,
                              pitch_px=truth.pitch_px * 0.998, rotation_rad=truth.rotation_rad + 0.001)
    fit = fit_lattice(white, seed)
    assert _mean_centre_error(fit.lattice, truth, 3280) < 0.05
    assert fit.n_lenses > 120_000


@pytest.fixture(scope="module")
def vignetted_white():
    """A full-size white image through the typical simulated camera's optics (its second stop, blur,
    micro-image response and lens transmission): model, camera, raw image."""
    from analysis.simulation.camera_effects import CameraEffects
    from analysis.simulation.realism import Realism

    model = _truth_model(3280)
    camera = CameraEffects.build(Realism(blur_px=0.8, vignetting_corner_cut=0.3, vignetting_onset=0.45,
                                         rim_response=0.75, lens_transmission_spread=0.03), serial=SERIAL)
    return model, camera, render_white_image(model, seed=2, camera=camera)


@pytest.mark.slow
def test_a_second_stops_cats_eyes_do_not_stretch_the_lattice(vignetted_white):
    """Cat's-eye micro-images toward the corners are not centrally symmetric: fitted with the rest,
    the typical simulated stop put the fitted centres 0.44 px off beyond 60 % of the half-diagonal."""
    model, _, white = vignetted_white
    fit = fit_lattice(white, model.lattice, black_level=model.black_level)
    ij, xy = model.lattice.centres(3280, 3280)
    fx, fy = fit.lattice.centre(ij[:, 0], ij[:, 1])
    outer = np.hypot(xy[:, 0] - model.lattice.origin_x, xy[:, 1] - model.lattice.origin_y) > 0.6 * 1640 * math.sqrt(2)
    assert fit.n_cut_blocks > 0
    assert np.sqrt(np.mean(np.hypot(fx - xy[:, 0], fy - xy[:, 1])[outer] ** 2)) < 0.03


@pytest.mark.slow
def test_the_second_stop_is_measured_from_the_white_images_micro_images(vignetted_white):
    """The share of each micro-image's aperture that the stop leaves, as the depth fit models it,
    agrees with the simulator's stop over the field (its cut edge within 1 % of the aperture's
    diameter, the typical camera's blur, rim response and lens transmission included, taken from
    the white image's profile as the calibration does); a white without one gives none."""
    from analysis.calibration.profile import fit_micro_image_profile
    from analysis.calibration.second_stop_fit import fit_second_stop
    from analysis.camera.second_stop import visible_fraction

    model, camera, white = vignetted_white
    truth = camera.second_stop(model)
    o = model.optics
    radius_m = o.aperture_diameter_m / 2
    profile = fit_micro_image_profile(white, model.lattice, black_level=model.black_level,
                                      white_level=model.white_level, radius_px=o.micro_image_radius_px)
    stop = fit_second_stop(white, model, radius_px=profile.radius_px, blur_px=profile.blur_px,
                           response_slope=math.log(profile.rim_response) / profile.radius_px ** 2)
    assert stop is not None
    s = np.linspace(0.0, 3280 / math.sqrt(2) * o.pixel_pitch_m / o.projection_factor, 12)
    # Where the stop's edge crosses the line through the axis: R2 - k s from the aperture's centre.
    edge, true_edge = (np.clip(p.radius_m - p.shift_per_m * s, -radius_m, radius_m) for p in (stop, truth))
    assert np.max(np.abs(edge - true_edge)) < 0.01 * 2 * radius_m, (edge, true_edge)
    np.testing.assert_allclose(visible_fraction(radius_m, stop.radius_m, stop.shift_per_m * s),
                               visible_fraction(radius_m, truth.radius_m, truth.shift_per_m * s), atol=0.01)
    assert fit_second_stop(render_white_image(model, seed=3), model, radius_px=o.micro_image_radius_px) is None


# --- white-image choice --------------------------------------------------------------------

def _white(name: str, *, zoom: int = 981, focus: int = 582, serial: str | None = SERIAL, level: float = 2400.0,
           exposure_s: float = 0.0143, size: int = 64, mla_rotation: float | None = None) -> WhiteImage:
    meta = simulated_camera_metadata(lens=SimulatedLens(zoom_step=zoom, focus_step=focus), size=size,
                                     exposure_s=exposure_s)
    if mla_rotation is not None:
        meta["devices"]["mla"]["rotation"] = mla_rotation
    model = CameraModel.from_metadata(meta)
    image = render_white_image(model, level=level, seed=len(name))
    private = simulated_private_metadata(serial) if serial else {}
    return WhiteImage.from_image(name, image, meta, private)


def _picture_metadata(zoom: int = 981, focus: int = 600) -> dict:
    return simulated_camera_metadata(lens=SimulatedLens(zoom_step=zoom, focus_step=focus), size=64)


def test_selects_nearest_zoom_then_focus_among_decoys():
    whites = [
        _white("MOD_0000", focus=600, serial="A999999999"),   # other camera, exact zoom and focus
        _white("MOD_0001", focus=600, exposure_s=0.004),      # short (dark) exposure
        _white("MOD_0002", focus=601, level=60.0),            # dark by level
        _white("MOD_0003", zoom=1203, focus=600),             # other zoom, exact focus
        _white("MOD_0004", focus=640),                        # farther focus
        _white("MOD_0005", focus=590),                        # the one
    ]
    chosen = select_white_image(whites, _picture_metadata(), serial=SERIAL)
    assert chosen.name == "MOD_0005"
    # Without the right one, the farther focus at the right zoom wins over the exact focus at another zoom.
    chosen = select_white_image([w for w in whites if w.name != "MOD_0005"], _picture_metadata(), serial=SERIAL)
    assert chosen.name == "MOD_0004"


def test_without_serial_the_mla_tells_cameras_apart():
    other = _white("MOD_0000", focus=600, serial=None, mla_rotation=-0.000859)
    mine = _white("MOD_0001", focus=650, serial=None)
    assert select_white_image([other, mine], _picture_metadata(), serial=None).name == "MOD_0001"
    with pytest.raises(CameraMismatchError):
        select_white_image([other], _picture_metadata(), serial=None)


def test_whites_of_another_camera_only():
    whites = [_white("MOD_0000", serial="A111111111"), _white("MOD_0001", serial="A222222222")]
    with pytest.raises(CameraMismatchError, match=r"A111111111 \(64x64 px\); A222222222 \(64x64 px\)"):
        select_white_image(whites, _picture_metadata(), serial=SERIAL)


def test_all_dark_or_none():
    whites = [_white("MOD_0000", level=50.0), _white("MOD_0001", level=80.0, focus=600)]
    with pytest.raises(NoWhiteImageError, match="dark"):
        select_white_image(whites, _picture_metadata(), serial=SERIAL)
    with pytest.raises(NoWhiteImageError):
        select_white_image([], _picture_metadata(), serial=SERIAL)


# --- calibrate, cache ------------------------------------------------------------------------

@pytest.fixture()
def white_folder(tmp_path, truth_model, white_800):
    meta = simulated_camera_metadata(size=SIZE)
    folder = tmp_path / "calibration"
    folder.mkdir()
    write_white_pair(WhiteImage.from_image("MOD_0007", white_800, meta, simulated_private_metadata(SERIAL)), folder)
    decoy = render_white_image(truth_model, level=40.0, seed=3)
    write_white_pair(WhiteImage.from_image("MOD_0008", decoy, meta, simulated_private_metadata(SERIAL)), folder)
    return folder


def test_calibration_fits_and_keeps_devignetting(white_folder, truth_model, white_800):
    meta = simulated_camera_metadata(size=SIZE)
    cal = load_calibration(white_folder, meta, serial=SERIAL)
    assert isinstance(cal, Calibration) and not cal.from_cache
    assert cal.white_name == "MOD_0007" and cal.serial == SERIAL
    assert (cal.zoom_step, cal.focus_step) == (981, 582)
    # Seeded from the metadata, which is 0.4 px and 1.2 mrad off the rendered truth.
    assert _mean_centre_error(cal.lattice, truth_model.lattice, SIZE) < 0.05
    assert cal.fit_n_lenses > 5000 and cal.fit_rms_px < 0.05
    assert cal.devignetting.dtype == np.float32 and cal.devignetting.shape == (SIZE, SIZE)
    expected = (white_800.astype(np.float64) - 168.0) / (4095.0 - 168.0)
    np.testing.assert_allclose(cal.devignetting, expected, rtol=1e-6, atol=1e-7)
    assert cal.model.optics == CameraModel.from_metadata(meta).optics


def test_cache_hit_skips_the_fit(white_folder, tmp_path):
    meta = simulated_camera_metadata(size=SIZE)
    cache = tmp_path / "cache"
    first = load_calibration(white_folder, meta, serial=SERIAL, cache_dir=cache)
    path = cache_path(cache, SERIAL, first.white_sha1)
    assert path.is_file() and path.parent.name == SERIAL and f"v{CACHE_VERSION}" in path.name
    mtime = path.stat().st_mtime_ns
    second = load_calibration(white_folder, meta, serial=SERIAL, cache_dir=cache)
    assert not first.from_cache and second.from_cache
    assert path.stat().st_mtime_ns == mtime
    assert second.lattice == first.lattice
    assert second.model == first.model
    assert second.devignetting.dtype == np.float32
    np.testing.assert_array_equal(second.devignetting, first.devignetting)
    # Mapped from the cache file, not read: only building a look-up table touches it.
    assert is_mapped(second.devignetting) and not second.devignetting.flags.writeable
    assert (second.white_sha1, second.white_name, second.fit_n_lenses) == \
        (first.white_sha1, first.white_name, first.fit_n_lenses)
    assert not any(p.name.endswith(".tmp") for p in path.parent.iterdir())
    # A second stop, where the white image shows one, is kept with the rest.
    from analysis.camera.second_stop import SecondStop
    stop = SecondStop(shift_per_m=1.25, radius_m=0.0058)
    save_calibration(replace(first, second_stop=stop), path)
    assert read_calibration(path).second_stop == stop and second.second_stop is None


def test_cache_files_of_older_formats_are_removed(white_folder, tmp_path):
    """Writing a calibration and its look-up table removes the files an older plenodust wrote for
    the same white image (tables are ~100 MB each); other white images' files and newer ones stay."""
    from analysis.cache import Cache
    from analysis.lightfield.table import TABLE_FORMAT_VERSION
    from analysis.pipeline.tables import get_table, table_cache_path

    meta = simulated_camera_metadata(size=SIZE)
    first = load_calibration(white_folder, meta, serial=SERIAL, cache_dir=tmp_path / "probe")
    folder = tmp_path / "cache" / SERIAL
    folder.mkdir(parents=True)
    sha = first.white_sha1
    old = [folder / f"{sha}.v{CACHE_VERSION - 1}.npz", folder / f"{sha}.lut.v{TABLE_FORMAT_VERSION - 1}.o1.r1.npz"]
    kept = [folder / f"{'0' * 40}.v{CACHE_VERSION - 1}.npz", folder / f"{sha}.lut.v{TABLE_FORMAT_VERSION + 1}.o1.r1.npz",
            folder / "notes.txt"]
    for path in old + kept:
        path.write_bytes(b"x")
    calibration = load_calibration(white_folder, meta, serial=SERIAL, cache_dir=tmp_path / "cache")
    get_table(calibration, Cache(directory=tmp_path / "cache"))
    assert cache_path(tmp_path / "cache", SERIAL, sha).is_file()
    assert table_cache_path(tmp_path / "cache", calibration, 1.0).is_file()
    assert not any(p.exists() for p in old)
    assert all(p.exists() for p in kept)


def test_a_table_of_another_lattice_is_rebuilt(white_folder, tmp_path, caplog):
    """A table file is named by its white image; one left by a calibration of another lattice (a
    newer lattice fit of the same white) is rebuilt, not read: its samples see other aperture points."""
    from analysis.cache import Cache
    from analysis.pipeline.tables import get_table

    meta = simulated_camera_metadata(size=SIZE)
    calibration = load_calibration(white_folder, meta, serial=SERIAL, cache_dir=tmp_path / "cache")
    old = get_table(calibration, Cache(directory=tmp_path / "cache"))
    lattice = calibration.model.lattice
    moved = replace(calibration, model=calibration.model.with_lattice(lattice.with_changes(origin_x=lattice.origin_x + 0.2)))
    with caplog.at_level(logging.WARNING):
        table = get_table(moved, Cache(directory=tmp_path / "cache"))
    assert "another sensor or lattice" in caplog.text
    k_ap = moved.model.optics.aperture_m_per_px
    for t, close in ((table, True), (old, False)):  # the stale table's samples are 0.2 px off
        rows, cols = np.divmod(t.pixel_index.astype(np.int64), SIZE)
        u, _ = moved.model.aperture_coordinates(cols + 0.5, rows + 0.5)
        assert (np.abs(t.u_m - u).max() < 1e-3 * k_ap) == close
    # The rebuilt table replaced the stale file: a fresh process reads it without rebuilding.
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        get_table(moved, Cache(directory=tmp_path / "cache"))
    assert "another sensor or lattice" not in caplog.text


@pytest.mark.parametrize("damage", ["garbage", "truncated", "other_white"])
def test_corrupt_cache_is_rebuilt(white_folder, tmp_path, caplog, damage):
    meta = simulated_camera_metadata(size=SIZE)
    cache = tmp_path / "cache"
    first = load_calibration(white_folder, meta, serial=SERIAL, cache_dir=cache)
    path = cache_path(cache, SERIAL, first.white_sha1)
    data = path.read_bytes()
    if damage == "garbage":
        path.write_bytes(b"not a calibration")
    elif damage == "truncated":
        path.write_bytes(data[: len(data) // 2])
    else:
        # A readable file, but of another white image, under this one's name.
        save_calibration(replace(first, white_sha1="f" * 40), path)
    with caplog.at_level(logging.WARNING, logger="analysis.calibration.calibrate"):
        again = load_calibration(white_folder, meta, serial=SERIAL, cache_dir=cache)
    assert not again.from_cache
    assert again.lattice == first.lattice
    assert "unusable" in caplog.text
    assert read_calibration(path, white_sha1=first.white_sha1).from_cache


def test_compressed_cache_is_read_whole(white_folder, tmp_path):
    """A cache file written compressed (by another tool) cannot be mapped: it is read instead."""
    meta = simulated_camera_metadata(size=SIZE)
    first = load_calibration(white_folder, meta, serial=SERIAL, cache_dir=tmp_path / "cache")
    path = cache_path(tmp_path / "cache", SERIAL, first.white_sha1)
    with np.load(path) as npz:
        members = {k: npz[k] for k in npz.files}
    # Replaced, not rewritten in place: ``first`` maps the file (a map over a truncated file faults).
    np.savez_compressed(tmp_path / "compressed.npz", **members)
    os.replace(tmp_path / "compressed.npz", path)
    again = read_calibration(path, white_sha1=first.white_sha1)
    assert not is_mapped(again.devignetting)
    np.testing.assert_array_equal(again.devignetting, first.devignetting)


def test_read_calibration_names_the_problem(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"\x00" * 10)
    with pytest.raises(CalibrationError, match="unreadable"):
        read_calibration(bad)


def test_lattice_param_sanity():
    # The fundamentals the fit demodulates at are the hex lattice's shortest reciprocal vectors.
    from analysis.calibration.lattice_fit import fundamental_frequencies
    lat = Lattice(origin_x=10.0, origin_y=20.0, pitch_px=9.9, rotation_rad=0.01, scale_y=1.001)
    g = fundamental_frequencies(lat)
    steps = lat.basis.T  # rows b_i, b_j
    assert np.allclose(g[:2] @ steps.T, np.eye(2))
    lengths = np.linalg.norm(g, axis=1)
    assert np.allclose(lengths, 2 / (math.sqrt(3) * 9.9), rtol=2e-3)


def test_cli_prints_choice_and_fit(white_folder, tmp_path, capsys):
    import json

    from service.cli.main import main

    # A picture's .TXT is the bare frame metadata; its serial is given separately.
    txt = tmp_path / "IMG_0001.TXT"
    txt.write_text(json.dumps(simulated_camera_metadata(size=SIZE)))
    cache = tmp_path / "cache"
    assert main(["calibrate", str(white_folder), "--metadata", str(txt), "--serial", SERIAL,
                 "--cache", str(cache)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["white"]["name"] == "MOD_0007" and out["white"]["serial"] == SERIAL
    assert out["from_cache"] is False and Path(out["cache_file"]).is_file()
    assert out["lattice"]["pitch_px"] == pytest.approx(
        CameraModel.from_metadata(simulated_camera_metadata(size=SIZE)).lattice.pitch_px, rel=1e-4)
    assert out["second_stop"] is None  # the ideal camera's micro-images are whole to the corners
    assert main(["calibrate", str(white_folder), "--white", "mod_0007", "--cache", str(cache)]) == 0
    assert json.loads(capsys.readouterr().out)["from_cache"] is True
    assert main(["calibrate", str(white_folder), "--white", "MOD_0042"]) == 2
    assert "MOD_0007, MOD_0008" in capsys.readouterr().err


def test_demodulation_kernel_matches_a_direct_sum():
    from analysis.calibration.lattice_fit import _BLOCK_PX, _STRIDE_PX, demodulate, fundamental_frequencies

    rng = np.random.default_rng(4)
    image = rng.random((160, 192)).astype(np.float32)
    seed = Lattice(origin_x=90.3, origin_y=77.9, pitch_px=9.9, rotation_rad=0.02, scale_y=1.001)
    centres, z, grid = demodulate(image, seed)
    assert grid == ((160 - _BLOCK_PX) // _STRIDE_PX + 1, (192 - _BLOCK_PX) // _STRIDE_PX + 1)
    g = fundamental_frequencies(seed)
    n = np.arange(_BLOCK_PX)
    w = np.sin(np.pi * (n + 0.5) / _BLOCK_PX) ** 2
    for by in range(grid[0]):
        for bx in range(grid[1]):
            y0, x0 = by * _STRIDE_PX, bx * _STRIDE_PX
            ys, xs = np.mgrid[y0:y0 + _BLOCK_PX, x0:x0 + _BLOCK_PX] + 0.5
            sub = image[y0:y0 + _BLOCK_PX, x0:x0 + _BLOCK_PX] * np.outer(w, w)
            for k in range(3):
                phase = -2 * np.pi * (g[k, 0] * (xs - seed.origin_x) + g[k, 1] * (ys - seed.origin_y))
                expected = np.sum(sub * np.exp(1j * phase))
                assert z[by * grid[1] + bx, k] == pytest.approx(expected, rel=1e-6, abs=1e-6)
            assert centres[by * grid[1] + bx] == pytest.approx(
                (x0 + _BLOCK_PX / 2 - seed.origin_x, y0 + _BLOCK_PX / 2 - seed.origin_y))


def test_centroid_of_a_symmetric_spot_is_its_centre():
    ys, xs = np.mgrid[0:40, 0:48] + 0.5
    spots = [(20.3, 17.8), (11.05, 30.6)]
    image = np.zeros((40, 48), np.float32)
    for x0, y0 in spots:
        image += np.exp(-((xs - x0) ** 2 + (ys - y0) ** 2) / (2 * 1.5 ** 2)).astype(np.float32)
    # Predicted centres a pixel off: the window follows the centroid.
    lattice = Lattice(origin_x=21.0, origin_y=17.0, pitch_px=12.0)
    from analysis.calibration.lattice_fit import _centroids

    out_x, out_y, out_w = np.empty(2), np.empty(2), np.empty(2)
    _centroids(image, np.array([21.0, 10.2]), np.array([17.0, 31.3]), 0.45 * lattice.pitch_px, 3,
               out_x, out_y, out_w)
    # Thresholded centroids lock toward pixel centres by a few hundredths of a pixel for spots
    # this small (one reason the fit itself does not use them).
    assert np.allclose(np.stack([out_x, out_y], axis=1), spots, atol=0.05)
    assert np.all(out_w > 0)


def test_simulated_camera_folder_end_to_end(tmp_path):
    # The calibration folder `plenodust simulate` writes: whites at three focus steps (the one at
    # the picture's focus step also as a dark twin) and one at another zoom.
    import json

    from analysis.formats.exposure import read_exposure
    from analysis.simulation.scenario_files import write_scenario

    files = write_scenario(tmp_path / "sim", "tilted-layer", 3, size=SIZE)
    exposure = read_exposure(files.lfp[0])
    doc = json.loads(files.scenario_json.read_text())
    cal = load_calibration(files.calibration_dir, exposure.metadata, serial=exposure.serial)
    chosen = next(w for w in doc["calibration"] if w["name"] == cal.white_name)
    assert not chosen["dark"]
    assert (chosen["zoom_step"], chosen["focus_step"]) == (981, 582)
    truth = Lattice(**doc["optics"]["lattice"])
    assert _mean_centre_error(cal.lattice, truth, SIZE) < 0.05


def test_white_of_another_sensor_size_is_not_this_camera():
    whites = [_white("MOD_0000", size=96), _white("MOD_0001", focus=900)]
    assert select_white_image(whites, _picture_metadata(), serial=SERIAL).name == "MOD_0001"
    with pytest.raises(CameraMismatchError, match=r"A202160042 \(96x96 px\)"):
        select_white_image(whites[:1], _picture_metadata(), serial=SERIAL)
