"""What the API answers, as pydantic models: they document ``/openapi.json`` and type the client.

Split by resource like the routes. Field names are the JSON keys; times are Unix seconds.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field

JobState = Literal["queued", "running", "done", "failed"]


class ProblemBody(BaseModel):
    """An error (RFC 9457 ``application/problem+json``); some problems carry more fields."""

    type: str = Field(description="URI naming the kind of problem")
    title: str
    status: int
    detail: str = Field(description="what happened and what to do about it")
    instance: str | None = Field(None, description="the path that was asked for")


class Job(BaseModel):
    """One job: the processing of one exposure."""

    id: str
    exposure_id: str
    state: JobState
    progress: float = Field(description="0 to 1")
    stage: str | None = Field(None, description="the pipeline stage running now, when known")
    error: str | None = Field(description="why the job failed (or why its last attempt did)")
    waits_for: Literal["calibration", "space"] | None = Field(
        None, description="a failed job that runs again by itself once this arrives: its camera's white "
                          "images, or free space on the data disk")
    attempts: int
    created_at: float
    started_at: float | None
    finished_at: float | None


class Page(BaseModel):
    """Paging fields shared by listings: ``next`` is the URL of the following page, if any."""

    total: int
    limit: int
    offset: int
    next: str | None


class JobPage(Page):
    items: list[Job]


class UploadAccepted(BaseModel):
    """An accepted exposure and its job (``Location`` names the job)."""

    exposure_id: str = Field(description="SHA-1 of the raw sensor bytes")
    job_id: str
    run: str
    frame: int = Field(description="order of the exposure within its run, from 0")
    created: bool = Field(description="false when these bytes were uploaded before")
    retried: bool = Field(False, description="a failed job of this exposure was queued again")


class ExposureInfo(BaseModel):
    id: str
    run: str
    frame: int
    kind: Literal["lfp", "raw"]
    source: Literal["upload", "camera"]
    serial: str | None
    created_at: float
    job: Job | None
    raw_kept: bool = Field(description="false once the raw files were removed under PLENODUST_RAW_RETENTION")
    slices: int = Field(description="refocused slices kept for viewing (GET .../slices/{k})")
    slice_alpha: list[float] = Field(description="the alpha of each kept slice")
    slice_binning: int = Field(description="output-image pixels per slice pixel along each axis")
    warnings: list[str]
    timings: dict[str, float] = Field(description="seconds per pipeline stage")
    coordinates: dict[str, Any] | None = Field(
        None, description="the physical calibration X, Y, Z came from: kind 'target' (with the calibration's "
                          "sha1, model and volume) or 'thin-lens' (the metadata's fallback)")


class ParticleTable(BaseModel):
    """A particle table by column (``GET ...?format=json``); CSV and HDF5 carry the same columns."""

    exposure_id: str | None = None
    run: str
    frame: int | None = None
    count: int
    columns: dict[str, list[float | int | None]] = Field(
        description="particle, x, y (output-image pixels), alpha (fitted), X, Y, Z (mm), brightness, quality "
                    "columns; a run's table has a frame column; NaN is null")


class TrajectoryTable(BaseModel):
    """A run's linked particles by column (``GET /runs/{run}/trajectories?format=json``)."""

    run: str
    count: int
    frames: list[int] = Field(description="the frames the rows come from")
    columns: dict[str, list[float | int | None]] = Field(
        description="frame, t (s since the run's first shot), particle (trajectory id, as in trackpy), index "
                    "(row in its exposure's table), x, y, alpha, X, Y, Z (mm), vX, vY, vZ (mm/s; null where a "
                    "trajectory has one shot), brightness and quality columns; NaN is null")


class RunSummaryTable(BaseModel):
    """A run's structure per shot (``GET /runs/{run}/summary?format=json``)."""

    run: str
    count: int
    particle_mass_kg: float
    columns: dict[str, list[float | int | None]] = Field(
        description="frame, t, count, with_velocity, vX..vZ (drift, mm/s), omegaX..omegaZ (rad/s), v_rms_* and "
                    "T_*_eV per axis with their *_err_*, T_eV, T_xy_eV, shells and per shell i shell{i}_r_mm, "
                    "shell{i}_r_err_mm, shell{i}_n, shell{i}_n_err, noise_X_mm..noise_Z_mm (position noise)")


class Curves(BaseModel):
    """Brightness curves ``B_i(alpha)``: mean product-image intensity per pixel of each particle's
    blob at each refocus parameter ``alpha``."""

    alpha: list[float]
    brightness: list[list[float | None]] = Field(description="one row per particle, one value per alpha")
    particles: list[int]


class RunSummary(BaseModel):
    run: str
    exposures: int
    done: int
    failed: int
    pending: int
    last: float | None


class RunList(BaseModel):
    current: str
    items: list[RunSummary]


class RunName(BaseModel):
    name: str


class RunExposure(BaseModel):
    id: str
    frame: int
    source: str
    created_at: float
    job_id: str | None
    state: JobState | None
    progress: float | None
    error: str | None
    particles: int | None


class RunExposurePage(Page):
    run: str
    items: list[RunExposure]


class CameraStatus(BaseModel):
    configured: bool
    state: str = Field(description="none, connecting, connected, disconnected")
    serial: str | None
    firmware: str | None = None
    battery: float | None = Field(description="percent")
    last_error: str | None = None
    last_poll: float | None = None
    calibrated: bool = False
    can_take_shots: bool = Field(False, description="whether POST /api/v1/camera/shots works with this camera")


class QueuedShot(BaseModel):
    picture: str
    exposure_id: str
    job_id: str
    run: str
    frame: int
    created: bool


class PullResult(BaseModel):
    queued: list[QueuedShot]
    camera: CameraStatus


class CalibrationInfo(BaseModel):
    serial: str
    path: str
    images: int
    source: Literal["camera", "upload"]
    created_at: float


class CalibrationList(BaseModel):
    items: list[CalibrationInfo]


class CalibrationUploaded(BaseModel):
    serial: str
    white_images: int
    jobs_retried: list[str] = Field(description="jobs that had failed for want of this camera's white images, "
                                                "queued again")


class MetricCalibrationInfo(BaseModel):
    """A stored target calibration (``plenodust calibrate-target``)."""

    serial: str | None
    zoom_step: int | None
    focus_step: int | None
    model: Literal["physical", "polynomial"] = Field(description="the mapping used: the one that predicted "
                                                                 "held-back target positions best")
    mapping: str
    sha1: str | None = Field(description="SHA-1 of the file; results record it")
    created_utc: str
    file: str
    held_out_rms_um: dict[str, float] | None = Field(
        None, description="RMS error on held-back stage positions per axis (X, Y, Z, 3d), micrometres")
    volume: dict[str, Any] = Field(description="what the target covered (target frame, mm; alpha)")


class MetricCalibrationList(BaseModel):
    items: list[MetricCalibrationInfo]


class Health(BaseModel):
    status: Literal["ok"]


class DiskSpace(BaseModel):
    data_dir: str
    free_bytes: int
    margin_bytes: int = Field(description="PLENODUST_MIN_FREE_BYTES: below this the service is not ready")
    ok: bool


class Readiness(BaseModel):
    ready: bool
    database: str
    workers: Literal["warm", "warming"]
    executor: str
    camera: str
    camera_ok: bool
    disk: DiskSpace
    uptime_s: float
    executor_error: str | None = None


PROBLEM_RESPONSE = {"model": ProblemBody, "content": {"application/problem+json": {}}}
