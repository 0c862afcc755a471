"""The `plenodust` command: one sub-command per module in this package.

Each command module exposes ``register(subparsers)``, which adds its parser and sets
``func`` to a callable taking the parsed arguments and returning an exit code.

Only the module of the command being run is imported (``--help`` imports none): the
analysis pulls in numba and scipy, a second or two that ``plenodust --help``, ``inspect`` or
``camera list`` should not wait for.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

# Command name -> (module in service.cli, one-line help), in the order `--help` lists them.
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("simulate", "write a simulated F01 exposure with known particle positions"),
    "process": ("process_cmd", "3D particle coordinates from raw exposures (.lfp, .RAW+.TXT, or folders)"),
    "track": ("track_cmd", "process a run's exposures and link them into 3D trajectories"),
    "link": ("link_cmd", "link a processed run's particle table into 3D trajectories"),
    "validate-plane": ("validate_plane_cmd", "plane fit, tilt and depth scatter of a particle table"),
    "score": ("score_cmd", "recall, precision and errors of a particle table against simulated truth"),
    "inspect": ("inspect_cmd", "show a Lytro file's sections, SHA-1 status and key metadata as JSON"),
    "camera": ("camera", "talk to a Lytro F01: info, list, pull, calibration, watch"),
    "serve": ("serve", "run the lab service"),
    "demo": ("demo", "run the service with a simulated camera that takes a shot every few seconds"),
    "calibrate": ("calibrate", "fit the micro-lens lattice to a camera's white images"),
    "calibrate-target": ("calibrate_target_cmd", "metric calibration (X, Y, Z in mm) from a dot target at known "
                                                 "stage positions"),
    "warm-up": ("warmup_cmd", "compile the analysis kernels into the numba cache (make setup runs it)"),
}
# Kept for callers that list the modules.
COMMAND_MODULES: list[str] = [module for module, _ in COMMANDS.values()]


def _command_in(argv: list[str]) -> str | None:
    """The sub-command named in ``argv`` (the first word that is not an option), if known."""
    for word in argv:
        if not word.startswith("-"):
            return word if word in COMMANDS else None
    return None


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s module is imported (all of them with ``command="*"``)."""
    parser = argparse.ArgumentParser(
        prog="plenodust",
        description="3D dusty-plasma particle coordinates from single Lytro F01 exposures.")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        if command in (name, "*"):
            importlib.import_module(f"service.cli.{module}").register(sub)
        else:
            sub.add_parser(name, help=help_text, add_help=False)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(_command_in(argv))
    args = parser.parse_args(argv)
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        # Ctrl-C ends a command; what it wrote is whole (files are renamed into place).
        print(f"plenodust {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
