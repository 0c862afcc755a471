"""`plenodust track EXPOSURES_OR_FOLDER --calibration DIR --out FILE`: process a run and link it.

Processes every exposure (as ``plenodust process``, with the same options) and links the
particles of consecutive shots into trajectories, in the order the exposures' clocks say they
were taken. ``--out FILE.csv`` or ``FILE.h5`` (NeXus) gets the linked table: ``frame, t,
particle`` (trajectory id, as in trackpy), ``index`` (row in its exposure's table), ``x, y,
alpha, X, Y, Z, vX, vY, vZ`` (mm/s) and the quality columns. ``--summary FILE.csv`` also writes
the structure per shot (count, drift, rotation, RMS velocity, kinetic temperature with the
position noise taken out, a ball's shells).

A JSON report goes to stdout: exposures, particles, trajectories, links, the position noise and
the run's temperature. Exit status: 0 done, 1 some exposures failed, 2 unusable arguments.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from analysis.errors import AnalysisError

from service.cli.link_cmd import add_link_arguments, link_params_from_args, report, write_linked
from service.cli.process_cmd import (Say, add_pipeline_arguments, batch_inputs, default_cache_dir, load_kernels,
                                     params_from_args)

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "track", help="process a run's exposures and link them into 3D trajectories",
        description=__doc__.split("\n\n", 1)[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("exposures", nargs="+", type=Path, metavar="EXPOSURES_OR_FOLDER",
                   help=".lfp files, .RAW files (with their .TXT beside them), or folders of them")
    p.add_argument("--calibration", required=True, type=Path, metavar="DIR",
                   help="the camera's white images (MOD_nnnn.RAW/.TXT) or a data.C.N bundle")
    p.add_argument("--out", required=True, type=Path, metavar="FILE", help="FILE.csv or FILE.h5 (NeXus)")
    p.add_argument("--cache", type=Path, default=None, metavar="DIR",
                   help="calibration and look-up table cache (default $PLENODUST_CACHE or ~/.cache/plenodust)")
    p.add_argument("--no-cache", action="store_true", help="neither read nor write the cache")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    add_link_arguments(p)
    add_pipeline_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from analysis.cache import Cache
    from analysis.tracking.run import track

    say = Say(quiet=args.quiet, prog="track")
    try:
        params = params_from_args(args)
        link_params = link_params_from_args(args)
    except AnalysisError as exc:
        print(f"plenodust track: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if args.out.suffix.lower() not in (".csv", ".h5", ".hdf5", ".nxs"):
        print(f"plenodust track: --out {args.out} must end in .csv or .h5", file=sys.stderr)
        return EXIT_USAGE
    files = batch_inputs("track", args.exposures, args.calibration)
    if files is None:
        return EXIT_USAGE
    cache_dir = None if args.no_cache else (args.cache or default_cache_dir())
    load_kernels(say)
    done = {"n": 0}

    def progress(index: int, fraction: float, stage: str) -> None:
        if stage == "done":
            done["n"] += 1
            say(f"{done['n']}/{len(files)} exposures processed")

    try:
        linked = track(files, args.calibration, params, link_params=link_params, engine=args.engine,
                       cache=Cache(directory=cache_dir), cache_dir=cache_dir, interval_s=args.interval,
                       progress=progress)
    except (AnalysisError, OSError) as exc:
        print(f"plenodust track: {exc}", file=sys.stderr)
        return EXIT_FAILED
    say(f"linked {len(files)} exposures")
    write_linked(linked, args.out, parameters={"pipeline": params.to_dict(), "linking": link_params.to_dict(),
                                                 "engine": args.engine})
    return report(linked, args, prog="track")
