"""`plenodust score FILE --truth TRUTH`: how well a particle table recovers a simulated truth.

Pairs the particles of a table written by ``plenodust process`` (``.csv`` or ``.h5``) with the
true ones of ``plenodust simulate`` (``IMG_nnnn.truth.csv``) and prints, as JSON: recall,
precision, depth error (after a linear fit, and absolute), lateral error and the depth error by
defocus, as fractions of the mean 3D nearest-neighbour distance, and the shadowing pairs
separated. With the exposure at hand (``IMG_nnnn.lfp`` or ``.RAW`` beside the truth, or
``--exposure``) it also prints the depth floor: the error of the best estimate that the raw
pixels alone allow. Exit status 0, or 2 when a file cannot be used.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from analysis.errors import AnalysisError


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("score", help="recall, precision and errors of a particle table against simulated truth",
                              description=__doc__.split("\n\n", 1)[1])
    p.add_argument("table", type=Path, metavar="FILE", help="particle table (.csv or .h5) from plenodust process")
    p.add_argument("--truth", type=Path, required=True, metavar="TRUTH",
                   help="IMG_nnnn.truth.csv from plenodust simulate")
    p.add_argument("--exposure", type=Path, default=None,
                   help="the simulated exposure (.lfp or .RAW), for the depth floor; default: beside TRUTH")
    p.add_argument("--frame", type=int, default=None, help="only this frame of a batch table")
    p.set_defaults(func=run)


def _exposure_beside(truth: Path) -> Path | None:
    stem = truth.name.removesuffix(".truth.csv")
    for suffix in (".lfp", ".RAW"):
        candidate = truth.with_name(stem + suffix)
        if candidate.is_file():
            return candidate
    return None


def run(args: argparse.Namespace) -> int:
    from analysis.simulation.scoring import depth_floor, score
    from analysis.camera.model import CameraModel
    from analysis.formats.exposure import read_exposure
    from analysis.errors import ParameterError
    from analysis.formats.particle_table import read_table

    try:
        found = read_table(args.table, frame=args.frame)
        truth = read_table(args.truth, required=("X", "Y", "Z", "alpha", "x", "y", "blur_pitches"))
        if "intensity" in truth:
            raise ParameterError(f"{args.truth} is a table of particles found (it has fit columns such as "
                                 "intensity); give the simulator's IMG_nnnn.truth.csv")
        report = score(found, truth).to_dict()
        exposure_path = args.exposure or _exposure_beside(args.truth)
        if exposure_path is not None:
            lattice = CameraModel.from_metadata(read_exposure(exposure_path).metadata).lattice
            single, floor = depth_floor(truth, lattice, nn_mm=report["nn_mm"])
            report["depth_floor"] = {"single_lens": single, "rms_over_nn": floor}
    except (AnalysisError, OSError, KeyError, ValueError) as exc:
        print(f"plenodust score: {exc}", file=sys.stderr)
        return 2
    json.dump(report, sys.stdout, indent=2, default=float)
    sys.stdout.write("\n")
    return 0
