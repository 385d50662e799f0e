"""Durable jobs: the SQLite job store and the runner that survives restarts."""

from api.jobs.runner import DEFAULT_STEPS, JobRunner, WorkSpec, WorkUnavailableError, load_work
from api.jobs.store import TERMINAL, JobNotFoundError, JobRecord, JobStateError, JobStore

__all__ = [
    "DEFAULT_STEPS",
    "JobRunner",
    "WorkSpec",
    "WorkUnavailableError",
    "load_work",
    "TERMINAL",
    "JobNotFoundError",
    "JobRecord",
    "JobStateError",
    "JobStore",
]
