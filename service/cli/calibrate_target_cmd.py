"""`plenodust calibrate-target EXPOSURE... --positions Z1 Z2 ... --pitch MM --out FILE`: a metric
calibration from a dot target imaged at known stage positions.

Each exposure shows the target at one stage position (give them in the same order, or a folder
whose exposures sort in that order). The dots are found with the pipeline, their grid identified
(rows, columns, the dot nearest the optical axis) and a mapping from where the pipeline sees a
particle to where it is fitted: a polynomial (Soloff, Adrian & Liu 1997) and a physical model
(the metadata's thin main lens, an auxiliary thin lens and radial distortion) compete on
held-back stage positions; the better is kept.

The coordinates it gives are in the target's frame: X along its rows of dots, Y down its columns,
Z the stage position in the units and zero of --positions (distances from the camera's main lens
give camera-frame depths; positions must grow away from the camera).

Writes the calibration as JSON (docs/interfaces.md; --out DIR names it
metric-<serial>-z<zoom>-f<focus>.json), and prints the chosen model and the residuals in
micrometres per stage position and axis, fitted and held back. Exit status 0 on success,
1 when the target's exposures cannot give a calibration (the message says why and what to do),
2 for unusable arguments.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from analysis.errors import AnalysisError

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "calibrate-target", help="metric calibration (X, Y, Z in mm) from a dot target at known stage positions",
        description=__doc__.split("\n\n", 1)[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("exposures", nargs="+", type=Path, metavar="EXPOSURE",
                   help="one exposure per stage position (.lfp, .RAW with its .TXT), or a folder of them")
    p.add_argument("--calibration", required=True, type=Path, metavar="DIR",
                   help="the camera's white images (MOD_nnnn.RAW/.TXT) or a data.C.N bundle")
    p.add_argument("--positions", type=float, nargs="+", default=None, metavar="MM",
                   help="stage position of each exposure, in order (mm; larger = farther from the camera)")
    p.add_argument("--positions-file", type=Path, default=None, metavar="FILE",
                   help="instead of --positions: a text file with one position per line, or the target.json "
                        "that plenodust simulate --scenario target writes (also gives --pitch)")
    p.add_argument("--pitch", type=float, default=None, metavar="MM", help="distance between neighbouring dots")
    p.add_argument("--out", required=True, type=Path, metavar="FILE",
                   help="the calibration file (.json), or a folder of them")
    p.add_argument("--aux-lens-f", type=float, default=None, metavar="MM",
                   help="focal length of an auxiliary lens in front of the camera, if known: a starting point of "
                        "the physical model (it is fitted either way)")
    p.add_argument("--aux-lens-distance", type=float, default=None, metavar="MM",
                   help="its distance in front of the main lens, if known")
    p.add_argument("--cache", type=Path, default=None, metavar="DIR",
                   help="calibration and look-up table cache (default $PLENODUST_CACHE or ~/.cache/plenodust)")
    p.add_argument("--no-cache", action="store_true", help="neither read nor write the cache")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run)


def positions_and_pitch(args: argparse.Namespace) -> tuple[list[float], float]:
    """The stage positions and the pitch, from the options or the positions file.

    Raises
    ------
    ValueError
        With a message for the user.
    """
    positions, pitch = args.positions, args.pitch
    if args.positions_file is not None:
        if positions:
            raise ValueError("give --positions or --positions-file, not both")
        text = args.positions_file.read_text()
        if args.positions_file.suffix.lower() == ".json":
            doc = json.loads(text)
            positions = [float(z) for z in doc["positions_mm"]]
            pitch = pitch if pitch is not None else float(doc["pitch_mm"])
        else:
            positions = [float(line.split("#")[0]) for line in text.splitlines() if line.split("#")[0].strip()]
    if not positions:
        raise ValueError("give the stage position of each exposure: --positions Z1 Z2 ... (mm)")
    if pitch is None:
        raise ValueError("give the dot pitch of the target: --pitch MM")
    return positions, pitch


def run(args: argparse.Namespace) -> int:
    from service.cli.process_cmd import batch_inputs

    try:
        positions, pitch = positions_and_pitch(args)
    except (ValueError, KeyError, OSError) as exc:
        print(f"plenodust calibrate-target: {exc}", file=sys.stderr)
        return EXIT_USAGE
    files = batch_inputs("calibrate-target", args.exposures, args.calibration)
    if files is None:
        return EXIT_USAGE
    if args.out.suffix.lower() != ".json":
        args.out.mkdir(parents=True, exist_ok=True)
    try:
        metric = _calibrate(args, files, positions, pitch)
    except (AnalysisError, OSError) as exc:
        print(f"plenodust calibrate-target: {exc}", file=sys.stderr)
        return EXIT_FAILED
    from analysis.calibration.metric_files import save_metric_calibration

    path = save_metric_calibration(metric, args.out)
    json.dump(summary(metric, path), sys.stdout, indent=2)
    sys.stdout.write("\n")
    return EXIT_OK


def _calibrate(args: argparse.Namespace, files: list[Path], positions: list[float], pitch: float) -> Any:
    from analysis.cache import Cache
    from analysis.calibration.cache import load_calibration
    from analysis.camera.front_optics import FrontOptics
    from analysis.formats.exposure import read_exposure
    from analysis.pipeline.target import calibrate_target
    from service.cli.process_cmd import default_cache_dir

    cache_dir = None if args.no_cache else (args.cache or default_cache_dir())
    say = (lambda line: None) if args.quiet else (
        lambda line: print(f"plenodust calibrate-target: {line}", file=sys.stderr, flush=True))
    first = read_exposure(files[0])
    calibration = load_calibration(args.calibration, first.metadata, serial=first.serial, cache_dir=cache_dir)
    guess = None
    if args.aux_lens_f is not None:
        guess = FrontOptics.with_lens(args.aux_lens_f, args.aux_lens_distance or 0.0)
    say(f"finding the dots in {len(files)} exposures")
    return calibrate_target(files, calibration, positions, pitch, cache=Cache(directory=cache_dir),
                            front_guess=guess, progress=say)


def summary(metric: Any, path: Path) -> dict[str, Any]:
    """What the command prints: the file, the chosen model, residuals (micrometres) and the comparison."""
    report = metric.report
    return {"out": str(path), **metric.camera.to_dict(), "model": metric.mapping.kind, "mapping": metric.mapping.name,
            "volume": metric.volume.to_dict(), "field_of_view_mm": report.get("field_of_view_mm"),
            "depth_range_mm": report.get("depth_range_mm"), "outliers": report.get("outliers"),
            "residuals_um": report.get("residuals"),
            "comparison": {kind: {"held_out_rms_um": c["held_out_rms_um"], "fit_rms_um": c["fit_rms_um"],
                                  "mapping": c["mapping"]} for kind, c in report.get("comparison", {}).items()},
            "exposures": [{k: e[k] for k in ("name", "position_mm", "dots_found", "dots_on_grid")}
                          for e in report.get("target", {}).get("exposures", [])]}
