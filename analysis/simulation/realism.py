"""What a real F01 in a plasma chamber adds to the ideal simulated camera: the `Realism` parameters.

The ideal simulator renders exactly the optics of camera-model.md, which the pipeline also
assumes. `Realism` lists the effects a real camera and a real chamber add on top, each with a
physical parameter and an "off" value that is the ideal camera's. The pipeline is told none of
them: the exposure's metadata stay those of the ideal camera, and only what a real camera would
also show (the white images, the dark frame) carries the camera's effects.

Effects are grouped as the realism bench switches them (`EFFECTS`):

``blur``
    Point spread of the micro-lenses and the pixels wider than the ideal 0.5 px (diffraction at
    the micro-lens, aberration, pixel cross-talk); optionally with a wide halo, so that the point
    spread is not the Gaussian the pipeline fits (off in the typical camera: a shape to vary).
``micro-images``
    A pixel response inside each micro-image falling off toward its rim (the pixels' angular
    response, ``cos^n`` of the ray's angle to its micro-image's chief ray), and a per-micro-lens
    transmission spread. Both belong to the camera: white images and exposures show them alike.
``vignetting``
    A second stop in the main lens (a barrel or a front-element rim): seen from a field point off
    axis the aperture is the intersection of two disks, so corner micro-images are cat's eyes.
``hot-pixels``
    A fixed pattern of hot, stuck and dead pixels seeded by the camera serial, the same in every
    frame of that camera (white and dark frames included), added after the read-out.
``glow``
    Plasma glow brighter toward the lower (powered) electrode: a vertical gradient.
``reflections``
    Out-of-focus laser light: a band reflected by the lower electrode and round glints.
``brightness``
    A particle brightness spread of 10x or more (laser-sheet profile, Mie scattering angle), so
    the brightest in-focus particles saturate the 12-bit ADC.
``drift``
    A sub-pixel shift and a tiny rotation of the micro-lens lattice between the white images and
    the exposure (thermal, mechanical).
``scene``
    Cluster size, shape, tilt and placement drawn from wide ranges, independently of the defaults
    the pipeline was developed on.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Any, Mapping

from analysis.errors import ParameterError

#: Effect groups, in the order the realism bench shows them; each maps to its `Realism` fields.
EFFECTS: dict[str, tuple[str, ...]] = {
    "blur": ("blur_px", "psf_halo", "psf_halo_px"),
    "micro-images": ("rim_response", "lens_transmission_spread"),
    "vignetting": ("vignetting_corner_cut", "vignetting_onset"),
    "hot-pixels": ("hot_pixel_fraction", "dead_pixel_fraction"),
    "glow": ("glow_gradient",),
    "reflections": ("reflection_dn", "glints", "glint_dn"),
    "brightness": ("brightness_spread",),
    "drift": ("lattice_drift_px", "lattice_drift_rad"),
    "scene": ("varied_scene",),
}

#: The ideal optics' Gaussian point spread (sigma, px): camera-model.md step 4.
IDEAL_BLUR_PX = 0.5


@dataclass(frozen=True)
class Realism:
    """Effects of a real F01 in a plasma chamber; the defaults are the ideal camera (all off).

    Attributes
    ----------
    blur_px : float
        Sigma in pixels of the Gaussian point spread applied to all light on the sensor
        (0.5 = ideal; real: 0.3 ... 1.5).
    psf_halo : float
        Fraction of the point spread's light in a wider Gaussian halo (light scattered in the
        micro-lenses and the colour filters, cross-talk beyond the next pixel); 0 = none, the
        Gaussian of ``blur_px`` alone, as in the typical camera and the ideal one.
    psf_halo_px : float
        Sigma in pixels of that halo.
    rim_response : float
        Pixel response at the rim of a micro-image relative to its centre, for the picture's
        f/2 (image side) main lens, whose marginal rays meet the sensor at 14 degrees to the
        micro-image's chief ray. A ray at angle ``theta`` is weighted by ``cos(theta)^n``, with
        ``n`` chosen to give this value at the rim (1 = flat, ideal).
    lens_transmission_spread : float
        Relative standard deviation of the micro-lenses' transmission (0 = ideal).
    vignetting_corner_cut : float
        Fraction of the aperture diameter that the second stop cuts off, seen from the corner
        of the sensor (0 = no second stop, ideal).
    vignetting_onset : float
        Field radius, as a fraction of the sensor's half-diagonal, at which the second stop starts
        to cut the aperture.
    hot_pixel_fraction : float
        Fraction of the sensor's pixels that are hot or stuck (0 = ideal).
    dead_pixel_fraction : float
        Fraction of the sensor's pixels that read black (0 = ideal).
    glow_gradient : float
        Plasma glow at the bottom edge of the field over that at the top edge (1 = uniform, ideal);
        the glow at the centre keeps the scene's ``background_dn``.
    reflection_dn : float
        Peak radiance of the laser band reflected by the lower electrode, in DN of a fully lit
        green pixel (0 = none).
    glints : int
        Number of out-of-focus glints (round reflections off screws, window rims).
    glint_dn : float
        Typical peak radiance of a glint, DN of a fully lit green pixel.
    brightness_spread : float
        Ratio of the brightest to the faintest particle, drawn log-uniform about the scene's
        median brightness (0 = the scene's own narrow spread, ideal).
    lattice_drift_px : tuple of float
        Shift ``(dx, dy)`` in pixels of the micro-lens lattice in the exposure relative to the
        white images.
    lattice_drift_rad : float
        Rotation of the lattice in the exposure relative to the white images, about the lens
        on the optical axis.
    varied_scene : bool
        Draw cluster size, shape, tilt and placement from wide ranges (see
        :func:`analysis.simulation.scenarios.make_scenario`).

    Examples
    --------
    >>> Realism().is_ideal
    True
    >>> Realism.typical().effects_on()[:3]
    ('blur', 'micro-images', 'vignetting')
    >>> Realism.only("blur").blur_px
    0.8
    """

    blur_px: float = IDEAL_BLUR_PX
    psf_halo: float = 0.0
    psf_halo_px: float = 3.0
    rim_response: float = 1.0
    lens_transmission_spread: float = 0.0
    vignetting_corner_cut: float = 0.0
    vignetting_onset: float = 0.5
    hot_pixel_fraction: float = 0.0
    dead_pixel_fraction: float = 0.0
    glow_gradient: float = 1.0
    reflection_dn: float = 0.0
    glints: int = 0
    glint_dn: float = 0.0
    brightness_spread: float = 0.0
    lattice_drift_px: tuple[float, float] = (0.0, 0.0)
    lattice_drift_rad: float = 0.0
    varied_scene: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "lattice_drift_px", tuple(float(v) for v in self.lattice_drift_px))
        checks = [
            (0.2 <= self.blur_px <= 3.0, f"blur_px={self.blur_px}: give a point-spread sigma of 0.2 ... 3 px"),
            (0.0 <= self.psf_halo <= 0.5, f"psf_halo={self.psf_halo}: give a fraction of the light of 0 ... 0.5"),
            (self.blur_px < self.psf_halo_px <= 10.0,
             f"psf_halo_px={self.psf_halo_px}: give a sigma wider than blur_px ({self.blur_px}) and at most 10 px"),
            (0.05 <= self.rim_response <= 1.0, f"rim_response={self.rim_response}: give 0.05 ... 1 (1 = flat)"),
            (0.0 <= self.lens_transmission_spread <= 0.3,
             f"lens_transmission_spread={self.lens_transmission_spread}: give 0 ... 0.3 (a few % is typical)"),
            (0.0 <= self.vignetting_corner_cut <= 0.9,
             f"vignetting_corner_cut={self.vignetting_corner_cut}: give 0 ... 0.9 of the aperture diameter"),
            (0.0 <= self.vignetting_onset < 1.0, f"vignetting_onset={self.vignetting_onset}: give 0 ... <1"),
            (0.0 <= self.hot_pixel_fraction <= 0.01,
             f"hot_pixel_fraction={self.hot_pixel_fraction}: give 0 ... 0.01 (1e-4 is typical)"),
            (0.0 <= self.dead_pixel_fraction <= 0.01,
             f"dead_pixel_fraction={self.dead_pixel_fraction}: give 0 ... 0.01"),
            (0.1 <= self.glow_gradient <= 100.0, f"glow_gradient={self.glow_gradient}: give a ratio of 0.1 ... 100"),
            (0.0 <= self.reflection_dn <= 1e5, f"reflection_dn={self.reflection_dn}: give 0 ... 1e5 DN"),
            (0 <= self.glints <= 20, f"glints={self.glints}: give 0 ... 20"),
            (0.0 <= self.glint_dn <= 1e5, f"glint_dn={self.glint_dn}: give 0 ... 1e5 DN"),
            (not self.glints or self.glint_dn > 0, "glints need a positive glint_dn"),
            (self.brightness_spread == 0.0 or 1.0 <= self.brightness_spread <= 1000.0,
             f"brightness_spread={self.brightness_spread}: give 0 (the scene's own) or a ratio of 1 ... 1000"),
            (len(self.lattice_drift_px) == 2 and all(abs(v) <= 5.0 for v in self.lattice_drift_px),
             f"lattice_drift_px={self.lattice_drift_px}: give (dx, dy), each within 5 px"),
            (abs(self.lattice_drift_rad) <= 0.01, f"lattice_drift_rad={self.lattice_drift_rad}: give |r| <= 0.01"),
        ]
        for ok, message in checks:
            if not ok:
                raise ParameterError(message)
        for name in ("blur_px", "psf_halo", "psf_halo_px", "rim_response", "lens_transmission_spread",
                     "glow_gradient", "reflection_dn", "glint_dn", "brightness_spread", "lattice_drift_rad"):
            if not math.isfinite(getattr(self, name)):
                raise ParameterError(f"{name} must be a finite number")

    @classmethod
    def typical(cls) -> "Realism":
        """A typical F01 in a dusty-plasma chamber: every effect on (values argued in docs).

        * blur 0.8 px: the micro-lenses work at about f/1.8, so the Airy core alone has a sigma of
          about 0.3 px at 532 nm; pixel integration (0.29 px), cross-talk between 1.4 um pixels and
          aberration add in quadrature to 0.7-0.9 px.
        * rim response 0.75 and a 3 % lens transmission spread: the marginal rays of an f/2
          beam meet the pixels at 14 degrees; small pixels lose a quarter of their response there.
          Replicated micro-lens arrays vary by a few % in transmission.
        * second stop cutting 30 % of the aperture diameter at the corner, from 45 % of the field:
          F01 white images show cat's-eye micro-images toward the corners.
        * hot/stuck pixels 1e-4 (about 1100 on the sensor), dead 2e-5: usual for a consumer CMOS.
        * glow 3x brighter at the bottom: the sheath of the powered lower electrode glows most.
        * a laser band of 2000 DN off the lower electrode and two glints of about 2500 DN,
          out of focus, tens of times the per-pixel signal of the faintest defocused particle.
        * brightness spread 12x: the laser sheet's Gaussian profile and the Mie scattering angle.
        * lattice drift (0.25, -0.15) px and 4e-5 rad: 5 K of warming between calibration and
          exposure moves a metal MLA mount by a few tenths of a micrometre.
        * varied scene.
        """
        return cls(blur_px=0.8, rim_response=0.75, lens_transmission_spread=0.03,
                   vignetting_corner_cut=0.3, vignetting_onset=0.45,
                   hot_pixel_fraction=1e-4, dead_pixel_fraction=2e-5, glow_gradient=3.0,
                   reflection_dn=2000.0, glints=2, glint_dn=2500.0, brightness_spread=12.0,
                   lattice_drift_px=(0.25, -0.15), lattice_drift_rad=4e-5, varied_scene=True)

    @classmethod
    def only(cls, *effects: str) -> "Realism":
        """The ideal camera with the named effect groups (`EFFECTS`) at their `typical` values.

        ``"all"`` names every group.
        """
        names = check_effects(effects)
        preset = cls.typical()
        return replace(cls(), **{f: getattr(preset, f) for name in names for f in EFFECTS[name]})

    @property
    def is_ideal(self) -> bool:
        """True when every effect is off: the simulator renders the ideal camera, byte for byte."""
        return not self.effects_on()

    def effects_on(self) -> tuple[str, ...]:
        """Names of the effect groups that differ from the ideal camera, in `EFFECTS` order."""
        ideal = Realism()
        on = []
        for name, names in EFFECTS.items():
            active = [f for f in names if getattr(self, f) != getattr(ideal, f)]
            # An onset, a halo's width or a glint level alone changes nothing.
            if name == "blur" and self.blur_px == ideal.blur_px and self.psf_halo == 0:
                active = []
            if name == "vignetting" and self.vignetting_corner_cut == 0:
                active = []
            if name == "reflections" and self.reflection_dn == 0 and self.glints == 0:
                active = []
            if active:
                on.append(name)
        return tuple(on)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready parameters (``scenario.json``), with the effect groups that are on."""
        doc = asdict(self)
        doc["lattice_drift_px"] = list(self.lattice_drift_px)
        doc["effects"] = list(self.effects_on())
        return doc

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> "Realism":
        """Inverse of `to_dict` (unknown keys refused, ``effects`` ignored)."""
        known = {f.name for f in fields(cls)}
        unknown = set(doc) - known - {"effects"}
        if unknown:
            raise ParameterError(f"unknown realism parameter(s) {', '.join(sorted(unknown))}; "
                                 f"known: {', '.join(sorted(known))}")
        values = {k: v for k, v in doc.items() if k in known}
        if "lattice_drift_px" in values:
            values["lattice_drift_px"] = tuple(values["lattice_drift_px"])
        return cls(**values)


def check_effects(effects: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """Effect group names, ``"all"`` expanded, checked against `EFFECTS`."""
    names: list[str] = []
    for item in effects:
        if item == "all":
            names.extend(EFFECTS)
        elif item in EFFECTS:
            names.append(item)
        else:
            raise ParameterError(f"unknown realism effect {item!r}; choose from all, {', '.join(EFFECTS)}")
    return tuple(dict.fromkeys(names))
