"""`plenodust validate-plane FILE`: how flat a particle layer came out (the paper's check).

Reads the ``X, Y, Z`` columns of a table written by ``plenodust process`` (``.csv`` or
``.h5``), fits a plane and prints, as JSON: its normal, tilt against the image plane, the RMS
distance of the particles from it, the mean 3D nearest-neighbour distance, and their ratio.
Exit status 0, or 2 when the file cannot be used.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from analysis.errors import AnalysisError


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("validate-plane", help="plane fit, tilt and depth scatter of a particle table",
                              description=__doc__.split("\n\n", 1)[1])
    p.add_argument("table", type=Path, metavar="FILE", help="particle table (.csv or .h5) from plenodust process")
    p.add_argument("--frame", type=int, default=None, help="only this frame of a batch table")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from analysis.camera.coordinates import validate_plane
    from analysis.formats.particle_table import read_table

    try:
        columns = read_table(args.table, frame=args.frame)
        report = validate_plane(columns["X"], columns["Y"], columns["Z"])
    except (AnalysisError, OSError, KeyError, ValueError) as exc:
        print(f"plenodust validate-plane: {args.table}: {exc}", file=sys.stderr)
        return 2
    json.dump(report.to_dict(), sys.stdout, indent=2)
    sys.stdout.write("\n")
    return 0
