"""A simulated exposure with its calibration and truth, as the pipeline tests use it."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from analysis.cache import Cache
from analysis.calibration.calibrate import Calibration
from analysis.calibration.cache import load_calibration
from analysis.formats.exposure import Exposure, read_exposure
from analysis.formats.particle_table import read_csv
from analysis.simulation.scenario_files import write_scenario


@dataclass(frozen=True)
class SimulatedCase:
    folder: Path
    exposure: Exposure
    calibration: Calibration
    truth: dict[str, np.ndarray]
    nn_mm: float          # mean 3D nearest-neighbour distance of the truth
    cache: Cache          # look-up tables (in memory and, with the calibrations, in folder/cache)


def simulated_case(folder: Path, scenario: str, seed: int, *, size: int) -> SimulatedCase:
    """Simulate ``scenario`` into ``folder`` (a sensor crop of ``size`` px) and calibrate from its whites."""
    write_scenario(folder, scenario, seed, size=size)
    exposure = read_exposure(folder / "IMG_0001.lfp")
    cache = Cache(directory=folder / "cache")
    calibration = load_calibration(folder / "calibration", exposure.metadata, serial=exposure.serial,
                                   cache_dir=cache.directory)
    return SimulatedCase(folder, exposure, calibration, read_csv(folder / "IMG_0001.truth.csv"),
                         mean_nn_mm(folder), cache)


def mean_nn_mm(folder: Path) -> float:
    """The first exposure's mean nearest-neighbour distance, from ``scenario.json``."""
    return json.loads((folder / "scenario.json").read_text())["exposures"][0]["mean_nn_distance_mm"]
