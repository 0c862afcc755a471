"""`plenodust simulate`: write a simulated exposure, its calibration and its truth as camera files."""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

from analysis.errors import AnalysisError, ParameterError
from analysis.simulation.camera import F01_SIZE
from analysis.simulation.dynamics import Motion
from analysis.simulation.realism import EFFECTS, Realism
from analysis.simulation.scenario_files import write_scenario
from analysis.simulation.scenarios import SCENARIO_NAMES
from analysis.simulation.target import TARGET, DotTarget, default_target, simulated_front_optics

_TYPICAL = Realism.typical()


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "simulate", help="write a simulated F01 exposure with known particle positions",
        description="Render a particle cluster through the simulated F01 and write it as the camera stores it: "
                    "DIR/IMG_nnnn.lfp, IMG_nnnn.RAW + .TXT, IMG_nnnn.truth.csv (X, Y, Z in mm), "
                    "DIR/calibration/MOD_nnnn.RAW + .TXT white images and DIR/scenario.json.")
    parser.add_argument("--scenario", choices=(*SCENARIO_NAMES, TARGET), default="tilted-layer",
                        help="cluster to simulate (default: tilted-layer, the paper's 13-degree layer; cloud: 400 "
                             "particles 2.6 mm in front of focus; target: a dot plate at several stage positions, "
                             "one exposure each, positions in DIR/target.json)")
    parser.add_argument("--seed", type=int, default=1, help="random seed; the same seed writes the same bytes")
    parser.add_argument("--out", type=Path, required=True, help="folder to write into (created)")
    parser.add_argument("--count", type=int, default=1,
                        help="number of exposures IMG_0001..N, one per --interval on the metadata clock; the cluster "
                             "moves between them (see the motion options)")
    parser.add_argument("--size", type=int, default=F01_SIZE,
                        help=f"sensor size in pixels (default {F01_SIZE}, the full F01); a smaller, centred crop "
                             "(multiple of 4) for quick tests keeps only the particles that fit on it")
    parser.add_argument("--brightness", type=float, default=1800.0,
                        help="median particle brightness: DN above black of a fully lit green pixel (default 1800)")
    parser.add_argument("--background", type=float, default=40.0,
                        help="plasma glow, a diffuse background in the same units (default 40)")
    parser.add_argument("--centre-z", type=float, default=None, metavar="MM",
                        help="distance of the cluster's centre from the lens (default: the focus distance, "
                             "+-0.3 mm); a few mm off focus keeps every particle's blur above a lens pitch")
    parser.add_argument("--serial", default=None,
                        help="camera serial (default A202160042); seeds the camera's hot pixels and lens "
                             "transmission")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    add_optics_arguments(parser)
    add_realism_arguments(parser)
    add_motion_arguments(parser)
    parser.set_defaults(func=run)


def add_optics_arguments(parser: argparse.ArgumentParser) -> None:
    """The front optics (every scene) and the dot target's options."""
    group = parser.add_argument_group(
        "front optics", "An auxiliary lens in front of the camera and radial distortion of the main lens, which the "
                        "metadata do not know (the paper's set-up: a 174 mm lens). Scenes are placed where the "
                        "camera focuses through them; the truth keeps the true X, Y, Z.")
    group.add_argument("--aux-lens-f", type=float, default=None, metavar="MM",
                       help="focal length of an auxiliary thin lens in front of the camera (e.g. 174)")
    group.add_argument("--aux-lens-distance", type=float, default=20.0, metavar="MM",
                       help="its distance in front of the main lens (default 20)")
    group.add_argument("--distortion", type=float, default=0.0, metavar="FRACTION",
                       help="radial distortion of the main lens: fractional displacement at the sensor's corner "
                            "(0.01 for 1 %%; negative: barrel)")
    group = parser.add_argument_group("target (--scenario target)", "A plate of dots at several stage positions.")
    group.add_argument("--positions", type=float, nargs="+", default=None, metavar="MM",
                       help="stage positions: depth of the middle dot in each exposure (default: 5 across 8 mm "
                            "about the focus)")
    group.add_argument("--pitch", type=float, default=1.0, metavar="MM", help="dot pitch (default 1)")
    group.add_argument("--extent", type=float, default=12.0, metavar="MM",
                       help="side of the square the dots fill (default 12)")
    group.add_argument("--tilt", type=float, default=0.0, metavar="DEG",
                       help="tilt of the plate about its rows (default 0)")
    group.add_argument("--rotation", type=float, default=0.0, metavar="DEG",
                       help="turn of its rows about the optical axis (default 0)")
    group.add_argument("--offset", type=float, nargs=2, default=(0.0, 0.0), metavar=("X_MM", "Y_MM"),
                       help="lateral position of the middle dot (default 0 0: on the axis)")


def optics_from_args(args: argparse.Namespace) -> tuple:
    """The front optics and (for ``--scenario target``) the target the options ask for."""
    front = simulated_front_optics(args.aux_lens_f, args.aux_lens_distance, distortion=args.distortion)
    if args.scenario != TARGET:
        return front, None
    plate = dict(pitch_mm=args.pitch, extent_mm=args.extent, tilt_deg=args.tilt, rotation_deg=args.rotation,
                 offset_mm=tuple(args.offset), brightness_dn=args.brightness)
    if args.positions:
        return front, DotTarget(positions_mm=tuple(args.positions), **plate)
    return front, default_target(front, **plate)


def add_motion_arguments(parser: argparse.ArgumentParser) -> None:
    """How the cluster moves between the exposures of ``--count N``."""
    m = Motion()
    g = parser.add_argument_group(
        "motion", "With --count above 1 the cluster moves between shots: each particle in a harmonic cage around "
                  "its site (Langevin: the gas's friction and kicks at a temperature), the sites turning and "
                  "drifting with the gas, and in a ball particles hopping between shells. The truth tables "
                  "get vX, vY, vZ (mm/s) and shell; scenario.json records the motion and every hop.")
    g.add_argument("--interval", type=float, default=m.interval_s, metavar="S",
                   help=f"seconds between shots on the metadata clock (default {m.interval_s:g})")
    g.add_argument("--temperature-ev", type=float, default=m.temperature_ev, metavar="EV",
                   help=f"kinetic temperature of the particles (default {m.temperature_ev:g} eV)")
    g.add_argument("--damping", type=float, default=m.damping_per_s, metavar="PER_S",
                   help=f"friction rate of the gas (default {m.damping_per_s:g} /s)")
    g.add_argument("--cage", type=float, default=m.cage_per_s, metavar="RAD_S",
                   help=f"angular frequency of each particle's cage (default {m.cage_per_s:g} rad/s)")
    g.add_argument("--spin", type=float, default=m.rotation_deg_per_s, metavar="DEG_S",
                   help=f"rotation of the cluster about the image's vertical (default {m.rotation_deg_per_s:g} deg/s)")
    g.add_argument("--drift", type=float, nargs=3, default=list(m.drift_mm_per_s), metavar=("VX", "VY", "VZ"),
                   help="drift of the cluster's centre in mm/s (default %s)" % " ".join(f"{v:g}" for v in m.drift_mm_per_s))
    g.add_argument("--hop-rate", type=float, default=m.hop_rate_per_s, metavar="PER_S",
                   help=f"shell hops per second in a ball (default {m.hop_rate_per_s:g})")
    g.add_argument("--particle-diameter-um", type=float, default=m.particle_diameter_um,
                   help=f"particle diameter (default {m.particle_diameter_um:g} um, the paper's MF particles)")


def motion_from_args(args: argparse.Namespace) -> Motion:
    """The :class:`Motion` the options ask for."""
    return Motion(interval_s=args.interval, temperature_ev=args.temperature_ev, damping_per_s=args.damping,
                  cage_per_s=args.cage, rotation_deg_per_s=args.spin, drift_mm_per_s=tuple(args.drift),
                  hop_rate_per_s=args.hop_rate, particle_diameter_um=args.particle_diameter_um)


def add_realism_arguments(parser: argparse.ArgumentParser) -> None:
    """The realism options: ``--realism [EFFECTS]`` and one option per parameter."""
    t = _TYPICAL
    group = parser.add_argument_group(
        "realism", "Effects of a real F01 in a plasma chamber that the pipeline is not told about (ideal camera by "
                   "default). --realism starts from a typical F01's values; each option below turns its effect on "
                   "(at the typical value when given without one) or overrides the preset; 0 (1 for ratios) "
                   "turns an effect off. Recorded in scenario.json.")
    group.add_argument("--realism", nargs="?", const="all", default=None, metavar="EFFECTS",
                       help="start from the typical F01 in a chamber: 'all' (the default) or a comma-separated list "
                            f"of {', '.join(EFFECTS)}")
    group.add_argument("--blur-px", type=float, default=None, metavar="SIGMA",
                       help=f"sigma of the point spread in px (ideal 0.5; typical {t.blur_px})")
    group.add_argument("--psf-halo", type=float, default=None, metavar="FRACTION",
                       help="fraction of the point spread's light in a wide Gaussian halo (scatter, cross-talk), so "
                            "the point spread is not the Gaussian the pipeline fits (0: none, as typical and ideal)")
    group.add_argument("--psf-halo-px", type=float, default=None, metavar="SIGMA",
                       help=f"sigma of that halo in px (default {t.psf_halo_px:g})")
    group.add_argument("--rim-response", type=float, default=None, metavar="R",
                       help=f"pixel response at a micro-image's rim relative to its centre (ideal 1; typical "
                            f"{t.rim_response})")
    group.add_argument("--lens-transmission-spread", type=float, default=None, metavar="FRACTION",
                       help=f"relative spread of the micro-lenses' transmission (typical {t.lens_transmission_spread})")
    group.add_argument("--vignetting", type=float, nargs="?", const=t.vignetting_corner_cut, default=None,
                       metavar="CORNER_CUT",
                       help="second stop in the main lens: fraction of the aperture diameter cut off at the sensor's "
                            f"corner (typical {t.vignetting_corner_cut}); cat's-eye micro-images")
    group.add_argument("--vignetting-onset", type=float, default=None, metavar="FRACTION",
                       help=f"field radius (of the half-diagonal) where the second stop starts to cut (typical "
                            f"{t.vignetting_onset})")
    group.add_argument("--hot-pixels", type=float, nargs="?", const=t.hot_pixel_fraction, default=None,
                       metavar="FRACTION", help=f"fraction of hot and stuck pixels, fixed per camera serial (typical "
                                               f"{t.hot_pixel_fraction:g})")
    group.add_argument("--dead-pixels", type=float, nargs="?", const=t.dead_pixel_fraction, default=None,
                       metavar="FRACTION", help=f"fraction of dead pixels (typical {t.dead_pixel_fraction:g})")
    group.add_argument("--glow", type=float, nargs="?", const=t.glow_gradient, default=None, metavar="RATIO",
                       help=f"plasma glow at the bottom of the field over that at the top (typical {t.glow_gradient:g})")
    group.add_argument("--reflection", type=float, nargs="?", const=t.reflection_dn, default=None, metavar="DN",
                       help=f"laser band reflected off the lower electrode, out of focus: peak radiance in DN "
                            f"(typical {t.reflection_dn:g})")
    group.add_argument("--glints", type=int, nargs="?", const=t.glints, default=None, metavar="N",
                       help=f"out-of-focus glints (typical {t.glints}, of about --glint-dn each)")
    group.add_argument("--glint-dn", type=float, default=None, metavar="DN",
                       help=f"typical peak radiance of a glint (typical {t.glint_dn:g})")
    group.add_argument("--brightness-spread", type=float, nargs="?", const=t.brightness_spread, default=None,
                       metavar="RATIO", help=f"brightest over faintest particle, log-uniform about --brightness "
                                             f"(typical {t.brightness_spread:g}; saturates in-focus particles)")
    group.add_argument("--lattice-drift-px", type=float, nargs="+", default=None, metavar="D",
                       help="shift DX [DY] in px of the micro-lens lattice in the exposure from the white images' "
                            f"(typical {t.lattice_drift_px[0]:g} {t.lattice_drift_px[1]:g})")
    group.add_argument("--lattice-drift-rad", type=float, default=None, metavar="RAD",
                       help=f"rotation of the lattice in the exposure from the white images' (typical "
                            f"{t.lattice_drift_rad:g})")
    group.add_argument("--varied-scene", action=argparse.BooleanOptionalAction, default=None,
                       help="draw the cluster's size, shape, tilt and placement from wide ranges")


def realism_from_args(args: argparse.Namespace) -> Realism:
    """The `Realism` the options ask for: the preset's effect groups, then each option given.

    Raises
    ------
    ParameterError
        An unknown effect name, or a value out of range.
    """
    effects = [] if args.realism is None else [e.strip() for e in args.realism.split(",") if e.strip()]
    realism = Realism.only(*effects) if effects else Realism()
    changes: dict = {}
    for option, name in [("blur_px", "blur_px"), ("psf_halo", "psf_halo"), ("psf_halo_px", "psf_halo_px"),
                         ("rim_response", "rim_response"),
                         ("lens_transmission_spread", "lens_transmission_spread"),
                         ("vignetting", "vignetting_corner_cut"), ("vignetting_onset", "vignetting_onset"),
                         ("hot_pixels", "hot_pixel_fraction"), ("dead_pixels", "dead_pixel_fraction"),
                         ("glow", "glow_gradient"), ("reflection", "reflection_dn"), ("glints", "glints"),
                         ("glint_dn", "glint_dn"), ("brightness_spread", "brightness_spread"),
                         ("lattice_drift_rad", "lattice_drift_rad"), ("varied_scene", "varied_scene")]:
        value = getattr(args, option)
        if value is not None:
            changes[name] = value
    if args.lattice_drift_px is not None:
        if len(args.lattice_drift_px) > 2:
            raise ParameterError("--lattice-drift-px takes DX and optionally DY")
        drift = list(args.lattice_drift_px) + [0.0] * (2 - len(args.lattice_drift_px))
        changes["lattice_drift_px"] = tuple(drift)
    if changes.get("glints") and "glint_dn" not in changes and realism.glint_dn == 0:
        changes["glint_dn"] = _TYPICAL.glint_dn
    return replace(realism, **changes)


def run(args: argparse.Namespace) -> int:
    start = time.perf_counter()

    def progress(line: str) -> None:
        if not args.quiet:
            print(f"[{time.perf_counter() - start:6.1f} s] {line}", file=sys.stderr, flush=True)

    try:
        realism = realism_from_args(args)
        serial = {} if args.serial is None else {"serial": args.serial}
        front, target = optics_from_args(args)
        files = write_scenario(args.out, args.scenario, args.seed, count=args.count, size=args.size,
                               brightness_dn=args.brightness, background_dn=args.background,
                               centre_z_mm=args.centre_z, realism=realism, motion=motion_from_args(args),
                               progress=progress, front_optics=front, target=target, **serial)
    except AnalysisError as exc:
        print(f"plenodust simulate: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"plenodust simulate: cannot write to {args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    print(files.scenario_json)
    return 0
