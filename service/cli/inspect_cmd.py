"""`plenodust inspect FILE`: a Lytro file's sections, SHA-1 status and key metadata, as JSON.

Exit status: 0 when the file is sound, 1 when it was read but has problems (a SHA-1
mismatch, a missing section, a wrong raw size, ...), 2 when it cannot be read or recognised.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

EXIT_OK, EXIT_PROBLEMS, EXIT_UNREADABLE = 0, 1, 2


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "inspect", help="show a Lytro file's sections, SHA-1 status and key metadata as JSON",
        description="Inspect an .lfp picture, a data.C.N bundle, a camera .RAW/.TXT pair, a white-image "
                    ".TXT or a frame-metadata JSON. Exit 0 if sound, 1 if it has problems, 2 if unreadable.")
    parser.add_argument("file", type=Path, help="the file to inspect")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from analysis.formats.file_report import inspect_file

    try:
        report = inspect_file(args.file)
    except OSError as exc:
        print(f"plenodust inspect: cannot read {args.file}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_UNREADABLE
    json.dump(report.as_dict(), sys.stdout, indent=2)
    sys.stdout.write("\n")
    if not report.readable:
        return EXIT_UNREADABLE
    return EXIT_OK if report.ok else EXIT_PROBLEMS
