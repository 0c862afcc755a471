"""`plenodust process EXPOSURE... --calibration DIR --out FILE`: particle tables from raw exposures.

EXPOSURE is an ``.lfp``, a ``.RAW`` with its ``.TXT`` beside it, or a folder of them (an
``.lfp`` and a ``.RAW`` of the same name count once, the ``.lfp`` is read). Several
exposures are one batch: they share the calibration, the look-up table and the compiled
kernels.

Output:

* one exposure: ``--out FILE.csv`` or ``FILE.h5``;
* a batch: ``--out FILE.csv``/``FILE.h5`` holds all particles with a ``frame`` column (the
  exposure's index in the order processed, listed in the summary), or ``--out DIR`` (no
  such suffix) gets one ``<name>.csv`` (``--format h5``: ``<name>.h5``) per exposure.

``--save-stack`` also writes the refocused images, the sub-aperture image and the brightness
curves as HDF5 (into the ``.h5`` output, or into ``<out>.stack.h5`` beside a CSV).

``--metric-calibration`` takes ``X, Y, Z`` from a target calibration (``plenodust
calibrate-target``): a file, or a folder from which each exposure's camera, zoom and focus picks one.

A JSON summary (one object per exposure: name, frame, particles, warnings, seconds, and which
calibration gave ``X, Y, Z``) goes to stdout. Exit status: 0 when every exposure was processed, 1 when some failed (each named
on stderr), 2 for unusable arguments.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from analysis.errors import AnalysisError

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2
_TABLE_SUFFIXES = (".csv", ".h5", ".hdf5", ".nxs")


def default_cache_dir() -> Path:
    """``$PLENODUST_CACHE``, else ``~/.cache/plenodust`` (calibrations and look-up tables)."""
    # The CLI runs without the service's settings; this one variable is its whole configuration.
    return Path(os.environ.get("PLENODUST_CACHE") or Path.home() / ".cache" / "plenodust")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "process", help="3D particle coordinates from raw exposures (.lfp, .RAW+.TXT, or folders)",
        description=__doc__.split("\n\n", 1)[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("exposures", nargs="+", type=Path, metavar="EXPOSURE",
                   help=".lfp, .RAW (with its .TXT beside it), or a folder of them")
    p.add_argument("--calibration", required=True, type=Path, metavar="DIR",
                   help="the camera's white images (MOD_nnnn.RAW/.TXT) or a data.C.N bundle")
    p.add_argument("--out", required=True, type=Path, metavar="FILE",
                   help="FILE.csv or FILE.h5; for a batch also a folder (one file per exposure)")
    p.add_argument("--format", choices=("csv", "h5"), default="csv",
                   help="file type per exposure when --out is a folder (default csv)")
    p.add_argument("--cache", type=Path, default=None, metavar="DIR",
                   help="calibration and look-up table cache (default $PLENODUST_CACHE or ~/.cache/plenodust)")
    p.add_argument("--no-cache", action="store_true", help="neither read nor write the cache")
    p.add_argument("--save-stack", action="store_true",
                   help="also write the refocused images, sub-aperture image and brightness curves (HDF5)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")

    add_pipeline_arguments(p)
    p.set_defaults(func=run)


def add_pipeline_arguments(p: argparse.ArgumentParser) -> None:
    """The pipeline's options (refocus, detection and depth, physical coordinates), shared by
    ``process`` and ``track``; :func:`params_from_args` reads them."""
    from analysis.pipeline.params import PipelineParams

    d = PipelineParams()
    g = p.add_argument_group("refocus")
    g.add_argument("--alpha-min", type=float, default=None,
                   help="refocus range, with --alpha-max (default: the range that holds the exposure's particles, "
                        "found from the exposure)")
    g.add_argument("--alpha-max", type=float, default=None, help="see --alpha-min")
    g.add_argument("--slices", type=int, default=d.n_slices,
                   help=f"refocused images (default {d.n_slices}); for a range found from the exposure, images per "
                        "0.026 of alpha, and at least this many")
    g.add_argument("--depth-range", type=float, nargs=2, metavar=("NEAR_MM", "FAR_MM"), default=None,
                   help="derive the alpha range from depths (thin-lens model) instead")
    g.add_argument("--aperture-fraction", type=float, default=d.aperture_fraction,
                   help=f"central part of the aperture radius for the sub-aperture image (default {d.aperture_fraction})")
    g.add_argument("--blur-sigma", type=float, default=d.blur_sigma_px,
                   help=f"Gaussian blur of the sub-aperture image, output pixels (default {d.blur_sigma_px})")
    g.add_argument("--grid-oversample", type=float, default=d.grid_oversample,
                   help=f"output pixels per lens row spacing (default {d.grid_oversample})")

    g = p.add_argument_group("detection and depth")
    g.add_argument("--threshold", type=float, default=None,
                   help="absolute threshold on the product images (default: from the noise)")
    g.add_argument("--threshold-sigma", type=float, default=d.threshold_sigma,
                   help=f"threshold in noise sigmas above the background (default {d.threshold_sigma})")
    g.add_argument("--min-pixels", type=int, default=d.min_pixels, help=f"default {d.min_pixels}")
    g.add_argument("--link-radius", type=float, default=d.link_radius_px,
                   help=f"linking radius across slices, output pixels (default {d.link_radius_px})")
    g.add_argument("--min-prominence", type=float, default=d.min_prominence,
                   help=f"a second maximum of a curve counts above this fraction (default {d.min_prominence})")
    g.add_argument("--no-depth-prior", action="store_true",
                   help="depth from each particle's own pixels only: no prior from neighbours on one surface "
                        "(particles whose light falls in one micro-lens keep a wide alpha_std)")
    g.add_argument("--late-pass", action=argparse.BooleanOptionalAction, default=d.late_pass,
                   help="one more detection pass after deblending: finds more of the faint particles blurred over "
                        "many pitches among brighter ones (realistic crowds: 1.5-2 %% more), at about 1.3x the time; "
                        "--no-late-pass for speed")
    g.add_argument("--glints", action=argparse.BooleanOptionalAction, default=d.glints,
                   help="find compact sources far out of focus beyond the particles' range (glints off electrodes "
                        "or windows) and take their light off the image first, and those seen through the cluster once "
                        "the particles are fitted; --no-glints to keep it")

    g = p.add_argument_group("physical coordinates (default: the metadata's thin-lens model)")
    g.add_argument("--metric-calibration", type=Path, default=None, metavar="FILE",
                   help="a target calibration (plenodust calibrate-target), or a folder of them: the one of the "
                        "exposure's camera, zoom and focus is used (none there: the thin lens, with a warning)")
    g.add_argument("--pixel-size-mm", type=float, default=None, help="object-space size of an output pixel")
    g.add_argument("--depth-per-alpha-mm", type=float, default=None, help="dZ/dalpha (negative for a normal lens)")
    g.add_argument("--reference-alpha", type=float, default=d.reference_alpha)
    g.add_argument("--reference-z-mm", type=float, default=d.reference_z_mm)


def params_from_args(args: argparse.Namespace) -> Any:
    from analysis.pipeline.params import PipelineParams

    return PipelineParams(
        alpha_min=args.alpha_min, alpha_max=args.alpha_max, n_slices=args.slices,
        depth_range_mm=tuple(args.depth_range) if args.depth_range else None,
        aperture_fraction=args.aperture_fraction, blur_sigma_px=args.blur_sigma,
        grid_oversample=args.grid_oversample, threshold=args.threshold, threshold_sigma=args.threshold_sigma,
        min_pixels=args.min_pixels, link_radius_px=args.link_radius, min_prominence=args.min_prominence,
        depth_prior=not args.no_depth_prior, late_pass=args.late_pass, glints=args.glints,
        pixel_size_mm=args.pixel_size_mm, depth_per_alpha_mm=args.depth_per_alpha_mm,
        reference_alpha=args.reference_alpha, reference_z_mm=args.reference_z_mm)


def batch_inputs(command: str, exposures: list[Path], calibration: Path) -> list[Path] | None:
    """The exposure files that ``exposures`` name (:func:`analysis.pipeline.batch.exposure_files`), or
    None once it has said on stderr what is missing: no exposure, or no calibration folder."""
    from analysis.pipeline.batch import exposure_files

    files = exposure_files(exposures)
    if not files:
        print(f"plenodust {command}: no .lfp or .RAW exposure found in " + ", ".join(str(p) for p in exposures),
              file=sys.stderr)
        return None
    if not calibration.exists():
        print(f"plenodust {command}: calibration {calibration} does not exist; give the folder of the camera's "
              "MOD_nnnn.RAW/.TXT white images or a data.C.N bundle", file=sys.stderr)
        return None
    return files


class _Coordinates:
    """The physical calibration of each exposure: its target calibration from ``--metric-calibration``
    (picked once per camera and zoom/focus setting), else None (the pipeline's default)."""

    def __init__(self, source: Path | None) -> None:
        self.source = source
        self._chosen: dict[tuple, Any] = {}

    def __call__(self, exposure: Any) -> Any:
        if self.source is None:
            return None
        from analysis.calibration.metric_files import camera_key, coordinates_for

        key = camera_key(exposure.metadata, exposure.serial)
        if key not in self._chosen:
            self._chosen[key] = coordinates_for(self.source, exposure.metadata, serial=exposure.serial)
        return self._chosen[key]


def run(args: argparse.Namespace) -> int:
    from analysis.cache import Cache
    from analysis.formats.exposure import read_exposure
    from analysis.formats.particle_table import combine, write_csv
    from analysis.pipeline.result import write_results_hdf5
    from analysis.pipeline.batch import CalibrationFolder
    from analysis.pipeline.process import process

    try:
        params = params_from_args(args)
    except AnalysisError as exc:
        print(f"plenodust process: {exc}", file=sys.stderr)
        return EXIT_USAGE
    files = batch_inputs("process", args.exposures, args.calibration)
    if files is None:
        return EXIT_USAGE
    out: Path = args.out
    to_folder = len(files) > 1 and out.suffix.lower() not in _TABLE_SUFFIXES
    if not to_folder and out.suffix.lower() not in _TABLE_SUFFIXES:
        print(f"plenodust process: --out {out} must end in .csv or .h5", file=sys.stderr)
        return EXIT_USAGE
    if to_folder:
        out.mkdir(parents=True, exist_ok=True)
    elif out.parent and not out.parent.exists():
        out.parent.mkdir(parents=True, exist_ok=True)

    if args.metric_calibration is not None and (args.pixel_size_mm is not None or args.depth_per_alpha_mm is not None):
        print("plenodust process: give --metric-calibration or a user calibration (--pixel-size-mm, "
              "--depth-per-alpha-mm), not both", file=sys.stderr)
        return EXIT_USAGE
    if args.metric_calibration is not None and not args.metric_calibration.exists():
        print(f"plenodust process: metric calibration {args.metric_calibration} does not exist; give the file "
              "plenodust calibrate-target wrote, or a folder of them", file=sys.stderr)
        return EXIT_USAGE
    cache_dir = None if args.no_cache else (args.cache or default_cache_dir())
    calibrations = CalibrationFolder(args.calibration, cache_dir)
    coordinates = _Coordinates(args.metric_calibration)
    cache = Cache(directory=cache_dir)
    say = Say(quiet=args.quiet)
    load_kernels(say)
    bar = progress_bar(len(files), quiet=args.quiet)
    results, summary, failed = [], [], 0
    for index, path in enumerate(files):
        entry: dict[str, Any] = {"exposure": str(path)}
        try:
            exposure = read_exposure(path)
            report = ExposureProgress(bar, say, index, len(files), path.name)
            result = process(exposure, calibrations(exposure), params, keep_stack=args.save_stack,
                             progress=report, cache=cache, coordinates=coordinates(exposure))
        except (AnalysisError, OSError) as exc:
            failed += 1
            message = getattr(exc, "strerror", None) if isinstance(exc, OSError) and not isinstance(
                exc, AnalysisError) else None
            print(f"plenodust process: {path}: {message or exc}", file=sys.stderr)
            entry["error"] = f"{type(exc).__name__}: {exc}"
            summary.append(entry)
            continue
        if to_folder:
            target = out / f"{path.stem}.{args.format}"
            _write_one(result, target, save_stack=args.save_stack)
            entry["out"] = str(target)
        else:
            entry["frame"] = len(results)
            results.append(result)
        entry.update(particles=len(result), warnings=result.warnings,
                     seconds=round(result.timings.get("total", float("nan")), 4),
                     coordinates={k: result.coordinates[k] for k in ("kind", "model", "sha1")
                                  if k in result.coordinates})
        summary.append(entry)
        if to_folder:
            result.stack = result.subaperture = None  # keep memory to one exposure
    if bar is not None:
        bar.close()

    if not to_folder and results:
        if len(results) == 1:
            _write_one(results[0], out, save_stack=args.save_stack)
        elif out.suffix.lower() == ".csv":
            write_csv(combine((r.particles for r in results), times=[r.shot_time for r in results]), out)
            if args.save_stack:
                write_results_hdf5(results, _stack_path(out))
        else:
            write_results_hdf5(results, out)
    json.dump({"out": str(out), "exposures": summary}, sys.stdout, indent=2)
    sys.stdout.write("\n")
    return EXIT_FAILED if failed else EXIT_OK


def _stack_path(csv_path: Path) -> Path:
    return csv_path.with_name(csv_path.stem + ".stack.h5")


def _write_one(result: Any, target: Path, *, save_stack: bool) -> None:
    if target.suffix.lower() == ".csv":
        result.to_csv(target)
        if save_stack:
            result.to_hdf5(_stack_path(target))
    else:
        result.to_hdf5(target)


class Say:
    """Progress lines on stderr, unless --quiet."""

    def __init__(self, *, quiet: bool, prog: str = "process") -> None:
        self.quiet, self.prog = quiet, prog

    def __call__(self, line: str) -> None:
        if not self.quiet:
            print(f"plenodust {self.prog}: {line}", file=sys.stderr, flush=True)


def load_kernels(say: Say) -> None:
    # Compiling the kernels takes about half a minute the first time after an install (and a
    # second to load them after): say so, rather than sit silent in the first exposure.
    from analysis.pipeline.process import warm_up
    from service.cli.warmup_cmd import still_working

    with still_working(say, "loading the analysis kernels (compiled on first use, about half a minute "
                            "after an install; `make setup` or `plenodust warm-up` does it ahead)"):
        warm_up()


def progress_bar(total: int, *, quiet: bool):
    if quiet or not sys.stderr.isatty():
        return None
    from tqdm import tqdm

    return tqdm(total=total, unit="exposure", file=sys.stderr,
                bar_format="{desc} {percentage:3.0f}%|{bar}| {n:.2f}/{total} [{elapsed}<{remaining}]")


class ExposureProgress:
    """The pipeline's progress callback, ``(fraction, stage)`` with the fraction weighted by the
    stages' cost: on a terminal the bar shows the stage running; off a terminal each new stage is
    one line."""

    def __init__(self, bar: Any, say: Say, index: int, total: int, name: str) -> None:
        self.bar, self.say, self.index, self.total, self.name = bar, say, index, total, name
        self.stage: str | None = None

    def __call__(self, fraction: float, stage: str | None = None) -> None:
        if self.bar is not None:
            if stage:
                self.bar.set_description_str(f"{self.name}: {stage}", refresh=False)
            self.bar.n = self.index + fraction
            self.bar.refresh()
        elif stage and stage != self.stage:
            self.say(f"{self.name} ({self.index + 1}/{self.total}): {stage} ({100 * fraction:.0f} %)")
        elif fraction >= 1.0 and self.stage is not None:
            self.say(f"{self.name} ({self.index + 1}/{self.total}): done")
        if stage:
            self.stage = stage
