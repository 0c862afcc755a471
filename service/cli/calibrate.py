"""`plenodust calibrate`: choose a white image, fit its micro-lens lattice and micro-image profile, find
the camera's defective pixels, print the result as JSON."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from dataclasses import replace

from analysis.calibration.calibrate import Calibration
from analysis.calibration.cache import cache_path, cached_calibration
from analysis.calibration.camera_defects import camera_defects, defects_cache_path
from analysis.calibration.white_choice import defect_search_frames, select_white_image
from analysis.errors import AnalysisError
from analysis.formats.frame_metadata import parse_txt
from analysis.formats.whites import load_white_images


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "calibrate", help="fit the micro-lens lattice to a camera's white images",
        description="Choose the white image for a picture (same camera, bright, nearest zoomStep, then "
                    "focusStep), fit the micro-image lattice and the micro-image profile (optical blur, aperture "
                    "image radius, rim response) to it, find the camera's hot, stuck and dead pixels in its white "
                    "images (the dark ones included), and print it all as JSON. With --cache, the calibration is "
                    "cached by camera serial and white-image SHA-1, the defect map by the frames it was found in.")
    parser.add_argument("source", type=Path,
                        help="folder of MOD_nnnn.RAW + .TXT white images (C:\\T1CALIB), or a data.C.N bundle")
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--metadata", type=Path,
                       help="the picture's .TXT (frame metadata): choose the white image that suits it")
    which.add_argument("--white", help="calibrate this white image (e.g. MOD_0012) instead of choosing one")
    parser.add_argument("--serial", help="the picture's camera serial, if its .TXT does not carry one")
    parser.add_argument("--cache", type=Path, help="calibration cache folder (read, and written on a miss)")
    parser.add_argument("--no-defects", action="store_true", help="skip the search for defective pixels")
    parser.set_defaults(func=run)


def _report(calibration: Calibration, seconds: float, cache: Path | None, serial: str | None) -> dict:
    lat = calibration.lattice
    return {
        "white": {"name": calibration.white_name, "sha1": calibration.white_sha1, "serial": calibration.serial,
                  "zoom_step": calibration.zoom_step, "focus_step": calibration.focus_step},
        "lattice": {"origin_x": lat.origin_x, "origin_y": lat.origin_y, "pitch_px": lat.pitch_px,
                    "rotation_rad": lat.rotation_rad, "scale_x": lat.scale_x, "scale_y": lat.scale_y},
        "fit": {"rms_px": calibration.fit_rms_px, "n_lenses": calibration.fit_n_lenses,
                "centroid_rms_px": calibration.fit_centroid_rms_px},
        "profile": None if calibration.profile is None else calibration.profile.to_dict(),
        "blur_px": calibration.blur_px,
        "second_stop": None if calibration.second_stop is None else calibration.second_stop.to_dict(),
        "defects": None if calibration.defects is None else {
            "pixels": len(calibration.defects), "hot_or_stuck": calibration.defects.n_hot,
            "dead_or_dark": calibration.defects.n_dark, "frames": list(calibration.defects.frames),
            "key": calibration.defects.key,
            "cache_file": None if cache is None else str(defects_cache_path(cache, calibration.serial or serial,
                                                                            calibration.defects.key))},
        "from_cache": calibration.from_cache,
        "cache_file": None if cache is None else str(cache_path(cache, calibration.serial or serial,
                                                                        calibration.white_sha1)),
        "seconds": round(seconds, 3),
    }


def run(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    try:
        whites = load_white_images(args.source)
        metadata: dict | None = None
        serial = args.serial
        if args.metadata is not None:
            metadata, private = parse_txt(args.metadata.read_bytes(), what=str(args.metadata))
            serial = serial or (private.get("camera") or {}).get("serialNumber")
            white = select_white_image(whites, metadata, serial=serial)
        else:
            named = {w.name.upper(): w for w in whites}
            if args.white.upper() not in named:
                print(f"plenodust calibrate: no white image {args.white} in {args.source}; it holds "
                      f"{', '.join(sorted(named))}", file=sys.stderr)
                return 2
            white = named[args.white.upper()]
        calibration = cached_calibration(white, cache_dir=args.cache, serial=serial, fallback_metadata=metadata)
        if not args.no_defects:
            frames = defect_search_frames(whites, white, metadata or white.metadata, serial=serial)
            calibration = replace(calibration, defects=camera_defects(frames, calibration, cache_dir=args.cache,
                                                                      serial=serial))
    except AnalysisError as exc:
        print(f"plenodust calibrate: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"plenodust calibrate: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(_report(calibration, time.perf_counter() - start, args.cache, serial), indent=2))
    return 0
