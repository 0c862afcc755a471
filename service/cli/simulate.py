"""`plenodust simulate`: write a simulated exposure, its calibration and its truth as camera files."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from analysis.errors import AnalysisError
from analysis.simulation.scenarios import SCENARIO_NAMES
from analysis.simulation.camera import F01_SIZE
from analysis.simulation.scenario_files import write_scenario


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "simulate", help="write a simulated F01 exposure with known particle positions",
        description="Render a particle cluster through the simulated F01 and write it as the camera stores it: "
                    "DIR/IMG_nnnn.lfp, IMG_nnnn.RAW + .TXT, IMG_nnnn.truth.csv (X, Y, Z in mm), "
                    "DIR/calibration/MOD_nnnn.RAW + .TXT white images and DIR/scenario.json.")
    parser.add_argument("--scenario", choices=SCENARIO_NAMES, default="tilted-layer",
                        help="cluster to simulate (default: tilted-layer, the paper's 13-degree layer)")
    parser.add_argument("--seed", type=int, default=1, help="random seed; the same seed writes the same bytes")
    parser.add_argument("--out", type=Path, required=True, help="folder to write into (created)")
    parser.add_argument("--count", type=int, default=1,
                        help="number of exposures IMG_0001..N; the cluster moves slightly between them")
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
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    start = time.perf_counter()

    def progress(line: str) -> None:
        if not args.quiet:
            print(f"[{time.perf_counter() - start:6.1f} s] {line}", file=sys.stderr, flush=True)

    try:
        files = write_scenario(args.out, args.scenario, args.seed, count=args.count, size=args.size,
                               brightness_dn=args.brightness, background_dn=args.background,
                               centre_z_mm=args.centre_z, progress=progress)
    except AnalysisError as exc:
        print(f"plenodust simulate: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"plenodust simulate: cannot write to {args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    print(files.scenario_json)
    return 0
