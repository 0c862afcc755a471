"""The simulator against the camera model it must obey (camera-model.md)."""

from __future__ import annotations

import csv
import json
from dataclasses import replace

import numpy as np
import pytest

from analysis.simulation.kernels import paint_disks
from analysis.camera.model import CameraModel
from analysis.formats.exposure import read_exposure
from analysis.simulation.scenarios import SCENARIO_NAMES, Particles, make_scenario
from analysis.simulation.camera import (DEFAULT_LENS, ELECTRONS_PER_DN, LASER_532_RESPONSE, READ_NOISE_DN,
    WHITE_RESPONSE, simulated_camera_metadata)
from analysis.simulation.render import (accumulate_particles, channel_response_map, in_view, particle_truth,
    read_out, render_exposure, render_white_image, white_coverage)
from analysis.simulation.scenario_files import write_scenario
from analysis.formats.whites import load_white_images
from service.cli.main import main as cli_main


def small_model(size: int = 256) -> CameraModel:
    return CameraModel.from_metadata(simulated_camera_metadata(size=size))


def micro_image_centroids(image: np.ndarray, model: CameraModel, *, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Intensity centroid of each micro-image fully on the sensor, and the model's centre."""
    radius = model.optics.micro_image_radius_px
    _, centres = model.lattice.centres(model.width, model.height, margin_px=margin)
    rows, cols = np.mgrid[0:model.height, 0:model.width]
    found = []
    for cx, cy in centres:
        c0, c1 = int(cx - radius - 1), int(cx + radius + 2)
        r0, r1 = int(cy - radius - 1), int(cy + radius + 2)
        patch = image[r0:r1, c0:c1]
        xs = cols[r0:r1, c0:c1] + 0.5
        ys = rows[r0:r1, c0:c1] + 0.5
        inside = (xs - cx) ** 2 + (ys - cy) ** 2 <= (radius + 1.0) ** 2
        w = np.where(inside, patch, 0.0)
        found.append((np.sum(w * xs) / w.sum(), np.sum(w * ys) / w.sum()))
    return np.array(found), centres


def test_white_micro_images_centred_on_model_lattice():
    model = small_model(256)
    raw = render_white_image(model, level=2400.0, noise=False).astype(np.float64)
    # Undo black and the Bayer responses so each micro-image is the plain disk it should be.
    signal = (raw - model.black_level) / channel_response_map(model.height, model.width, WHITE_RESPONSE)
    found, centres = micro_image_centroids(signal, model, margin=8.0)
    err = np.hypot(*(found - centres).T)
    assert len(centres) > 400
    assert err.mean() < 0.05
    assert err.max() < 0.1


def test_white_noisy_green_centroids_and_level():
    model = small_model(256)
    raw = render_white_image(model, level=2400.0, seed=3).astype(np.float64)
    green = (np.add.outer(np.arange(model.height), np.arange(model.width)) % 2) == 1
    signal = np.where(green, raw - model.black_level, 0.0)
    found, centres = micro_image_centroids(signal, model, margin=8.0)
    assert np.hypot(*(found - centres).T).mean() < 0.15
    # Fully lit green pixels at the micro-image centres carry the requested level (cos^4 ~ 1 here).
    cx = np.floor(centres[:, 0]).astype(int)
    cy = np.floor(centres[:, 1]).astype(int)
    cx += (cx + cy) % 2 == 0  # step onto a green site
    assert np.median(raw[cy, cx] - model.black_level) == pytest.approx(2400.0, rel=0.02)


def test_white_image_falls_off_as_cos4_toward_the_corner():
    full = CameraModel.from_metadata(simulated_camera_metadata())
    start = full.width - 128  # a 128 px window in the bottom-right corner of the full sensor
    corner = replace(full, width=128, height=128,
                     lattice=full.lattice.with_changes(origin_x=full.lattice.origin_x - start,
                                                       origin_y=full.lattice.origin_y - start))
    cov = white_coverage(corner)
    ij, centres = corner.lattice.centres(128, 128, margin_px=8.0)
    s, t = corner.lens_plane_position_m(ij[:, 0], ij[:, 1])
    p_m = corner.optics.exit_pupil_m
    cos4 = (p_m ** 2 / (p_m ** 2 + s ** 2 + t ** 2)) ** 2
    assert cos4.max() < 0.97  # the fall-off is there to see
    # The centre pixel of each micro-image is fully lit: its value is the chief ray's cos^4.
    centre_values = cov[centres[:, 1].astype(int), centres[:, 0].astype(int)]
    assert np.allclose(centre_values, cos4, rtol=2e-3)


def test_white_image_deterministic_per_seed():
    model = small_model(128)
    a = render_white_image(model, seed=7)
    assert a.dtype == np.uint16
    assert np.array_equal(a, render_white_image(model, seed=7))
    assert not np.array_equal(a, render_white_image(model, seed=8))


# --- particles through the optics -------------------------------------------------------------


HEX_CELL_AREA = np.sqrt(3) / 2  # lens cell area in pitch^2


def one_particle(x_mm: float, y_mm: float, z_mm: float, brightness: float = 2000.0) -> Particles:
    return Particles(np.array([x_mm]), np.array([y_mm]), np.array([z_mm]), np.array([brightness]))


def light_per_lens(model: CameraModel, signal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sum of ``signal`` per lens (each pixel to its nearest micro-image centre): centres x, y and sums."""
    rows, cols = np.nonzero(signal > 0)
    i, j = model.lattice.nearest(cols + 0.5, rows + 0.5)
    keys, inverse = np.unique(np.stack([i, j], axis=1), axis=0, return_inverse=True)
    sums = np.bincount(inverse.ravel(), weights=signal[rows, cols])
    cx, cy = model.lattice.centre(keys[:, 0], keys[:, 1])
    return cx, cy, sums


def test_in_focus_particle_lights_one_lens_at_its_image_position():
    model = small_model(256)
    rng = np.random.default_rng(11)
    z0 = model.optics.focus_distance_mm
    for _ in range(5):
        # A point at the focus distance, somewhere on the crop.
        x_px, y_px = rng.uniform(60, 196, size=2)
        scale = model.optics.exit_pupil_m / z0 * model.optics.projection_factor / model.optics.pixel_pitch_m
        p = one_particle((x_px - model.lattice.origin_x) / scale, (y_px - model.lattice.origin_y) / scale, z0)
        truth = particle_truth(model, p)
        assert truth.alpha[0] == pytest.approx(1.0, abs=1e-12)
        assert truth.blur_pitches[0] == pytest.approx(0.0, abs=1e-9)
        assert (truth.x_px[0], truth.y_px[0]) == pytest.approx((x_px, y_px), abs=1e-9)
        signal = accumulate_particles(model, p, rng=np.random.default_rng(1))
        cx, cy, sums = light_per_lens(model, signal)
        brightest = np.argmax(sums)
        assert sums[brightest] / sums.sum() > 0.999
        ei, ej = model.lattice.nearest(x_px, y_px)
        assert (cx[brightest], cy[brightest]) == pytest.approx(model.lattice.centre(ei, ej), abs=1e-9)
        # The whole aperture disk lands behind that lens: radius (D/2) d / P, each pixel inside
        # at the particle's brightness (cos^4 is within 0.2 % of 1 on this crop).
        r = model.optics.micro_image_radius_px
        assert signal.sum() == pytest.approx(2000.0 * np.pi * r * r, rel=0.005)
        rows, cols = np.nonzero(signal > 0)
        dist = np.hypot(cols + 0.5 - cx[brightest], rows + 0.5 - cy[brightest])
        assert dist.max() < r + 0.75
        inner = signal[rows[dist < r - 0.75], cols[dist < r - 0.75]]
        assert inner.mean() == pytest.approx(2000.0, rel=0.005)
        assert inner.std() < 0.1 * 2000.0


@pytest.mark.parametrize("blur_target", [3.0, 6.0])
def test_defocused_particle_spreads_over_predicted_blur_disk(blur_target: float):
    model = small_model(320)
    optics = model.optics
    pitch = model.lattice.pitch_px
    # Depth whose blur diameter D |Fp - P| / Fp is blur_target pitches (nearer than focus: Fp > P).
    fp = optics.exit_pupil_m / (1 - blur_target * optics.lens_pitch_m / optics.aperture_diameter_m)
    z_mm = 1e3 / (1 / optics.focal_length_m - 1 / fp)
    radius = blur_target / 2
    perimeter = 6 / np.sqrt(3)
    steiner = (HEX_CELL_AREA + perimeter * radius + np.pi * radius ** 2) / HEX_CELL_AREA
    counts = []
    for x_mm, y_mm in np.random.default_rng(12).uniform(-0.06, 0.06, size=(8, 2)):
        p = one_particle(x_mm, y_mm, z_mm)
        truth = particle_truth(model, p)
        assert truth.blur_pitches[0] == pytest.approx(blur_target, rel=1e-9)
        signal = accumulate_particles(model, p, rng=np.random.default_rng(2))
        cx, cy, sums = light_per_lens(model, signal)
        dx = (cx - truth.x_px[0]) / pitch
        dy = (cy - truth.y_px[0]) / pitch
        w = sums / sums.sum()
        # Light-weighted centre of the lit lenses is the ideal image position ...
        assert abs(np.sum(w * dx)) < 0.1 and abs(np.sum(w * dy)) < 0.1
        # ... their spread that of a uniform disk of the predicted diameter (<r^2> = R^2/2) plus
        # the hex cell's own second moment (5/36 pitch^2; additive once the disk spans cells) ...
        rms = np.sqrt(np.sum(w * (dx ** 2 + dy ** 2)))
        assert rms == pytest.approx(np.sqrt(radius ** 2 / 2 + 5 / 36), rel=0.05)
        # ... and every lit lens touches the disk (centre within R + the cell's circumradius).
        assert np.hypot(dx, dy).max() < radius + 1 / np.sqrt(3)
        counts.append(np.count_nonzero(w > 0))
    # Lit lenses: on average the Steiner count of hex cells meeting a disk, (A + per R + pi R^2) / A
    # (fewer where the disk sits symmetrically on a cell corner).
    assert np.mean(counts) == pytest.approx(steiner, rel=0.05)
    assert np.all(np.abs(np.array(counts) / steiner - 1) < 0.25)


@pytest.mark.parametrize("blur_target, side", [(3.0, 1), (3.0, -1), (6.0, 1), (6.0, -1)])
def test_camera_model_lookup_refocuses_simulated_light_at_the_truth(blur_target: float, side: int):
    """camera-model.md's look-up table read on simulated pixels: each lit pixel's lens centre
    ``s`` and aperture point ``u`` define a ray; the plane ``alpha P`` where those rays meet
    best (least squares) and the point where they meet are the particle's truth."""
    model = small_model(320)
    o = model.optics
    fp = o.exit_pupil_m / (1 - side * blur_target * o.lens_pitch_m / o.aperture_diameter_m)
    p = one_particle(0.04, -0.02, 1e3 / (1 / o.focal_length_m - 1 / fp))
    truth = particle_truth(model, p)
    signal = accumulate_particles(model, p, rng=np.random.default_rng(3))
    rows, cols = np.nonzero(signal > 0)
    x, y = cols + 0.5, rows + 0.5
    u = np.stack(model.aperture_coordinates(x, y), axis=1)
    i, j, _, _ = model.micro_image_offsets(x, y)
    a = np.stack(model.lens_plane_position_m(i, j), axis=1) - u   # ray direction per unit alpha
    w = signal[rows, cols].astype(np.float64)
    w /= w.sum()
    du, da = u - w @ u, a - w @ a
    alpha = -np.sum(w[:, None] * du * da) / np.sum(w[:, None] * da * da)
    meet = (w @ u + alpha * (w @ a)) / alpha * o.projection_factor / o.pixel_pitch_m  # chief ray on the MLA, px
    assert alpha == pytest.approx(truth.alpha[0], abs=3e-4)
    assert meet[0] + model.lattice.origin_x == pytest.approx(truth.x_px[0], abs=0.1)
    assert meet[1] + model.lattice.origin_y == pytest.approx(truth.y_px[0], abs=0.1)


def test_green_sites_see_the_laser_red_and_blue_little():
    model = small_model(128)
    p = one_particle(0.0, 0.0, model.optics.focus_distance_mm)
    raw = render_exposure(model, p, seed=4, noise=False).astype(np.float64) - model.black_level
    rows, cols = np.mgrid[0:128, 0:128]
    # The core of the in-focus micro-image (away from the rim, where the blur mixes levels).
    core = np.hypot(cols + 0.5 - model.lattice.origin_x, rows + 0.5 - model.lattice.origin_y) < 2.5
    green = (rows + cols) % 2 == 1
    red = (rows % 2 == 1) & (cols % 2 == 1)
    blue = (rows % 2 == 0) & (cols % 2 == 0)
    g = raw[core & green].mean()
    assert g == pytest.approx(2000.0, rel=0.05)
    assert raw[core & red].mean() / g == pytest.approx(LASER_532_RESPONSE["r"], abs=0.01)
    assert raw[core & blue].mean() / g == pytest.approx(LASER_532_RESPONSE["b"], abs=0.01)
    # Nothing but that one micro-image is lit.
    assert np.count_nonzero(raw > 5) < 100


def test_paint_disks_matches_brute_force_coverage():
    rng = np.random.default_rng(5)
    cx = rng.uniform(6, 26, 4)
    cy = rng.uniform(6, 26, 4)
    value = rng.uniform(0.5, 2.0, 4)
    radius = 4.3
    got = np.zeros((32, 32))
    paint_disks(got, cx, cy, value, radius, 12)
    fine = 40
    sub = (np.arange(32 * fine) + 0.5) / fine
    yy, xx = np.meshgrid(sub, sub, indexing="ij")
    ref = np.zeros((32 * fine, 32 * fine))
    for x0, y0, v in zip(cx, cy, value):
        ref += v * ((xx - x0) ** 2 + (yy - y0) ** 2 <= radius ** 2)
    ref = ref.reshape(32, fine, 32, fine).mean(axis=(1, 3))
    # 12 x 12 rim supersampling: a few 1/144 steps of coverage per pixel at most.
    assert np.abs(got - ref).max() < 0.03 * value.max()
    assert got.sum() == pytest.approx(ref.sum(), rel=1e-3)


def test_readout_noise_statistics():
    expected = np.full((200, 200), 1000.0, dtype=np.float32)
    out = read_out(expected, black=168.0, white=4095.0, rng=np.random.default_rng(0)).astype(np.float64)
    assert out.mean() == pytest.approx(1168.0, abs=0.5)
    assert out.var() == pytest.approx(1000.0 / ELECTRONS_PER_DN + READ_NOISE_DN ** 2 + 1 / 12, rel=0.03)
    clipped = read_out(np.full((4, 4), 9000.0, dtype=np.float32), black=168.0, white=4095.0, rng=None)
    assert np.all(clipped == 4095)


def test_exposure_deterministic_per_seed():
    model = small_model(128)
    p = one_particle(0.02, 0.01, 59.5)
    a = render_exposure(model, p, seed=3, background_dn=20.0)
    assert np.array_equal(a, render_exposure(model, p, seed=3, background_dn=20.0))
    assert not np.array_equal(a, render_exposure(model, p, seed=4, background_dn=20.0))


# --- scenarios ---------------------------------------------------------------------------------

def test_tilted_layer_geometry():
    s = make_scenario("tilted-layer", 5)
    p = s.particles
    assert 50 <= len(p) <= 70
    xyz = np.stack([p.x_mm, p.y_mm, p.z_mm], axis=1)
    centred = xyz - xyz.mean(axis=0)
    normal = np.linalg.svd(centred)[2][-1]
    tilt = np.degrees(np.arccos(abs(normal[2])))
    assert tilt == pytest.approx(13.0, abs=0.3)
    # Extent in the layer: about 14 mm across.
    in_plane = centred - np.outer(centred @ normal, normal)
    assert 11.0 < 2 * np.linalg.norm(in_plane, axis=1).max() <= 14.5


def test_shadowing_pairs_share_a_line_of_sight():
    s = make_scenario("shadowing", 6)
    model = CameraModel.from_metadata(simulated_camera_metadata())
    truth = particle_truth(model, s.particles)
    pairs = np.array(s.parameters["shadowing_pairs"])
    assert len(pairs) >= 5
    a, b = pairs[:, 0], pairs[:, 1]
    sep_px = np.hypot(truth.x_px[a] - truth.x_px[b], truth.y_px[a] - truth.y_px[b])
    assert np.all(sep_px < 2.0 * model.lattice.pitch_px)
    assert np.all(np.abs(s.particles.z_mm[a] - s.particles.z_mm[b]) >= 0.99)
    assert np.all(np.abs(truth.alpha[a] - truth.alpha[b]) > 0.004)


def test_ball_geometry():
    p = make_scenario("ball", 7).particles
    assert len(p) == 150
    xyz = np.stack([p.x_mm, p.y_mm, p.z_mm], axis=1)
    r = np.linalg.norm(xyz - xyz.mean(axis=0), axis=1)
    assert 1.8 < r.max() < 2.3
    assert np.ptp(p.z_mm) > 3.0  # truly 3D, not a layer


@pytest.mark.parametrize("name", [n for n in SCENARIO_NAMES if n != "cloud"])
def test_scenarios_fit_refocus_range_and_sensor(name: str):
    model = CameraModel.from_metadata(simulated_camera_metadata())
    for seed in range(12):
        s = make_scenario(name, seed)
        truth = particle_truth(model, s.particles)
        # Well inside the default refocus range 0.987 ... 1.013, spread over a good part of it.
        assert truth.alpha.min() > 0.989 and truth.alpha.max() < 1.011
        assert np.ptp(truth.alpha) > 0.010
        # From sharp to several pitches of blur.
        assert truth.blur_pitches.min() < 0.5 and truth.blur_pitches.max() > 3.0
        assert np.all(in_view(model, truth))
        # In-focus particles bright but unsaturated.
        assert np.max(s.particles.brightness_dn) + s.background_dn < model.white_level - model.black_level
    s = make_scenario(name, 8)
    assert np.array_equal(s.particles.z_mm, make_scenario(name, 8).particles.z_mm)
    assert not np.array_equal(s.particles.z_mm, make_scenario(name, 9).particles.z_mm)
    assert DEFAULT_LENS.focus_distance_mm == pytest.approx(model.optics.focus_distance_mm)


def test_cloud_fills_an_ellipsoid_in_front_of_focus():
    model = CameraModel.from_metadata(simulated_camera_metadata())
    for seed in range(4):
        s = make_scenario("cloud", seed)
        p = s.particles
        assert len(p) == 400
        xyz = np.stack([p.x_mm, p.y_mm, p.z_mm], axis=1)
        gaps = np.linalg.norm(xyz[:, None] - xyz[None], axis=2) + np.eye(400) * 99
        assert gaps.min() >= 0.5 - 1e-9  # the hard core
        assert 9.0 < np.ptp(p.x_mm) <= 10.0 and 6.0 < np.ptp(p.y_mm) <= 7.0 and 3.2 < np.ptp(p.z_mm) <= 4.0
        truth = particle_truth(model, p)
        # In front of focus (alpha > 1), every particle within the off-focus range 0.999 ... 1.026.
        assert truth.alpha.min() > 1.0 and truth.alpha.max() < 1.026
        assert np.all(in_view(model, truth))


# --- files ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    return write_scenario(out, "shadowing", 21, count=2, size=1024)


def read_truth(path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_written_files_parse_with_the_format_readers(written):
    files = written
    lfp = read_exposure(files.lfp[0])
    pair = read_exposure(files.raw[0])
    assert np.array_equal(lfp.image, pair.image)
    assert lfp.sha1 == pair.sha1
    assert lfp.serial == pair.serial == "A202160042"
    model = CameraModel.from_metadata(lfp.metadata)
    assert (model.width, model.height) == (1024, 1024)
    assert model == CameraModel.from_metadata(simulated_camera_metadata(size=1024))
    # The truth table lists exactly the particles rendered on the crop, with their truth.
    doc = json.loads(files.scenario_json.read_text())
    rows = read_truth(files.truth[0])
    assert len(rows) == doc["exposures"][0]["particles_in_view"] > 5
    # A run (count 2) also has each particle's velocity and shell.
    assert list(rows[0]) == ["particle", "X", "Y", "Z", "alpha", "x", "y", "blur_pitches", "brightness",
                             "vX", "vY", "vZ", "shell"]
    scenario = make_scenario("shadowing", 21)
    k = int(rows[0]["particle"])
    assert float(rows[0]["Z"]) == pytest.approx(scenario.particles.z_mm[k], abs=1e-6)
    # Each listed particle shows up in the image where the truth says.
    image = lfp.image.astype(np.float64) - model.black_level
    for row in rows:
        x, y = int(float(row["x"])), int(float(row["y"]))
        reach = int((float(row["blur_pitches"]) / 2 + 1) * model.lattice.pitch_px)
        patch = image[max(y - reach, 0):y + reach, max(x - reach, 0):x + reach]
        assert patch.max() > 300
    # The second exposure, a second later on the metadata clock, shows (nearly) the same particles,
    # moved a little; its truth has their velocities.
    rows2 = {r["particle"]: r for r in read_truth(files.truth[1])}
    both = [r for r in rows if r["particle"] in rows2]
    assert len(both) >= 0.9 * len(rows)
    dz = [float(rows2[r["particle"]]["Z"]) - float(r["Z"]) for r in both]
    assert 0 < np.std(dz) < 0.1
    step = np.array([[float(rows2[r["particle"]][c]) - float(r[c]) for c in "XYZ"] for r in both])
    velocity = np.array([[float(rows2[r["particle"]][f"v{c}"]) for c in "XYZ"] for r in both])
    assert np.median(np.linalg.norm(step - velocity * 1.0, axis=1)) < np.median(np.linalg.norm(step, axis=1))
    times = [read_exposure(p).metadata["devices"]["clock"]["zuluTime"] for p in files.lfp]
    assert times == ["2021-06-01T09:00:00.000Z", "2021-06-01T09:00:01.000Z"]


def test_written_calibration_folder(written):
    whites = load_white_images(written.calibration_dir)
    assert [w.name for w in whites] == [f"MOD_{i:04d}" for i in range(5)]
    assert {w.serial for w in whites} == {"A202160042"}
    picture = read_exposure(written.lfp[0])
    zoom = picture.metadata["devices"]["lens"]["zoomStep"]
    same_zoom = [w for w in whites if w.zoom_step == zoom]
    assert len(same_zoom) == 4 and len({w.focus_step for w in same_zoom}) == 3
    means = {w.name: float(w.image().mean()) for w in whites}
    dark = [name for name, m in means.items() if m < 500]
    assert len(dark) == 1
    assert [w for w in whites if w.name == dark[0]][0].exposure_duration_s < min(
        w.exposure_duration_s for w in whites if w.name != dark[0])
    other = [w for w in whites if w.zoom_step != zoom]
    assert len(other) == 1
    other_model = CameraModel.from_metadata(other[0].metadata)
    assert other_model.lattice.pitch_px != picture.model.lattice.pitch_px
    # The white image at the picture's zoom and focus has its micro-images on the picture's lattice.
    match = [w for w in same_zoom if w.focus_step == picture.metadata["devices"]["lens"]["focusStep"]
             and w.name not in dark][0]
    model = picture.model
    green = (np.add.outer(np.arange(1024), np.arange(1024)) % 2) == 1
    signal = np.where(green, match.image().astype(np.float64) - model.black_level, 0.0)
    found, centres = micro_image_centroids(signal[300:700, 300:700], _shifted(model, -300), margin=8.0)
    assert np.hypot(*(found - centres).T).mean() < 0.15


def _shifted(model: CameraModel, by: float) -> CameraModel:
    """The model of a 400 px window starting ``-by`` px into the sensor."""
    lat = model.lattice.with_changes(origin_x=model.lattice.origin_x + by, origin_y=model.lattice.origin_y + by)
    return replace(model, lattice=lat, width=400, height=400)


def test_write_scenario_deterministic_per_seed(tmp_path):
    a = write_scenario(tmp_path / "a", "tilted-layer", 5, size=256)
    b = write_scenario(tmp_path / "b", "tilted-layer", 5, size=256)
    c = write_scenario(tmp_path / "c", "tilted-layer", 6, size=256)
    for x, y in zip(a.lfp + a.raw + a.truth + a.whites, b.lfp + b.raw + b.truth + b.whites):
        assert x.read_bytes() == y.read_bytes(), x.name
    assert a.raw[0].read_bytes() != c.raw[0].read_bytes()


def test_full_frame_truth_lists_every_particle():
    model = CameraModel.from_metadata(simulated_camera_metadata())
    for name in SCENARIO_NAMES:
        particles = make_scenario(name, 3).particles
        assert np.all(in_view(model, particle_truth(model, particles)))


def test_cli_simulate_writes_the_layout(tmp_path, capsys):
    out = tmp_path / "run"
    assert cli_main(["simulate", "--scenario", "ball", "--seed", "4", "--out", str(out), "--size", "256",
                     "--quiet"]) == 0
    for name in ["IMG_0001.lfp", "IMG_0001.RAW", "IMG_0001.TXT", "IMG_0001.truth.csv", "scenario.json",
                 "calibration/MOD_0000.RAW", "calibration/MOD_0000.TXT"]:
        assert (out / name).is_file(), name
    assert capsys.readouterr().out.strip().endswith("scenario.json")
    assert cli_main(["simulate", "--out", str(tmp_path / "bad"), "--size", "250", "--quiet"]) == 2
    assert "multiple of 4" in capsys.readouterr().err


def test_glow_and_brightness_options(tmp_path):
    dark = read_exposure(write_scenario(tmp_path / "d", "ball", 2, size=256, background_dn=0.0).lfp[0])
    glow = read_exposure(write_scenario(tmp_path / "g", "ball", 2, size=256, background_dn=200.0,
                                        brightness_dn=900.0).lfp[0])
    green = (np.add.outer(np.arange(256), np.arange(256)) % 2) == 1
    black = dark.model.black_level
    assert np.median(dark.image[green]) == pytest.approx(black, abs=1)
    # The glow fills the micro-images like a white image: about 200 DN where a disk is fully lit.
    assert np.percentile(glow.image[green], 60) - black == pytest.approx(200.0, rel=0.1)
    # Particle light scales with the brightness asked for (900 vs the default 1800), glow aside.
    lit_dark = np.percentile(dark.image.astype(np.float64) - black, 99.9)
    lit_glow = np.percentile(glow.image.astype(np.float64) - black, 99.9) - 200.0
    assert lit_glow / lit_dark == pytest.approx(0.5, abs=0.03)


def test_particles_nearer_than_the_focal_length_are_refused():
    from analysis.errors import ParameterError
    model = small_model(64)
    with pytest.raises(ParameterError, match="focal length"):
        render_exposure(model, one_particle(0.0, 0.0, 5.0), seed=0)


def test_cluster_placed_off_focus_lights_no_single_lens(tmp_path):
    """--centre-z moves the cluster: a ball 2.6 mm in front of focus has every blur above a pitch."""
    from analysis.simulation.scoring import single_lens
    from analysis.formats.particle_table import read_csv

    assert cli_main(["simulate", "--scenario", "ball", "--seed", "2", "--size", "1200", "--centre-z", "57.4",
                     "--out", str(tmp_path), "--quiet"]) == 0
    truth = read_csv(tmp_path / "IMG_0001.truth.csv")
    assert truth["Z"].size > 10
    assert abs(np.mean(truth["Z"]) - 57.4) < 1.0 and np.all(truth["alpha"] > 1.0)
    assert np.all(truth["blur_pitches"] > 1.0)
    lattice = read_exposure(tmp_path / "IMG_0001.lfp").model.lattice
    assert not single_lens(truth, lattice).any()


def test_the_motion_turns_with_spin_and_the_plate_with_rotation() -> None:
    # The merge of the target plate's --rotation and the motion's turn: both reach their own setting.
    from analysis.simulation.dynamics import Motion
    from service.cli.main import build_parser
    from service.cli.simulate import motion_from_args, optics_from_args

    args = build_parser("simulate").parse_args(
        ["simulate", "--out", "x", "--scenario", "target", "--spin", "5", "--rotation", "10", "--positions", "60"])
    assert motion_from_args(args).rotation_deg_per_s == 5.0
    assert optics_from_args(args)[1].rotation_deg == 10.0
    assert motion_from_args(build_parser("simulate").parse_args(["simulate", "--out", "x"])).rotation_deg_per_s \
        == Motion().rotation_deg_per_s
