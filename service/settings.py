"""Service settings: the only module that reads the environment (``PLENODUST_*``)."""

from __future__ import annotations

import re
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

# Run names become file names (one HDF5 file per run), so keep them to a safe alphabet.
RUN_NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"
_RUN_RE = re.compile(RUN_NAME_PATTERN)


class Settings(BaseSettings):
    """Everything the service can be told, by argument or by ``PLENODUST_<NAME>``.

    Attributes
    ----------
    data_dir : Path
        SQLite database, raw exposures, results and run files live here.
    camera : str
        ``usb``, ``wifi:HOST[:PORT]``, ``simulated:DIR`` or ``none``.
    executor : str
        ``local`` (a warm process pool on this machine) or ``dask://HOST:PORT``.
    workers : int
        Processes in the local pool, and jobs run at once.
    api_key : SecretStr or None
        When set, every mutating route needs ``Authorization: Bearer <key>``.
    min_free_bytes : int
        Free space kept on the data disk (default 1 GB); below it the service refuses uploads
        (507) and is not ready.
    raw_retention : int
        Keep the raw files of only the newest N exposures (0, the default: keep all).
    metric_calibration : Path or None
        A target calibration file (``plenodust calibrate-target``) added to the service's own at
        start; more can be uploaded (``POST /api/v1/calibrations/metric``).
    """

    model_config = SettingsConfigDict(env_prefix="PLENODUST_", extra="ignore")

    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    data_dir: Path = Path("plenodust-data")
    camera: str = "none"
    executor: str = "local"
    workers: int = Field(1, ge=1, le=64)
    api_key: SecretStr | None = None
    # An F01 .lfp is about 16.2 MB; leave room for a RAW+TXT pair in multipart framing.
    max_body_bytes: int = Field(40 * 1024 * 1024, ge=1024)
    # A camera's 62 white images (.RAW + .TXT) are about 1 GB; they are streamed to disk.
    max_calibration_bytes: int = Field(2 * 1024 ** 3, ge=1024)
    # Jobs queued or running; beyond this an upload gets 503 with Retry-After.
    queue_capacity: int = Field(64, ge=1)
    retry_after_s: int = Field(2, ge=1)
    lease_s: float = Field(30.0, gt=0)
    heartbeat_s: float = Field(5.0, gt=0)
    max_attempts: int = Field(3, ge=1)
    camera_poll_s: float = Field(2.0, gt=0)
    # On first contact with a camera, also queue the pictures already on it.
    camera_pull_existing: bool = False
    run: str = "default"
    # Pipeline parameters (fields of analysis.pipeline.process.PipelineParams), e.g.
    # PLENODUST_PIPELINE='{"n_slices": 60, "alpha_min": 0.99}'; empty for the defaults.
    pipeline: dict[str, Any] = Field(default_factory=dict)
    # Refocused slices kept per exposure for the dashboard's slice viewer.
    keep_slices: bool = True
    # Free space the service keeps on the data disk. Below it /readyz says not ready, uploads
    # get 507 and no job starts; jobs that failed for want of space run again once it is back.
    min_free_bytes: int = Field(1_000_000_000, ge=0)
    # Raw exposures kept: the newest N exposures keep their raw files, older ones (whose job
    # is done) lose them and keep their particle tables. 0 keeps every raw file (the default:
    # a lab's exposures are precious).
    raw_retention: int = Field(0, ge=0)
    metric_calibration: Path | None = None
    warm_up: bool = True
    log_level: Literal["debug", "info", "warning", "error"] = "info"

    @field_validator("camera")
    @classmethod
    def _camera_spec(cls, value: str) -> str:
        if value in ("none", "usb") or value.startswith(("wifi:", "simulated:")):
            return value
        raise ValueError(f"camera {value!r}: use usb, wifi:HOST[:PORT], simulated:DIR or none")

    @field_validator("executor")
    @classmethod
    def _executor_spec(cls, value: str) -> str:
        if value == "local" or value.startswith(("dask://", "tcp://")):
            return value
        raise ValueError(f"executor {value!r}: use local or dask://HOST:PORT")

    @field_validator("run")
    @classmethod
    def _run_name(cls, value: str) -> str:
        if not _RUN_RE.match(value):
            raise ValueError(f"run name {value!r}: use letters, digits, '.', '_' or '-' (at most 64)")
        return value

    @field_validator("api_key")
    @classmethod
    def _api_key_not_empty(cls, value: SecretStr | None) -> SecretStr | None:
        # An empty variable means "no key", never "the empty key".
        if value is not None and not value.get_secret_value():
            return None
        return value


def valid_run_name(name: str) -> bool:
    """Whether ``name`` can be used as a run name (it becomes a file name)."""
    return bool(_RUN_RE.match(name))


@lru_cache
def get_settings() -> Settings:
    """The settings from the environment, read once."""
    return Settings()
