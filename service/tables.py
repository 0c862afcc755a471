"""Particle tables as JSON (columnar), CSV or HDF5, chosen by ``?format=`` or ``Accept``."""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from fastapi import Request
from fastapi.responses import JSONResponse, Response

from analysis.formats.particle_table import csv_text, table_h5_bytes
from service.problems import Problem

TableFormat = Literal["json", "csv", "h5"]
MEDIA_TYPES = {"json": "application/json", "csv": "text/csv; charset=utf-8", "h5": "application/x-hdf5"}
_ACCEPT = {"application/json": "json", "text/csv": "csv", "application/x-hdf5": "h5",
           "application/x-hdf": "h5", "application/octet-stream": "h5", "*/*": "json",
           "application/*": "json", "text/*": "csv"}


def choose_format(request: Request, explicit: str | None) -> str:
    """``explicit`` if given, else the first ``Accept`` type we serve, else JSON.

    Raises
    ------
    Problem
        406 when ``Accept`` names only types we cannot produce.
    """
    if explicit:
        return explicit
    accept = request.headers.get("accept", "")
    if not accept.strip():
        return "json"
    ranked = []
    for i, part in enumerate(accept.split(",")):
        media, *params = (p.strip() for p in part.split(";"))
        q = 1.0
        for p in params:
            if p.startswith("q="):
                try:
                    q = float(p[2:])
                except ValueError:
                    q = 0.0
        ranked.append((-q, i, media.lower()))
    for neg_q, _, media in sorted(ranked):
        if neg_q < 0 and media in _ACCEPT:
            return _ACCEPT[media]
    raise Problem(406, "Not acceptable", f"cannot answer with {accept!r}; ask for application/json, "
                  "text/csv or application/x-hdf5, or use ?format=json|csv|h5", kind="not-acceptable")


def _json_value(v: object) -> object:
    if isinstance(v, float) and not math.isfinite(v):
        return None  # JSON has no NaN
    return v


def columns_json(columns: dict[str, np.ndarray]) -> dict[str, list]:
    return {name: [_json_value(v) for v in np.asarray(col).tolist()] for name, col in columns.items()}


def table_response(columns: dict[str, np.ndarray], fmt: str, *, meta: dict, filename: str) -> Response:
    """The table in ``fmt``; ``meta`` goes into the JSON body beside the columns."""
    if fmt == "csv":
        return Response(csv_text(columns), media_type=MEDIA_TYPES["csv"],
                        headers={"Content-Disposition": f'inline; filename="{filename}.csv"'})
    if fmt == "h5":
        return Response(table_h5_bytes(columns, title=filename), media_type=MEDIA_TYPES["h5"],
                        headers={"Content-Disposition": f'attachment; filename="{filename}.h5"'})
    count = len(next(iter(columns.values()))) if columns else 0
    return JSONResponse({**meta, "count": count, "columns": columns_json(columns)})
