"""`plenodust link TABLE --out FILE`: link a run's particle table into trajectories.

TABLE is a batch table with a ``frame`` column (``plenodust process DIR --out run.csv`` or
``.h5``, or ``plenodust track``'s output, which is linked again). Its ``t`` column (seconds since
the first shot, from the exposures' clocks) times the shots; a table without one needs
``--interval``. ``--out FILE.csv`` or ``FILE.h5`` gets the linked table (columns as ``plenodust
track`` writes them), ``--summary FILE.csv`` the structure per shot. A JSON report goes to stdout.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from analysis.errors import AnalysisError

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "link", help="link a processed run's particle table into 3D trajectories",
        description=__doc__.split("\n\n", 1)[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("table", type=Path, metavar="TABLE", help="a batch table (.csv or .h5) with a frame column")
    p.add_argument("--out", required=True, type=Path, metavar="FILE", help="FILE.csv or FILE.h5 (NeXus)")
    add_link_arguments(p)
    p.set_defaults(func=run)


def add_link_arguments(p: argparse.ArgumentParser) -> None:
    """Options of linking and of the per-shot summary, shared by ``link`` and ``track``."""
    from analysis.tracking.linking import LinkParams
    from analysis.tracking.units import MF_DENSITY_KG_M3, MF_DIAMETER_UM

    d = LinkParams()
    g = p.add_argument_group("linking")
    g.add_argument("--memory", type=int, default=d.memory,
                   help=f"frames a particle may go unseen and keep its trajectory (default {d.memory})")
    g.add_argument("--gate", type=float, default=d.gate_sigma,
                   help=f"largest link, in measured step spreads (default {d.gate_sigma})")
    g.add_argument("--max-step-nn", type=float, default=d.max_step_nn,
                   help=f"search range cap, in mean nearest-neighbour distances (default {d.max_step_nn})")
    g.add_argument("--engine", choices=("plenodust", "trackpy"), default="plenodust",
                   help="plenodust (per-particle depth uncertainty, rotation predicted; default) or trackpy.link")
    g.add_argument("--interval", type=float, default=None, metavar="S",
                   help="seconds between shots, for exposures or tables without a clock")
    g.add_argument("--summary", type=Path, default=None, metavar="FILE.csv",
                   help="also write the structure per shot (count, temperature, shells)")
    g.add_argument("--particle-diameter-um", type=float, default=MF_DIAMETER_UM,
                   help=f"for temperatures (default {MF_DIAMETER_UM}, the paper's MF particles)")
    g.add_argument("--particle-density", type=float, default=MF_DENSITY_KG_M3, metavar="KG_M3",
                   help=f"for temperatures (default {MF_DENSITY_KG_M3:g}, melamine-formaldehyde)")


def link_params_from_args(args: argparse.Namespace) -> Any:
    from analysis.tracking.linking import LinkParams

    return LinkParams(memory=args.memory, gate_sigma=args.gate, max_step_nn=args.max_step_nn)


def write_linked(linked: Any, out: Path, *, parameters: dict) -> None:
    """The linked table as CSV or NeXus (``/entry/data`` with ``signal = Z``, parameters in
    ``/entry/process``)."""
    from analysis.formats.particle_table import write_csv, write_hdf5
    from analysis.tracking.run import linked_table_columns

    out.parent.mkdir(parents=True, exist_ok=True)
    columns = linked_table_columns(linked)
    if out.suffix.lower() == ".csv":
        write_csv(columns, out)
    else:
        write_hdf5(out, columns, parameters=parameters, title="plenodust trajectories")


def report(linked: Any, args: argparse.Namespace, *, prog: str) -> int:
    """The JSON report on stdout (and the summary file when asked)."""
    from analysis.formats.particle_table import write_csv
    from analysis.tracking.summary import summarize
    from analysis.tracking.trajectories import trajectory_lengths
    from analysis.tracking.units import particle_mass_kg

    mass = particle_mass_kg(args.particle_diameter_um, args.particle_density)
    summary = summarize(linked, mass_kg=mass)
    if args.summary is not None:
        args.summary.parent.mkdir(parents=True, exist_ok=True)
        write_csv(summary.table, args.summary)
    lengths = trajectory_lengths(linked)
    temperature, err = summary.temperature_ev()
    out = {"out": str(args.out), "frames": int(linked["frame"].nunique()) if len(linked) else 0,
           "particles": int(len(linked)), "trajectories": int(lengths.size),
           "mean_trajectory_frames": float(lengths.mean()) if lengths.size else math.nan,
           "position_noise_mm": summary.noise.to_dict()["sigma_mm"],
           "temperature_ev": temperature, "temperature_err_ev": err, "particle_mass_kg": mass}
    json.dump(out, sys.stdout, indent=2, allow_nan=True)
    sys.stdout.write("\n")
    return EXIT_OK


def run(args: argparse.Namespace) -> int:
    import pandas as pd

    from analysis.formats.particle_table import read_table
    from analysis.tracking.trajectories import link

    if args.out.suffix.lower() not in (".csv", ".h5", ".hdf5", ".nxs"):
        print(f"plenodust link: --out {args.out} must end in .csv or .h5", file=sys.stderr)
        return EXIT_USAGE
    try:
        table = read_table(args.table, required=("frame", "X", "Y", "Z"))
        link_params = link_params_from_args(args)
        linked = link(pd.DataFrame(table), link_params, engine=args.engine, interval_s=args.interval)
    except (AnalysisError, OSError) as exc:
        print(f"plenodust link: {exc}", file=sys.stderr)
        return EXIT_USAGE if isinstance(exc, AnalysisError) else EXIT_FAILED
    write_linked(linked, args.out, parameters={"linking": link_params.to_dict(), "engine": args.engine,
                                                 "source": str(args.table)})
    return report(linked, args, prog="link")
