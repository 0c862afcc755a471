"""The simulated F01: a consistent thin-lens camera written as real-looking F01 metadata.

The real F01 zoom lens does not fit a thin lens (camera-model.md), so the simulator uses its own
main lens: a thin lens whose exit pupil is the lens itself, ``P`` in front of the micro-lens
array. Sensor and MLA are the real F01's (the template is the metadata of a real picture,
``fixtures/real/f01-frame-metadata.json``). :func:`simulated_camera_metadata` writes the thin-lens
numbers into ``devices.lens`` so that :meth:`CameraModel.from_metadata` gives back exactly the
geometry that is rendered.

Why these optics: the refocus range downstream is ``alpha`` 0.987 ... 1.013. ``dalpha/dZ = -m^2/P``
(``m = P/Z`` the magnification), and the blur on the MLA is ``D |1 - alpha| / alpha``. With the
image-side f-number ``P/D = 2`` the micro-images nearly fill the lens pitch; ``m = 0.27`` puts
a 14 mm cluster on about 2700 of the 3280 pixels; ``P = 16 mm`` then maps 1 mm of depth to
0.0044 in ``alpha`` and 2.6 lens pitches of blur, so the 13-degree layer (3.2 mm deep) spans
about half the refocus range with blur from zero to about four pitches.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

from analysis.errors import ParameterError

# Real F01 MLA and sensor (imageio IMG_0001__frame.json, firmware v1.0.2; lytro-f01.md 1.6).
F01_LENS_PITCH_M = 1.389859962463379e-05
F01_MLA_ROTATION_RAD = 0.0019290975760668516
F01_MLA_SCALE_Y = 1.0004994869232178
F01_MLA_OFFSET_X_M = -2.7138671874999998e-06
F01_MLA_OFFSET_Y_M = 5.6601560115814212e-07
F01_MLA_TO_SENSOR_M = 2.5e-05
F01_PIXEL_PITCH_M = 1.3999999761581417e-06
F01_SIZE = 3280

# Sensor noise model of the simulated camera (an assumption; no F01 noise data was available).
ELECTRONS_PER_DN = 1.5
READ_NOISE_DN = 2.0

# Relative responses of the Bayer channels. White light: the normalizedResponses PlenoptiCam
# falls back to (lytro-f01.md 1.6). 532 nm laser light: green sites see nearly all of it.
WHITE_RESPONSE = {"r": 0.76306647062301636, "g": 1.0, "b": 0.74476742744445801}
LASER_532_RESPONSE = {"r": 0.03, "g": 1.0, "b": 0.05}

DEFAULT_SERIAL = "A202160042"
DEFAULT_SENSOR_SERIAL = "0x5A17C0DE0042B00F"


@dataclass(frozen=True)
class SimulatedLens:
    """Thin main lens of the simulated camera.

    Parameters
    ----------
    lens_to_mla_m : float
        ``P``, the distance from the lens (its own exit pupil) to the micro-lens array.
    focus_distance_mm : float
        ``Z0``, the object distance imaged sharply on the MLA (``alpha = 1``).
    image_f_number : float
        ``P / D``; 2 makes the micro-images (radius ``(D/2) d / P``) nearly fill the pitch.
    zoom_step, focus_step : int
        Stepper positions written into the metadata (used to choose white images).
    """

    lens_to_mla_m: float = 0.016
    focus_distance_mm: float = 60.0
    image_f_number: float = 2.0
    zoom_step: int = 981
    focus_step: int = 582

    def __post_init__(self) -> None:
        if not (0.001 <= self.lens_to_mla_m <= 1.0):
            raise ParameterError(f"lens_to_mla_m={self.lens_to_mla_m} m is not a plausible P; use 0.001 ... 1 m")
        if self.focus_distance_mm * 1e-3 <= self.lens_to_mla_m:
            raise ParameterError("focus_distance_mm must exceed lens_to_mla_m for a real image; "
                                 "use a longer working distance")
        if not (0.8 <= self.image_f_number <= 16):
            raise ParameterError(f"image_f_number={self.image_f_number} is outside 0.8 ... 16")

    @property
    def focal_length_m(self) -> float:
        """``f = 1 / (1/Z0 + 1/P)``."""
        return 1.0 / (1.0 / (self.focus_distance_mm * 1e-3) + 1.0 / self.lens_to_mla_m)

    @property
    def aperture_diameter_m(self) -> float:
        return self.lens_to_mla_m / self.image_f_number

    @property
    def f_number(self) -> float:
        """The metadata's ``fNumber``: focal length over aperture diameter."""
        return self.focal_length_m / self.aperture_diameter_m


# The picture's lens, a second zoom position for the "other zoom" white image.
DEFAULT_LENS = SimulatedLens()
OTHER_ZOOM_LENS = SimulatedLens(lens_to_mla_m=0.020, focus_distance_mm=75.0, zoom_step=1203, focus_step=640)

_TEMPLATE: dict[str, Any] = {
    "type": "lightField",
    "image": {
        "width": F01_SIZE,
        "height": F01_SIZE,
        "orientation": 1,
        "representation": "rawPacked",
        "rawDetails": {
            "pixelFormat": {
                "rightShift": 0,
                "black": {"r": 168, "gr": 168, "gb": 168, "b": 168},
                "white": {"r": 4095, "gr": 4095, "gb": 4095, "b": 4095},
            },
            "pixelPacking": {"endianness": "big", "bitsPerPixel": 12},
            "mosaic": {"tile": "r,gr:gb,b", "upperLeftPixel": "b"},
        },
        "color": {
            "ccmRgbToSrgbArray": [3.1115827560424805, -1.9393929243087769, -0.172189861536026,
                                  -0.3629055917263031, 1.6408803462982178, -0.27797481417655945,
                                  0.078967012465000153, -1.1558042764663696, 2.0768373012542725],
            "gamma": 0.41666001081466675,
            "applied": {},
            "whiteBalanceGain": {"r": 1, "gr": 1.1171875, "gb": 1.1171875, "b": 1.72265625},
        },
        "modulationExposureBias": -1.1242823600769043,
        "limitExposureBias": 0,
    },
    "devices": {
        "clock": {"zuluTime": "2021-06-01T09:00:00.000Z"},
        "sensor": {
            "bitsPerPixel": 12,
            "mosaic": {"tile": "r,gr:gb,b", "upperLeftPixel": "b"},
            "iso": 200,
            "analogGain": {"r": 5.4375, "gr": 4, "gb": 4, "b": 4.625},
            "pixelPitch": F01_PIXEL_PITCH_M,
        },
        "lens": {
            "infinityLambda": 7,
            "focalLength": None,
            "zoomStep": None,
            "focusStep": None,
            "fNumber": None,
            "temperature": 28.675750732421875,
            "temperatureAdc": 2776,
            "zoomStepperOffset": 0,
            "focusStepperOffset": 27,
            "exitPupilOffset": {"z": None},
        },
        "ndfilter": {"exposureBias": 0},
        "shutter": {
            "mechanism": "sensorOpenApertureClose",
            "frameExposureDuration": 0.01433531753718853,
            "pixelExposureDuration": 0.01433531753718853,
        },
        "soc": {"temperature": 30.941009521484375, "temperatureAdc": 3203},
        "accelerometer": {"sampleArray": [{"x": 0.0, "y": 1.0, "z": 0.0, "time": 0}]},
        "mla": {
            "tiling": "hexUniformRowMajor",
            "lensPitch": F01_LENS_PITCH_M,
            "rotation": F01_MLA_ROTATION_RAD,
            "defectArray": [],
            "config": "com.lytro.mla.3",
            "scaleFactor": {"x": 1, "y": F01_MLA_SCALE_Y},
            "sensorOffset": {"x": F01_MLA_OFFSET_X_M, "y": F01_MLA_OFFSET_Y_M, "z": F01_MLA_TO_SENSOR_M},
        },
    },
    "modes": {"creative": "auto"},
    "camera": {
        "make": "Lytro, Inc.",
        "model": "F01",
        "firmware": "v1.0a119, vv1.0.2, Tue Jun 19 11:53:16 PDT 2012, cceebc3aa8e9dec7d959ea7daaa01d67ce7704af, "
                    "mods=0, ofw=0",
    },
}


def simulated_camera_metadata(*, lens: SimulatedLens = DEFAULT_LENS, size: int = F01_SIZE,
                              exposure_s: float = 0.01433531753718853,
                              zulu_time: str = "2021-06-01T09:00:00.000Z") -> dict:
    """Frame metadata of the simulated F01 (the picture's ``.TXT`` / ``metadataRef`` JSON).

    Parameters
    ----------
    lens : SimulatedLens
        Thin main lens; written as ``focalLength``, ``fNumber``, ``exitPupilOffset.z`` (= ``P``),
        ``zoomStep`` and ``focusStep``.
    size : int
        Sensor width and height in pixels: 3280 for the F01, smaller for a centred crop (even).
    exposure_s : float
        ``frameExposureDuration`` and ``pixelExposureDuration``.
    zulu_time : str
        ``devices.clock.zuluTime``.

    Returns
    -------
    dict
        A fresh metadata dict; ``CameraModel.from_metadata`` of it is the rendered geometry.

    Examples
    --------
    >>> from analysis.camera.model import CameraModel
    >>> model = CameraModel.from_metadata(simulated_camera_metadata())
    >>> round(model.optics.focus_distance_mm, 6)
    60.0
    """
    if size < 16 or size > F01_SIZE or size % 2:
        raise ParameterError(f"size={size} must be an even number of pixels in 16 ... {F01_SIZE}")
    meta = copy.deepcopy(_TEMPLATE)
    meta["image"]["width"] = meta["image"]["height"] = int(size)
    lens_meta = meta["devices"]["lens"]
    lens_meta["focalLength"] = lens.focal_length_m
    lens_meta["fNumber"] = lens.f_number
    lens_meta["exitPupilOffset"]["z"] = lens.lens_to_mla_m
    lens_meta["zoomStep"] = int(lens.zoom_step)
    lens_meta["focusStep"] = int(lens.focus_step)
    meta["devices"]["shutter"]["frameExposureDuration"] = float(exposure_s)
    meta["devices"]["shutter"]["pixelExposureDuration"] = float(exposure_s)
    meta["devices"]["clock"]["zuluTime"] = zulu_time
    return meta


def simulated_private_metadata(serial: str = DEFAULT_SERIAL) -> dict:
    """Private metadata with the camera serial (F01 serials start with ``A``)."""
    if not serial.startswith("A"):
        raise ParameterError(f"serial {serial!r} must start with 'A' like every F01 serial")
    return {"devices": {"sensor": {"sensorSerial": DEFAULT_SENSOR_SERIAL}},
            "camera": {"serialNumber": serial}}


def white_normalized_responses() -> list[dict]:
    """``devices.sensor.normalizedResponses`` written into white-image metadata."""
    r = WHITE_RESPONSE
    return [{"cct": 5100, "r": r["r"], "gr": r["g"], "gb": r["g"], "b": r["b"]}]


def chief_ray_cos4(radius_m: float | Any, lens_to_mla_m: float | None) -> Any:
    """``cos^4`` of the angle between the optical axis and a ray from the lens centre to a point
    ``radius_m`` off-axis on the MLA plane (1 for telecentric models)."""
    if lens_to_mla_m is None:
        return 1.0 + 0.0 * radius_m
    cos2 = lens_to_mla_m ** 2 / (lens_to_mla_m ** 2 + radius_m ** 2)
    return cos2 * cos2

