"""``/api/v1/runs``: runs, their exposures, and all their particles with a ``frame`` column."""

from __future__ import annotations

import asyncio

from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, Body, Query, Request
from fastapi.responses import FileResponse, Response
from starlette.background import BackgroundTask

from analysis.tracking.trajectories import LEADING_COLUMNS
from service.deps import ApiKey, State
from service.models import (PROBLEM_RESPONSE, ParticleTable, RunExposurePage, RunList, RunName, RunSummaryTable,
                            TrajectoryTable)
from service.problems import Problem
from service.settings import valid_run_name
from service.tables import TableFormat, choose_format, table_response

router = APIRouter(prefix="/api/v1/runs", tags=["runs"])


@router.get("", summary="Runs, most recent first", response_model=RunList)
async def list_runs(state: State) -> dict:
    return {"current": state.current_run, "items": await asyncio.to_thread(state.store.runs)}


@router.get("/current", summary="The run new camera shots are filed under", response_model=RunName)
async def get_current_run(state: State) -> dict:
    return {"name": state.current_run}


@router.put("/current", dependencies=[ApiKey], summary="Start filing camera shots under another run",
            response_model=RunName, responses={422: PROBLEM_RESPONSE})
async def set_current_run(state: State, name: str = Body(..., embed=True)) -> dict:
    if not valid_run_name(name):
        raise Problem(422, "Invalid run name", f"{name!r}: use letters, digits, '.', '_' or '-' (at most 64)",
                      kind="invalid-run-name")
    await asyncio.to_thread(state.db.set_value, "current_run", name)
    state.bus.publish("run", {"current": name})
    return {"name": name}


def _known_run(state: State, run: str) -> None:
    if not valid_run_name(run) or not state.db.read("SELECT 1 FROM exposures WHERE run = ? LIMIT 1", (run,)):
        raise Problem(404, "Not found", f"no run {run!r}; GET /api/v1/runs lists them", kind="run-not-found")


@router.get("/{run}/exposures", summary="Exposures of a run with their job state, one page at a time",
            response_model=RunExposurePage, responses={404: PROBLEM_RESPONSE})
async def run_exposures(run: str, state: State,
                        limit: Annotated[int, Query(ge=1, le=500)] = 50,
                        offset: Annotated[int, Query(ge=0)] = 0,
                        order: Annotated[Literal["asc", "desc"], Query(
                            description="by frame: asc (first frame first) or desc (newest first)")] = "asc",
                        ) -> dict:
    _known_run(state, run)
    items, total = await asyncio.to_thread(state.store.run_exposures, run, limit=limit, offset=offset,
                                           newest_first=order == "desc")
    following = offset + len(items)
    return {"run": run, "items": items, "total": total, "limit": limit, "offset": offset,
            "next": f"/api/v1/runs/{run}/exposures?offset={following}&limit={limit}&order={order}"
            if following < total else None}


@router.get("/{run}/particles", summary="All particles of a run, with a frame column",
            response_model=ParticleTable,
            responses={200: {"content": {"text/csv": {"schema": {"type": "string"}},
                                         "application/x-hdf5": {"schema": {"type": "string", "format": "binary"}}}},
                       404: PROBLEM_RESPONSE, 406: PROBLEM_RESPONSE, 409: PROBLEM_RESPONSE})
async def run_particles(run: str, request: Request, state: State, format: TableFormat | None = None) -> Response:
    fmt = choose_format(request, format)
    _known_run(state, run)
    if fmt == "h5":
        # The run file itself (NeXus, with the parameters of every frame), copied under the run's
        # lock: appends change it in place, so streaming it directly could send half of one.
        copy = await asyncio.to_thread(state.store.run_file_snapshot, run)
        if copy is None:
            raise Problem(409, "No result yet", f"run {run!r} has no processed exposure yet", kind="no-result")
        return FileResponse(copy, media_type="application/x-hdf5", filename=f"{run}.nxs",
                            background=BackgroundTask(copy.unlink, missing_ok=True))
    columns = await asyncio.to_thread(state.store.read_run_columns, run)
    if columns is None:
        raise Problem(409, "No result yet", f"run {run!r} has no processed exposure yet", kind="no-result")
    return table_response(columns, fmt, meta={"run": run}, filename=run)


_TABLE_RESPONSES = {200: {"content": {"text/csv": {"schema": {"type": "string"}},
                                      "application/x-hdf5": {"schema": {"type": "string", "format": "binary"}}}},
                    404: PROBLEM_RESPONSE, 406: PROBLEM_RESPONSE, 409: PROBLEM_RESPONSE}


@router.get("/{run}/trajectories", summary="A run's particles linked into trajectories (trackpy's columns)",
            response_model=TrajectoryTable, responses=_TABLE_RESPONSES)
async def run_trajectories(run: str, request: Request, state: State, format: TableFormat | None = None,
                           frame_min: Annotated[int, Query(ge=0, description="first frame")] = 0,
                           frame_max: Annotated[int | None, Query(ge=0, description="last frame")] = None,
                           particle: Annotated[int | None, Query(ge=0, description="one trajectory")] = None,
                           ) -> Response:
    """Rows of linked frames only (``particle`` >= 0), by frame: each new shot is linked as its result
    arrives. ``frame_min``/``frame_max`` read only those frames' rows (a trail of the last few)."""
    fmt = choose_format(request, format)
    _known_run(state, run)
    columns = await asyncio.to_thread(state.store.read_run_frames, run, frame_min, frame_max)
    if columns is None or "frame" not in columns:
        raise Problem(409, "No result yet", f"run {run!r} has no processed exposure yet", kind="no-result")
    ids = np.asarray(columns.get("particle", np.full(len(columns["frame"]), -1)))
    keep = ids >= 0
    if particle is not None:
        keep &= ids == particle
    lead = [c for c in LEADING_COLUMNS if c in columns]
    table = {name: np.asarray(columns[name])[keep] for name in lead + [c for c in columns if c not in lead]}
    frames = sorted({int(f) for f in table["frame"].tolist()})
    return table_response(table, fmt, meta={"run": run, "frames": frames}, filename=f"{run}-trajectories")


@router.get("/{run}/summary", summary="A run's structure per shot: count, temperature, shells",
            response_model=RunSummaryTable, responses=_TABLE_RESPONSES)
async def run_summary(run: str, request: Request, state: State, format: TableFormat | None = None) -> Response:
    """One row per linked shot (analysis.tracking.summary): the shot before the newest has central
    velocities, the newest one-sided ones until the next shot comes."""
    fmt = choose_format(request, format)
    _known_run(state, run)
    columns = await asyncio.to_thread(state.tracker.summary, run) if state.tracker is not None else None
    if columns is None:
        raise Problem(409, "No result yet", f"run {run!r} has no linked shot yet", kind="no-result")
    return table_response(columns, fmt, meta={"run": run, "particle_mass_kg": state.tracker.mass_kg},
                          filename=f"{run}-summary")
