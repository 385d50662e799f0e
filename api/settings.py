"""Settings of the REST API, in one place.

Every field can be set from the environment with the ``STAGE_`` prefix
(``STAGE_DATA=/srv/stage``, ``STAGE_DASK=tcp://head:8786``...), except the token,
which is read from ``STAGE_API_TOKEN``. ``stage serve`` fills them from its
command line.

Layout of the data root::

    DATA/
      rig.toml              the rig (unless ``rig`` points elsewhere)
      takes/<take>.h5       takes (HDF5, see docs/take-format.md)
      calibrations/<id>.json
      jobs/<job>/           results of one job (spine.json, meshes/, report.json)
      jobs.sqlite           the durable job store (SQLite, WAL)
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

__all__ = ["Settings"]


class Settings(BaseSettings):
    """Configuration of the API server.

    Parameters
    ----------
    data : Path
        Data root. Nothing outside it is ever read or written by a request.
    api_token : SecretStr or None
        Bearer token required by every endpoint that changes anything
        (env ``STAGE_API_TOKEN``). When ``None`` the server refuses writes
        (403) unless ``allow_anonymous_writes`` is set (tests, local demos).
    read_protected : bool
        Require the token for reading too.
    max_upload_bytes : int
        Largest accepted take upload.
    dask : str or None
        Address of an existing Dask scheduler (``tcp://host:8786``); ``None`` runs
        jobs on the embedded local process pool.
    workers : int or None
        Processes of the local pool (default: CPU count).
    rig : Path or None
        Rig file; default ``DATA/rig.toml``.
    work : str
        ``module:function`` that processes one take with the signature of
        :func:`pipeline.process.process_take`. A hook for tests and plug-ins.
    heartbeat_s, stale_after_s : float
        A running job refreshes its heartbeat every ``heartbeat_s``; a job still
        marked running whose heartbeat is older than ``stale_after_s`` was
        interrupted (server killed) and is queued again, to resume.
    max_attempts : int
        A job interrupted this many times is marked failed.
    """

    model_config = SettingsConfigDict(env_prefix="STAGE_", extra="ignore", validate_default=True, populate_by_name=True)

    data: Path = Path("stage-data")
    api_token: SecretStr | None = Field(default=None, validation_alias="STAGE_API_TOKEN")
    allow_anonymous_writes: bool = False
    read_protected: bool = False
    max_upload_bytes: Annotated[int, Field(gt=0)] = 8 * 1024**3
    dask: str | None = None
    workers: Annotated[int, Field(ge=1, le=1024)] | None = None
    rig: Path | None = None
    work: str = "pipeline.process:process_take"
    heartbeat_s: Annotated[float, Field(gt=0)] = 2.0
    stale_after_s: Annotated[float, Field(gt=0)] = 10.0
    max_attempts: Annotated[int, Field(ge=1)] = 5
    max_concurrent_jobs: Annotated[int, Field(ge=1, le=64)] = 1
    poll_s: Annotated[float, Field(gt=0)] = 0.25

    @field_validator("data")
    @classmethod
    def _absolute(cls, v: Path) -> Path:
        return Path(v).expanduser().resolve()

    @field_validator("dask")
    @classmethod
    def _dask_address(cls, v: str | None) -> str | None:
        if v in (None, ""):
            return None
        if "://" not in v and v != "local":
            raise ValueError("dask must be a scheduler address like tcp://host:8786 (or 'local' for a LocalCluster)")
        return v

    @property
    def takes_dir(self) -> Path:
        return self.data / "takes"

    @property
    def jobs_dir(self) -> Path:
        return self.data / "jobs"

    @property
    def calibrations_dir(self) -> Path:
        return self.data / "calibrations"

    @property
    def db_path(self) -> Path:
        return self.data / "jobs.sqlite"

    @property
    def rig_path(self) -> Path:
        return self.rig if self.rig is not None else self.data / "rig.toml"

    def ensure_dirs(self) -> None:
        """Create the data root's folders."""
        for d in (self.data, self.takes_dir, self.jobs_dir, self.calibrations_dir):
            d.mkdir(parents=True, exist_ok=True)
