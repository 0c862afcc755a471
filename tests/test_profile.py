"""The optical blur and micro-image response fitted to white images of a camera the fit was not told about."""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from analysis.calibration.calibrate import DEFAULT_BLUR_PX, calibrate
from analysis.calibration.lattice_fit import fit_lattice
from analysis.calibration.profile import fit_micro_image_profile, micro_image_template
from analysis.camera.model import CameraModel
from analysis.errors import CalibrationError
from analysis.formats.whites import WhiteImage
from analysis.simulation.camera import simulated_camera_metadata, simulated_private_metadata
from analysis.simulation.camera_effects import CameraEffects
from analysis.simulation.realism import Realism
from analysis.simulation.realism_kernels import paint_micro_images
from analysis.simulation.render import read_out, render_white_image

FULL = CameraModel.from_metadata(simulated_camera_metadata())
SERIAL = "A202160042"


def window(start_x: float, start_y: float, size: int) -> CameraModel:
    """A ``size`` px window of the full sensor at ``(start_x, start_y)`` (optical axis where it is)."""
    lat = FULL.lattice.with_changes(origin_x=FULL.lattice.origin_x - start_x, origin_y=FULL.lattice.origin_y - start_y)
    return replace(FULL, width=size, height=size, lattice=lat)


def centred(size: int) -> CameraModel:
    return window((3280 - size) / 2, (3280 - size) / 2, size)


def effective_sigma(sigma: float) -> float:
    """Standard deviation of the sampled kernel the simulator blurs with (cv2's, for float32 images):
    a few taps at integer offsets, narrower than ``sigma`` below about 0.7 px."""
    kernel = cv2.getGaussianKernel(int(round(sigma * 8 + 1)) | 1, sigma).ravel()
    x = np.arange(kernel.size) - kernel.size // 2
    return math.sqrt(float((kernel * x * x).sum()))


def continuous_white(model: CameraModel, sigma: float, *, seed: int = 0, level: float = 2400.0,
                     oversample: int = 8) -> np.ndarray:
    """A white image with a truly continuous Gaussian blur: micro-images (the aperture's disk) drawn on a
    grid ``oversample`` times finer, blurred there (well sampled), then integrated over each pixel."""
    fine = np.zeros((model.height * oversample, model.width * oversample), dtype=np.float32)
    ij, centres = model.lattice.centres(model.width, model.height, margin_px=-8.0)
    n = len(ij)
    paint_micro_images(fine, np.ascontiguousarray(centres[:, 0] * oversample),
                       np.ascontiguousarray(centres[:, 1] * oversample), np.ones(n),
                       model.optics.micro_image_radius_px * oversample, np.zeros(n), np.zeros(n), math.inf, 0.0, 0.0, 4)
    fine = cv2.GaussianBlur(fine, (0, 0), sigmaX=sigma * oversample, sigmaY=sigma * oversample,
                            borderType=cv2.BORDER_REFLECT_101)
    coverage = fine.reshape(model.height, oversample, model.width, oversample).mean(axis=(1, 3))
    return read_out(coverage * np.float32(level), black=model.black_level, white=model.white_level,
                    rng=np.random.default_rng(seed))


def fit(raw: np.ndarray, model: CameraModel, **kwargs):
    lattice = fit_lattice(raw, model.lattice, black_level=model.black_level).lattice
    return fit_micro_image_profile(raw, lattice, black_level=model.black_level,
                                   radius_px=model.optics.micro_image_radius_px, **kwargs)


def test_template_keeps_the_light_and_puts_half_of_it_at_the_rim():
    for blur in (0.0, 0.5, 1.5):
        t = micro_image_template(blur, 4.0, 1.0, half_width_px=12.0, step_px=1 / 16)
        assert t.sum() * (1 / 16) ** 2 == pytest.approx(math.pi * 16.0, rel=2e-3)   # blur moves light, keeps it
        big = micro_image_template(blur, 40.0, 1.0, half_width_px=48.0, step_px=1 / 8)
        n = big.shape[0]
        assert big[n // 2, n // 2 + 320] == pytest.approx(0.5, abs=0.01)            # at a gentle rim: half
    t = micro_image_template(0.5, 4.0, 1.0, half_width_px=12.0, step_px=1 / 16)
    n = t.shape[0]
    falling = micro_image_template(0.5, 4.0, 0.6, half_width_px=12.0, step_px=1 / 16)
    # rim ** (r / R)^2, averaged over the pixel and the blur (they add 2 (1/12 + 0.5^2) to r^2 on average).
    spread = 2 * (1 / 12 + 0.25)
    assert falling[n // 2, n // 2] == pytest.approx(0.6 ** (spread / 16), abs=2e-3)
    assert falling[n // 2, n // 2 + 32] == pytest.approx(0.6 ** ((4 + spread) / 16), abs=3e-3)


@pytest.mark.parametrize("sigma", [0.3, 0.5, 0.8, 1.2])
def test_blur_of_a_continuous_gaussian_is_recovered(sigma):
    model = centred(256)
    profile = fit(continuous_white(model, sigma, seed=int(10 * sigma)), model)
    assert profile.blur_px == pytest.approx(sigma, abs=0.03)
    assert profile.radius_px == pytest.approx(model.optics.micro_image_radius_px, abs=0.03)
    assert profile.rim_response == pytest.approx(1.0, abs=0.03)


@pytest.mark.parametrize("blur", [0.3, 0.5, 0.8, 1.2, 1.5])
@pytest.mark.parametrize("micro_images", [False, True])
def test_blur_of_the_realistic_camera_is_recovered(blur, micro_images):
    """The simulator blurs with cv2's sampled kernel: from 0.8 px up it is a Gaussian of that sigma; below,
    a few taps narrower than it (0.3 px: 0.09 px), which the fit sees as a Gaussian narrower still."""
    extra = dict(rim_response=0.75, lens_transmission_spread=0.03) if micro_images else {}
    model = centred(512)
    camera = CameraEffects.build(Realism(blur_px=blur, **extra), serial=SERIAL)
    profile = fit(render_white_image(model, seed=3, camera=camera), model)
    truth = effective_sigma(blur)
    assert profile.blur_px == pytest.approx(truth, abs=0.03 if blur >= 0.8 else 0.08)
    assert profile.radius_px == pytest.approx(model.optics.micro_image_radius_px, abs=0.03)
    assert profile.rim_response == pytest.approx(0.75 if micro_images else 1.0, abs=0.05)
    assert profile.lens_gain_spread == pytest.approx(0.03 if micro_images else 0.0, abs=0.006)
    assert 0 < profile.blur_std_px < 0.02


def test_a_second_stop_does_not_bias_the_blur():
    """The micro-images nearest the optical axis are used; a second stop cuts those toward the corners.
    In a window whose nearest point to the axis is 700 px away, beside the onset of the cut, and with
    an extreme stop, the fit still sees uncut micro-images only."""
    model = window(1640 + 500, 1640 + 500, 512)
    for cut in (0.3, 0.6):
        camera = CameraEffects.build(Realism(blur_px=0.8, vignetting_corner_cut=cut, vignetting_onset=0.45,
                                             rim_response=0.75, lens_transmission_spread=0.03), serial=SERIAL)
        raw = render_white_image(model, seed=5, camera=camera)
        profile = fit_micro_image_profile(raw, model.lattice, black_level=model.black_level,
                                          radius_px=model.optics.micro_image_radius_px)
        assert profile.blur_px == pytest.approx(0.8, abs=0.03)
        assert profile.rim_response == pytest.approx(0.75, abs=0.03)


def test_cut_micro_images_are_refused_rather_than_fitted():
    model = window(3280 - 512, 3280 - 512, 512)   # the corner: every micro-image a cat's eye
    camera = CameraEffects.build(Realism(blur_px=0.8, vignetting_corner_cut=0.6, vignetting_onset=0.3), serial=SERIAL)
    raw = render_white_image(model, seed=5, camera=camera)
    with pytest.raises(CalibrationError, match="full shape"):
        fit_micro_image_profile(raw, model.lattice, black_level=model.black_level,
                                radius_px=model.optics.micro_image_radius_px)


def test_defective_pixels_and_dust_do_not_move_the_blur():
    model = centred(512)
    camera = CameraEffects.build(Realism(blur_px=1.2), serial=SERIAL)
    raw = render_white_image(model, seed=3, camera=camera).copy()
    clean = fit(raw, model)
    rng = np.random.default_rng(1)
    rows, cols = rng.integers(0, 512, size=(2, 300))
    raw[rows, cols] = 4095
    raw[rows[:100], (cols[:100] + 3) % 512] = model.black_level
    raw[250:254, 250:262] = model.black_level + 300     # a speck of dust
    dirty = fit(raw, model)
    assert dirty.blur_px == pytest.approx(clean.blur_px, abs=0.01)


def test_calibration_carries_the_profile_and_falls_back_without_one():
    model = centred(512)
    meta = simulated_camera_metadata(size=512)
    camera = CameraEffects.build(Realism(blur_px=1.2), serial=SERIAL)
    white = WhiteImage.from_image("MOD_0002", render_white_image(model, seed=3, camera=camera), meta,
                                  simulated_private_metadata(SERIAL))
    cal = calibrate(white)
    assert cal.profile is not None and cal.blur_px == pytest.approx(1.2, abs=0.03)
    assert replace(cal, profile=None).blur_px == DEFAULT_BLUR_PX


def test_the_depth_fit_models_the_calibrations_blur(tmp_path, monkeypatch):
    import analysis.pipeline.process as pipeline
    from analysis.cache import Cache
    from analysis.calibration.cache import load_calibration
    from analysis.formats.exposure import read_exposure
    from analysis.pipeline.params import PipelineParams
    from analysis.simulation.scenario_files import write_scenario

    write_scenario(tmp_path, "tilted-layer", 3, size=512, realism=Realism(blur_px=1.2))
    exposure = read_exposure(tmp_path / "IMG_0001.lfp")
    cal = load_calibration(tmp_path / "calibration", exposure.metadata, serial=exposure.serial)
    assert cal.blur_px == pytest.approx(1.2, abs=0.03)
    seen = []

    def spy(*args, **kwargs):
        fitter = pipeline.RayFitter.__wrapped__(*args, **kwargs)
        seen.append(fitter.blur_px)
        return fitter

    spy.__wrapped__ = pipeline.RayFitter
    monkeypatch.setattr(pipeline, "RayFitter", spy)
    result = pipeline.process(exposure, cal, PipelineParams(), cache=Cache())
    assert seen == [cal.blur_px] and len(result.particles["x"]) > 0
