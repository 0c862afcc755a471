"""``/api/v1/jobs``: the state of queued, running and finished jobs."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query

from service.deps import State
from service.models import PROBLEM_RESPONSE, Job, JobPage
from service.problems import Problem

router = APIRouter(prefix="/api/v1/jobs", tags=["jobs"])


@router.get("/{job_id}", summary="One job: state, progress, stage, error", response_model=Job,
            responses={404: PROBLEM_RESPONSE})
async def get_job(job_id: str, state: State) -> dict:
    job = state.queue.get(job_id)
    if job is None:
        raise Problem(404, "Not found", f"no job {job_id!r}", kind="job-not-found")
    return job.public()


@router.get("", summary="Jobs, newest first, one page at a time", response_model=JobPage)
async def list_jobs(state: State,
                    job_state: Annotated[Literal["queued", "running", "done", "failed"] | None,
                                         Query(alias="state")] = None,
                    limit: Annotated[int, Query(ge=1, le=500)] = 50,
                    offset: Annotated[int, Query(ge=0)] = 0) -> dict:
    jobs, total = state.queue.list(state=job_state, limit=limit, offset=offset)
    following = offset + len(jobs)
    return {"items": [j.public() for j in jobs], "total": total, "limit": limit, "offset": offset,
            "next": (f"/api/v1/jobs?offset={following}&limit={limit}"
                     + (f"&state={job_state}" if job_state else "")) if following < total else None}
