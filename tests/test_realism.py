"""The realistic simulated camera: each effect is in the rendered bytes, as parameterised."""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from analysis.camera.model import CameraModel
from analysis.errors import ParameterError
from analysis.formats.exposure import read_exposure
from analysis.formats.particle_table import read_csv
from analysis.formats.whites import load_white_images
from analysis.simulation.camera import WHITE_RESPONSE, simulated_camera_metadata
from analysis.simulation.camera_effects import CameraEffects, SensorDefects
from analysis.simulation.chamber import ChamberLight, ExtendedSource, render_reflections
from analysis.simulation.realism import EFFECTS, Realism
from analysis.simulation.render import (accumulate_particles, camera_coverage, channel_response_map, particle_truth,
    render_exposure, render_white_image)
from analysis.simulation.scenario_files import write_scenario
from analysis.simulation.scenarios import Particles, make_scenario
from service.cli.main import main as cli_main

FULL = CameraModel.from_metadata(simulated_camera_metadata())
FLAT = {"r": 1.0, "g": 1.0, "b": 1.0}


def window(start_x: float, start_y: float, size: int) -> CameraModel:
    """A ``size`` px window of the full sensor starting at ``(start_x, start_y)``: the optical axis and
    the lattice stay where they are on the full sensor."""
    lat = FULL.lattice.with_changes(origin_x=FULL.lattice.origin_x - start_x,
                                    origin_y=FULL.lattice.origin_y - start_y)
    return replace(FULL, width=size, height=size, lattice=lat)


def centred(size: int) -> CameraModel:
    return window((3280 - size) / 2, (3280 - size) / 2, size)


def camera(**fields) -> CameraEffects:
    return CameraEffects.build(Realism(**fields), serial="A202160042")


def sha1(path) -> str:
    return hashlib.sha1(path.read_bytes()).hexdigest()


def micro_image_moments(image: np.ndarray, model: CameraModel, *, margin: float, lattice=None):
    """Sum, centroid and second moments (along the radius from the optical axis, and across) of the
    light in each lens cell (pixels nearest that micro-image centre on ``lattice``) of the lenses
    ``margin`` px inside the image on ``model``'s lattice."""
    ij = model.lattice.lens_indices(model.width, model.height, margin_px=margin)
    lattice = model.lattice if lattice is None else lattice
    centres = np.stack(lattice.centre(ij[:, 0], ij[:, 1]), axis=1)
    ys, xs = np.mgrid[0:model.height, 0:model.width] + 0.5
    li, lj = lattice.nearest(xs, ys)
    out = []
    for (i, j), (cx, cy) in zip(ij, centres):
        cell = (li == i) & (lj == j)
        w = image[cell].astype(np.float64)
        x, y = xs[cell], ys[cell]
        total = w.sum()
        mx, my = (w * x).sum() / total, (w * y).sum() / total
        radial = np.array([cx - model.lattice.origin_x, cy - model.lattice.origin_y])
        radial = radial / np.linalg.norm(radial) if np.linalg.norm(radial) > 1 else np.array([1.0, 0.0])
        along = (x - mx) * radial[0] + (y - my) * radial[1]
        across = -(x - mx) * radial[1] + (y - my) * radial[0]
        out.append((total, mx, my, (w * along ** 2).sum() / total, (w * across ** 2).sum() / total))
    return centres, np.array(out)


# --- the parameters -------------------------------------------------------------------------------


def test_realism_defaults_are_the_ideal_camera_and_the_preset_turns_every_effect_on():
    assert Realism().is_ideal and Realism().effects_on() == ()
    assert Realism.typical().effects_on() == tuple(EFFECTS)
    for name in EFFECTS:
        assert Realism.only(name).effects_on() == (name,)
    assert Realism.only("all") == Realism.typical()
    assert Realism.from_dict(json.loads(json.dumps(Realism.typical().to_dict()))) == Realism.typical()
    with pytest.raises(ParameterError, match="blur_px"):
        Realism(blur_px=0.0)
    with pytest.raises(ParameterError, match="choose from"):
        Realism.only("fog")


# --- realism off: the ideal simulator, byte for byte ------------------------------------------------

# SHA-1s of write_scenario(tmp, "ball", 2, size=256) from the ideal simulator before realism existed
# (commit 3300f52). A change here means the ideal camera changed: the project's benchmark figures
# and every test built on the simulator would have to be re-established.
IDEAL_BALL_2_256 = {
    "IMG_0001.RAW": "46e5cd5fea8d108ab100631b0ef77a7c7a6d8c10",
    "IMG_0001.truth.csv": "69bced17ba2013e66591fa6b226e16b69508c5ba",
    "MOD_0001.RAW": "5896c2ced989c5bc857055e25a459b267fd81f86",
    "MOD_0002.RAW": "611179a43f31a799d2376676793838e0790343b1",
}


def test_realism_off_writes_the_ideal_simulators_bytes(tmp_path):
    for folder, kwargs in [("default", {}), ("explicit", {"realism": Realism()})]:
        files = write_scenario(tmp_path / folder, "ball", 2, size=256, **kwargs)
        got = {p.name: sha1(p) for p in [files.raw[0], files.truth[0], files.calibration_dir / "MOD_0001.RAW",
                                         files.calibration_dir / "MOD_0002.RAW"]}
        assert got == IDEAL_BALL_2_256
        assert "realism" not in json.loads(files.scenario_json.read_text())


def test_realistic_scenario_same_seed_same_bytes(tmp_path):
    a = write_scenario(tmp_path / "a", "tilted-layer", 4, size=512, realism=Realism.typical())
    b = write_scenario(tmp_path / "b", "tilted-layer", 4, size=512, realism=Realism.typical())
    c = write_scenario(tmp_path / "c", "tilted-layer", 5, size=512, realism=Realism.typical())
    for x, y in zip(a.lfp + a.raw + a.truth + a.whites + [a.scenario_json],
                    b.lfp + b.raw + b.truth + b.whites + [b.scenario_json]):
        assert x.read_bytes() == y.read_bytes(), x.name
    assert a.raw[0].read_bytes() != c.raw[0].read_bytes()
    doc = json.loads(a.scenario_json.read_text())
    assert Realism.from_dict(doc["realism"]["parameters"]) == Realism.typical()
    assert doc["realism"]["camera"]["second_stop"]["radius_m"] > 0
    assert {s["kind"] for s in doc["realism"]["chamber"]["sources"]} == {"band", "glint"}
    # The truth table keeps its columns and meaning: the ideal chief ray of the metadata's camera.
    truth = read_csv(a.truth[0])
    model = read_exposure(a.lfp[0]).model
    particles = Particles(truth["X"], truth["Y"], truth["Z"], truth["brightness"])
    assert np.allclose(particle_truth(model, particles).x_px, truth["x"], atol=1e-3)


# --- the camera's own effects --------------------------------------------------------------------


def test_blur_widens_a_points_micro_image_by_the_expected_variance():
    model = centred(96)
    z0 = model.optics.focus_distance_mm
    point = Particles(np.array([0.01]), np.array([-0.02]), np.array([z0]), np.array([1000.0]))
    variances = {}
    for sigma in (0.5, 1.2):
        image = render_exposure(model, point, seed=3, noise=False, responses=FLAT, camera=camera(blur_px=sigma))
        signal = image.astype(np.float64) - model.black_level
        ys, xs = np.mgrid[0:96, 0:96] + 0.5
        mx, my = (signal * xs).sum() / signal.sum(), (signal * ys).sum() / signal.sum()
        variances[sigma] = ((signal * (xs - mx) ** 2).sum() / signal.sum(), (signal * (ys - my) ** 2).sum() / signal.sum())
    # A Gaussian adds its variance per axis (cv2's sampled kernel: about 0.21 px^2 at 0.5 px, 1.44 at 1.2).
    for axis in (0, 1):
        assert variances[1.2][axis] - variances[0.5][axis] == pytest.approx(1.44 - 0.21, abs=0.06)
    # The white images carry the same point spread: Gaussians compose.
    sharp = camera_coverage(model, camera(blur_px=0.3))
    wide = camera_coverage(model, camera(blur_px=1.2))
    composed = cv2.GaussianBlur(sharp, (0, 0), math.sqrt(1.2 ** 2 - 0.3 ** 2), borderType=cv2.BORDER_REFLECT_101)
    assert np.abs(wide - composed).max() < 0.02 * wide.max() < np.abs(wide - sharp).max()


def test_a_halo_spreads_its_share_of_the_light_as_wide_as_asked_in_exposures_and_white_images():
    """A point spread that is no Gaussian: ``psf_halo`` of the light in a Gaussian of ``psf_halo_px``."""
    model = centred(96)
    z0 = model.optics.focus_distance_mm
    point = Particles(np.array([0.01]), np.array([-0.02]), np.array([z0]), np.array([1000.0]))
    ys, xs = np.mgrid[0:96, 0:96] + 0.5
    moments = {}
    for halo in (0.0, 0.2):
        image = render_exposure(model, point, seed=3, noise=False, responses=FLAT,
                                camera=camera(blur_px=0.8, psf_halo=halo, psf_halo_px=3.0))
        signal = image.astype(np.float64) - model.black_level
        mx, my = (signal * xs).sum() / signal.sum(), (signal * ys).sum() / signal.sum()
        moments[halo] = signal.sum(), (signal * ((xs - mx) ** 2 + (ys - my) ** 2)).sum() / signal.sum()
    assert moments[0.2][0] == pytest.approx(moments[0.0][0], rel=0.01)  # the halo moves light, adds none
    # Per axis, a mixture's variance is the weighted mean of its parts': 0.2 (3^2 - 0.8^2) more.
    assert (moments[0.2][1] - moments[0.0][1]) / 2 == pytest.approx(0.2 * (9.0 - 0.64), rel=0.05)
    # The white images carry it too.
    plain = camera_coverage(model, camera(blur_px=0.8))
    haloed = camera_coverage(model, camera(blur_px=0.8, psf_halo=0.2, psf_halo_px=3.0))
    assert haloed.sum() == pytest.approx(plain.sum(), rel=0.01) and np.abs(haloed - plain).max() > 0.05 * plain.max()
    assert Realism(psf_halo_px=5.0).is_ideal and Realism(psf_halo=0.1).effects_on() == ("blur",)
    with pytest.raises(ParameterError, match="psf_halo_px"):
        Realism(blur_px=1.2, psf_halo=0.1, psf_halo_px=1.0)


def test_second_stop_makes_corner_micro_images_cats_eyes_of_the_predicted_area():
    cam = camera(blur_px=0.3, vignetting_corner_cut=0.3, vignetting_onset=0.45)
    shapes = {}
    for label, start in [("centre", 1640 - 64), ("corner", 3280 - 128)]:
        model = window(start, start, 128)
        coverage = camera_coverage(model, cam)
        centres, m = micro_image_moments(coverage, model, margin=10)
        stop = cam.second_stop(model)
        o = model.optics
        to_px = o.mla_to_sensor_m / (o.exit_pupil_m * o.pixel_pitch_m)
        s = np.hypot(*(centres - model.lattice.origin).T) * o.pixel_pitch_m / o.projection_factor
        cos4 = (o.exit_pupil_m ** 2 / (o.exit_pupil_m ** 2 + s ** 2)) ** 2
        expected = cos4 * np.array([_circle_intersection(o.micro_image_radius_px, stop.radius_m * to_px,
                                                         stop.shift_per_m * r * to_px) for r in s])
        assert np.allclose(m[:, 0], expected, rtol=0.01)
        shapes[label] = (expected / cos4 / (math.pi * o.micro_image_radius_px ** 2), m[:, 3] / m[:, 4])
    assert np.all(shapes["centre"][0] > 0.999) and np.all(np.abs(shapes["centre"][1] - 1) < 0.03)
    # At the corner the aperture is cut to about two thirds, the cut along the radius: narrower that way.
    assert np.all(shapes["corner"][0] < 0.8) and np.all(shapes["corner"][1] < 0.8)


def _circle_intersection(r1: float, r2: float, d: float) -> float:
    if d >= r1 + r2:
        return 0.0
    if d <= abs(r1 - r2):
        return math.pi * min(r1, r2) ** 2
    a = r1 * r1 * math.acos((d * d + r1 * r1 - r2 * r2) / (2 * d * r1))
    a += r2 * r2 * math.acos((d * d + r2 * r2 - r1 * r1) / (2 * d * r2))
    return a - 0.5 * math.sqrt((-d + r1 + r2) * (d + r1 - r2) * (d - r1 + r2) * (d + r1 + r2))


def test_micro_image_response_falls_toward_the_rim_as_cos_n():
    model = centred(96)
    flat = camera_coverage(model, camera(blur_px=0.3))
    rim = camera_coverage(model, camera(blur_px=0.3, rim_response=0.6))
    cam = camera(rim_response=0.6)
    # The response of a ray at the micro-image's rim (14 degrees for f/2) is the one asked for.
    r = model.optics.micro_image_radius_px
    assert cam.pixel_response(np.array([r]), model)[0] == pytest.approx(0.6, rel=1e-6)
    _, centres = model.lattice.centres(96, 96, margin_px=12)
    got, expected = [], []
    for cx, cy in centres:
        for step in (0, 1, 2, 3):
            c, row = int(cx + step), int(cy)
            got.append(rim[row, c] / flat[row, c])
            expected.append(cam.pixel_response(np.hypot(c + 0.5 - cx, row + 0.5 - cy), model))
    got, expected = np.array(got), np.array(expected)
    assert np.abs(got - expected).max() < 0.02
    assert expected.min() < 0.8


def test_lens_transmission_and_response_appear_alike_in_white_images_and_exposures():
    """They belong to the camera: an exposure of the diffuse glow divided by the white image is flat."""
    model = centred(128)
    cam = camera(blur_px=0.9, rim_response=0.7, lens_transmission_spread=0.05,
                 vignetting_corner_cut=0.3, vignetting_onset=0.45)
    white = render_white_image(model, level=2000.0, noise=False, camera=cam).astype(np.float64) - model.black_level
    glow = render_exposure(model, Particles(*(np.zeros(0),) * 4), seed=1, background_dn=1000.0, noise=False,
                           camera=cam).astype(np.float64) - model.black_level
    lit = white > 0.5 * np.percentile(white, 95)
    ratio = glow[lit] / white[lit]
    assert np.median(ratio) == pytest.approx(0.5, rel=0.01)
    assert np.percentile(np.abs(ratio - 0.5), 99) < 0.01  # rounding only
    # The per-lens transmission spread is in the white image: a few % between lenses, as asked.
    centres, m = micro_image_moments(white / channel_response_map(128, 128, WHITE_RESPONSE), model, margin=10)
    assert np.std(m[:, 0]) / np.mean(m[:, 0]) == pytest.approx(0.05, rel=0.3)


def test_hot_pixels_are_the_cameras_same_in_white_dark_and_exposure_frames(tmp_path):
    def changed(folder_a, folder_b, name):
        a = read_exposure(folder_a / f"{name}.lfp").image if name.startswith("IMG") else \
            {w.name: w for w in load_white_images(folder_a / "calibration")}[name].image()
        b = read_exposure(folder_b / f"{name}.lfp").image if name.startswith("IMG") else \
            {w.name: w for w in load_white_images(folder_b / "calibration")}[name].image()
        return set(zip(*np.nonzero(a != b)))

    clean = tmp_path / "clean"
    write_scenario(clean, "ball", 3, size=256)
    defects = {}
    for serial, seed in [("A202160042", 3), ("A303134643", 3)]:
        folder = tmp_path / serial
        write_scenario(folder, "ball", seed, size=256, serial=serial,
                       realism=Realism(hot_pixel_fraction=1e-3, dead_pixel_fraction=2e-4))
        frames = {name: changed(clean, folder, name) for name in ("IMG_0001", "MOD_0001", "MOD_0002")}
        # The dark frame (MOD_0001), a bright white (MOD_0002) and the exposure: the same pixels.
        assert len(frames["IMG_0001"]) > 40
        union = set.union(*frames.values())
        for name, where in frames.items():
            assert len(where) >= 0.95 * len(union), name
        defects[serial] = union
        image = read_exposure(folder / "IMG_0001.lfp").image
        dark = {w.name: w for w in load_white_images(folder / "calibration")}["MOD_0001"].image()
        assert np.sum(image == 4095) >= 3 and np.sum(dark == 4095) >= 3  # stuck pixels
    # Another camera, another pattern.
    assert len(defects["A202160042"] & defects["A303134643"]) <= 2
    # Drawn on the full sensor: a crop shows the full sensor's defects where it lies.
    full = SensorDefects.draw("A202160042", hot_fraction=1e-3, dead_fraction=2e-4)
    crop = full.on_crop(256, 256)
    assert set(zip(crop.rows.tolist(), crop.cols.tolist())) == {(int(r), int(c)) for r, c in defects["A202160042"]}


def test_saturated_particles_clip_at_the_white_level():
    model = centred(128)
    z0 = model.optics.focus_distance_mm
    points = Particles(np.array([-0.05, 0.05]), np.array([0.0, 0.0]), np.array([z0, z0]), np.array([1800.0, 6000.0]))
    image = render_exposure(model, points, seed=2, camera=camera(blur_px=0.8))
    assert image.max() == 4095 and np.sum(image == 4095) > 20
    dim = render_exposure(model, points.subset(np.array([0])), seed=2, camera=camera(blur_px=0.8))
    assert dim.max() < 4095
    # The brightness spread of a scene: 12x about the median, positions as in the ideal scene.
    ideal = make_scenario("ball", 5)
    spread = make_scenario("ball", 5, brightness_spread=12.0)
    assert np.array_equal(ideal.particles.z_mm, spread.particles.z_mm)
    b = spread.particles.brightness_dn
    assert 9.0 < b.max() / b.min() <= 12.0
    assert np.median(b) == pytest.approx(1800.0, rel=0.25)
    assert np.sum(b > 4095 - 168) > 10


def test_lattice_drift_moves_the_exposures_micro_images_from_the_white_images():
    model = centred(256)
    cam = camera(lattice_drift_px=(0.3, -0.2), lattice_drift_rad=1e-3)
    white = render_white_image(model, level=2000.0, noise=False, camera=cam).astype(np.float64) - model.black_level
    glow = render_exposure(model, Particles(*(np.zeros(0),) * 4), seed=1, background_dn=2000.0, noise=False,
                           camera=cam).astype(np.float64) - model.black_level
    mosaic = channel_response_map(256, 256, WHITE_RESPONSE)
    centres, m_white = micro_image_moments(white / mosaic, model, margin=12)
    # Each measured in the cells of its own lattice, so the cells cut both alike.
    _, m_glow = micro_image_moments(glow / mosaic, model, margin=12, lattice=cam.exposure_lattice(model.lattice))
    shift = m_glow[:, 1:3] - m_white[:, 1:3]
    # The white image sits on the metadata's lattice; the exposure's is shifted and turned by the drift.
    assert np.abs(np.mean(m_white[:, 1:3] - centres, axis=0)).max() < 0.01
    assert np.mean(shift, axis=0) == pytest.approx((0.3, -0.2), abs=0.015)
    # The turn: the shift grows across the field by the rotation (x shift ~ -theta dy, y shift ~ theta dx).
    rel = centres - model.lattice.origin
    assert np.polyfit(rel[:, 0], shift[:, 1], 1)[0] == pytest.approx(1e-3, abs=2e-4)
    assert np.polyfit(rel[:, 1], shift[:, 0], 1)[0] == pytest.approx(-1e-3, abs=2e-4)
    # Exactly the white image's micro-images on the drifted lattice.
    still = camera(lattice_drift_px=(0.0, 0.0))
    moved = camera_coverage(model, still, lattice=cam.exposure_lattice(model.lattice)) * mosaic * np.float32(2000.0)
    assert np.abs(glow - moved).max() <= 0.5 + 1e-3


# --- the chamber's light -----------------------------------------------------------------------------


def test_reflections_traced_back_agree_with_forward_traced_points():
    """A glint rendered by the backward tracer equals the same light as a grid of point particles
    traced forward (camera-model.md), through a second stop, rim response and lens transmission."""
    model = window(3280 - 320, 3280 - 320, 320)
    cam = camera(vignetting_corner_cut=0.3, vignetting_onset=0.45, rim_response=0.7, lens_transmission_spread=0.03)
    o = model.optics
    z = 64.0
    to_px = o.exit_pupil_m / z * o.projection_factor / o.pixel_pitch_m
    x0, y0 = (160 - model.lattice.origin_x) / to_px, (160 - model.lattice.origin_y) / to_px
    sigma, level = 0.05, 1000.0
    glint = ExtendedSource(kind="glint", z_mm=z, x_mm=x0, y_mm=y0, sigma_mm=sigma, level_dn=level)
    back = render_reflections(model, model.lattice, ChamberLight(sources=(glint,)), cam)
    step = 0.01
    g = np.arange(-4 * sigma, 4 * sigma + 1e-9, step)
    gx, gy = (a.ravel() for a in np.meshgrid(g, g))
    radiance = level * np.exp(-0.5 * (gx ** 2 + gy ** 2) / sigma ** 2)
    cell_mm2 = math.sqrt(3) / 2 * (o.lens_pitch_m * z / o.exit_pupil_m) ** 2  # one lens cell on the source plane
    points = Particles(x0 + gx, y0 + gy, np.full(gx.size, z), radiance * step ** 2 / cell_mm2)
    forward = accumulate_particles(model, points, rng=np.random.default_rng(0), samples_per_side=40, camera=cam)
    assert back.sum() == pytest.approx(forward.sum(), rel=0.01)
    b, f = (cv2.GaussianBlur(a, (0, 0), 1.0) for a in (back, forward))
    assert np.sqrt(np.mean((b - f) ** 2)) < 0.005 * f.max()
    # All its light falls in its footprint.
    ys, xs = np.mgrid[0:320, 0:320] + 0.5
    inside = glint.covers(model, xs, ys)
    assert back[~inside].sum() < 1e-3 * back.sum()


def test_reflection_band_and_glow_gradient_in_an_exposure():
    model = centred(512)
    realism = Realism(reflection_dn=2000.0, glow_gradient=3.0)
    chamber = ChamberLight.build(realism, seed=1)
    band = chamber.sources[0]
    empty = Particles(*(np.zeros(0),) * 4)
    # A crop of the full frame: move the band into it, 12 mm behind focus.
    band = replace(band, y_mm=0.0, z_mm=72.0)
    chamber = replace(chamber, sources=(band,))
    image = render_exposure(model, empty, seed=0, background_dn=40.0, noise=False,
                            chamber=chamber).astype(np.float64) - model.black_level
    green = (np.add.outer(np.arange(512), np.arange(512)) % 2) == 1
    rows = np.array([np.percentile(image[r][green[r]], 90) for r in range(512)])
    cx, cy, reach = band.footprint_px(model)
    assert rows[int(cy)] > 500  # the band, out of focus, over the glow
    assert rows[int(cy)] > 10 * rows[int(cy - reach - 20)]
    # The glow's gradient: 3x from top to bottom of the full frame, so 3 ** (512/3280) over this crop.
    glow_only = render_exposure(model, empty, seed=0, background_dn=200.0, noise=False,
                                chamber=ChamberLight(glow_gradient=3.0)).astype(np.float64)
    top = np.percentile(glow_only[:64][green[:64]], 90)
    bottom = np.percentile(glow_only[-64:][green[-64:]], 90)
    assert (bottom - 168) / (top - 168) == pytest.approx(3 ** (448 / 3280), rel=0.03)
    # The footprint test used by the bench.
    assert chamber.on_reflection(model, np.array([cx, cx]), np.array([cy, cy - reach - 1])).tolist() == [True, False]


# --- scenes --------------------------------------------------------------------------------------


def test_varied_scenes_leave_the_defaults():
    tilts, sizes, counts = [], [], []
    for seed in range(8):
        layer = make_scenario("tilted-layer", seed, varied=True)
        tilts.append(layer.parameters["tilt_deg"])
        counts.append(len(layer.particles))
        sizes.append(make_scenario("ball", seed, varied=True).parameters["diameter_mm"])
    assert min(tilts) < 11 or max(tilts) > 15
    assert len(set(counts)) > 3 and np.ptp(sizes) > 1.0 and max(sizes) > 4.5
    kept = make_scenario("ball", 3, varied=True, centre_z_mm=57.4)
    assert kept.parameters["centre_mm"][2] == 57.4
    assert not np.array_equal(kept.particles.x_mm, make_scenario("ball", 3, centre_z_mm=57.4).particles.x_mm)


def test_cli_realism_options(tmp_path, capsys):
    out = tmp_path / "run"
    assert cli_main(["simulate", "--scenario", "ball", "--seed", "2", "--size", "256", "--out", str(out), "--quiet",
                     "--realism", "hot-pixels,blur", "--blur-px", "1.1", "--glints", "--lattice-drift-px", "0.3"]) == 0
    doc = json.loads((out / "scenario.json").read_text())["realism"]
    p = doc["parameters"]
    assert p["blur_px"] == 1.1 and p["hot_pixel_fraction"] == Realism.typical().hot_pixel_fraction
    assert p["glints"] == 2 and p["glint_dn"] > 0 and p["lattice_drift_px"] == [0.3, 0.0]
    assert p["effects"] == ["blur", "hot-pixels", "reflections", "drift"]
    assert p["reflection_dn"] == 0
    assert cli_main(["simulate", "--out", str(tmp_path / "bad"), "--size", "256", "--quiet", "--realism", "fog"]) == 2
    assert "choose from all, blur" in capsys.readouterr().err
    assert cli_main(["simulate", "--out", str(tmp_path / "bad"), "--size", "256", "--quiet", "--blur-px", "9"]) == 2
    halo = tmp_path / "halo"
    assert cli_main(["simulate", "--scenario", "ball", "--seed", "2", "--size", "256", "--out", str(halo), "--quiet",
                     "--psf-halo", "0.15", "--psf-halo-px", "2.5"]) == 0
    doc = json.loads((halo / "scenario.json").read_text())["realism"]
    assert doc["parameters"]["effects"] == ["blur"] and doc["camera"]["halo"] == {"fraction": 0.15, "sigma_px": 2.5}


def test_false_particles_on_a_reflection_are_counted():
    from analysis.simulation.scoring import false_on_reflection

    model = CameraModel.from_metadata(simulated_camera_metadata())
    chamber = ChamberLight.build(Realism(reflection_dn=2000.0), seed=3)
    band = chamber.sources[0]
    truth = {"X": np.array([0.0, 1.0]), "Y": np.array([0.0, -1.0]), "Z": np.array([60.0, 60.5])}
    # Found: both true ones, one false particle on the band's line of sight (at another depth), one far off it.
    on_band_y = band.y_mm * 61.0 / band.z_mm
    found = {"X": np.array([0.0, 1.0, 2.0, 2.0]), "Y": np.array([0.0, -1.0, on_band_y, -4.0]),
             "Z": np.array([60.0, 60.5, 61.0, 61.0])}
    assert false_on_reflection(found, truth, chamber, model) == 1
    assert false_on_reflection(found, truth, ChamberLight(), model) == 0
    doc = json.loads(json.dumps(chamber.to_dict(model)))
    assert ChamberLight.from_dict(doc) == chamber


def test_recall_is_split_by_whether_a_reflections_light_falls_on_the_particle():
    from analysis.simulation.scoring import recall_in_reflections

    model = CameraModel.from_metadata(simulated_camera_metadata())
    chamber = ChamberLight.build(Realism(reflection_dn=2000.0), seed=3)
    band = chamber.sources[0]
    on_band_y = band.y_mm * 60.0 / band.z_mm
    # Three true particles on the band's line of sight, two far off it; one of each kind found.
    truth = {"X": np.array([0.0, 1.0, 2.0, 0.0, 1.0]), "Y": np.array([on_band_y] * 3 + [-4.0, -4.5]),
             "Z": np.full(5, 60.0)}
    found = {c: truth[c][[1, 4]] for c in "XYZ"}
    split = recall_in_reflections(found, truth, chamber, model)
    assert (split.true_in, split.found_in, split.true_out, split.found_out) == (3, 1, 2, 1)
    assert recall_in_reflections(found, truth, ChamberLight(), model).true_in == 0
