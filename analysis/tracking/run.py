"""From a run's exposures (a folder, or a list) to one linked table, in one call.

Example (from a notebook)::

    from analysis.tracking.run import track
    from analysis.tracking.summary import summarize

    linked = track("shots/", "shots/calibration")        # pandas: frame, t, particle, X, Y, Z, vX, ...
    structure = summarize(linked).to_dataframe()          # per shot: count, temperature, shells

The exposures are processed in any order and linked in the order their metadata's clock
(``devices.clock.zuluTime``) says they were taken: ``frame`` counts shots from 0 in that order,
``t`` is seconds since the first.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterable, Sequence

import numpy as np

from analysis.cache import Cache
from analysis.errors import ParameterError
from analysis.pipeline.batch import CalibrationFolder, exposure_files

from .linking import LinkParams
from .trajectories import Engine, link

if TYPE_CHECKING:
    import pandas as pd

    from analysis.calibration.calibrate import Calibration
    from analysis.formats.exposure import Exposure
    from analysis.pipeline.params import PipelineParams
    from analysis.pipeline.result import Result

def link_results(results: Sequence[Result], params: LinkParams | None = None, *, engine: Engine = "plenodust",
                 interval_s: float | None = None) -> pd.DataFrame:
    """Link processed exposures (:class:`analysis.pipeline.result.Result`) in shot-time order.

    Parameters
    ----------
    results : sequence of Result
        In any order; each one's ``shot_time`` (from its metadata's clock) orders them.
    params : LinkParams, optional
    engine : {"plenodust", "trackpy"}
    interval_s : float, optional
        Time between shots, used only where an exposure's metadata carry no clock (they are then
        taken in the order given).

    Returns
    -------
    pandas.DataFrame
        See :func:`analysis.tracking.trajectories.link`; also ``exposure`` (the exposure's name).

    Raises
    ------
    ParameterError
        Exposures without a clock and no ``interval_s``.
    """
    import pandas as pd

    times = [r.shot_time for r in results]
    if any(t is None for t in times):
        if interval_s is None:
            raise ParameterError("some exposures' metadata carry no clock (devices.clock.zuluTime); give the "
                                 "time between shots (interval_s, --interval) to link them in the order given")
        times = [k * float(interval_s) for k in range(len(results))]
    order = sorted(range(len(results)), key=lambda k: (times[k], k))
    start = times[order[0]] if order else 0.0
    frames = []
    for frame, k in enumerate(order):
        df = results[k].to_dataframe(frame=frame, t=float(times[k] - start))
        df["exposure"] = results[k].exposure_name or ""
        frames.append(df)
    if not frames:
        return pd.DataFrame(columns=["frame", "t", "particle", "index", "X", "Y", "Z", "vX", "vY", "vZ"])
    return link(pd.concat(frames, ignore_index=True), params, engine=engine)


def track(exposures: str | Path | Iterable[str | Path | Exposure],
          calibration: str | Path | Calibration | Callable[[Exposure], Calibration],
          params: PipelineParams | None = None, *, link_params: LinkParams | None = None,
          engine: Engine = "plenodust", cache: Cache | None = None, cache_dir: str | Path | None = None,
          interval_s: float | None = None,
          progress: Callable[[int, float, str], None] | None = None,
          on_result: Callable[[Result], None] | None = None) -> pd.DataFrame:
    """Process a run's exposures and link them into trajectories: one call, one DataFrame.

    Parameters
    ----------
    exposures : folder, file, or iterable of paths or Exposure objects
        ``.lfp`` files, ``.RAW`` files with their ``.TXT`` beside them, or folders of them.
    calibration : folder, Calibration or callable
        The camera's white images (a folder: :class:`CalibrationFolder`), a fitted calibration, or
        a callable giving the calibration of an exposure.
    params : PipelineParams, optional
        The pipeline's settings (as for :func:`analysis.pipeline.process.process`).
    link_params : LinkParams, optional
    engine : {"plenodust", "trackpy"}
    cache : Cache, optional
        Look-up tables shared by the batch (default: a new one).
    cache_dir : path, optional
        Keep fitted calibrations on disk there (with a calibration folder).
    interval_s : float, optional
        Time between shots for exposures without a clock.
    progress : callable ``(index, fraction, stage)``, optional
    on_result : callable, optional
        Called with each exposure's :class:`Result` as it is done (e.g. to save it).

    Returns
    -------
    pandas.DataFrame
        The linked table (:func:`link_results`).
    """
    from analysis.pipeline.process import process_many

    if isinstance(exposures, (str, Path)):
        exposures = [exposures]
    items = [e if not isinstance(e, (str, Path)) else Path(e) for e in exposures]
    paths = exposure_files([i for i in items if isinstance(i, Path)])
    batch = [i for i in items if not isinstance(i, Path)] + paths
    if not batch:
        raise ParameterError("no .lfp or .RAW exposure to track; give files or folders of them")
    if isinstance(calibration, (str, Path)):
        calibration = CalibrationFolder(calibration, cache_dir)
    kept = []
    for result in process_many(batch, calibration, params, cache=cache or Cache(), progress=progress):
        result.stack = result.subaperture = None  # memory stays that of one exposure
        result.curves = None
        if on_result is not None:
            on_result(result)
        kept.append(result)
    return link_results(kept, link_params, engine=engine, interval_s=interval_s)


def linked_table_columns(df: pd.DataFrame) -> dict[str, np.ndarray]:
    """A linked DataFrame as plain columns for the table writers (text columns as ``str``)."""
    out = {}
    for name in df.columns:
        values = df[name].to_numpy()
        out[name] = values.astype(str) if values.dtype.kind == "O" else values
    return out
