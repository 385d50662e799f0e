"""Durable job records in SQLite (WAL mode) under the data root.

One row per job: kind, take, steps, parameters, state, progress per step,
heartbeat, attempts, error, cancel flag, and the warnings the job said (each once, in the order said, kept as
they are said: a failed or cancelled job keeps those said before it stopped). Progress events (one per increase of the
number of frames done, summed over steps) are kept in a second table so that a
Server-Sent-Events client that reconnects with ``Last-Event-ID: N`` receives the
events it missed.

States: ``queued -> running -> done | failed | cancelled``; a running job whose
heartbeat goes stale (its server was killed) goes back to ``queued`` and its
``attempts`` counter says how many times it was started.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
import uuid
from pathlib import Path
from typing import Any, Iterable, Literal

from pydantic import BaseModel, ConfigDict, Field
from typing_extensions import NotRequired, TypedDict

__all__ = ["JobRecord", "StepProgress", "JobStore", "JobNotFoundError", "JobStateError", "STATES", "TERMINAL"]

STATES = ("queued", "running", "done", "failed", "cancelled")
TERMINAL = frozenset({"done", "failed", "cancelled"})

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    kind TEXT NOT NULL,
    take TEXT NOT NULL,
    steps TEXT NOT NULL,
    params TEXT NOT NULL,
    state TEXT NOT NULL,
    created REAL NOT NULL,
    started REAL,
    finished REAL,
    heartbeat REAL,
    attempts INTEGER NOT NULL DEFAULT 0,
    error TEXT,
    cancel INTEGER NOT NULL DEFAULT 0,
    owner TEXT,
    progress TEXT NOT NULL DEFAULT '{}',
    done INTEGER NOT NULL DEFAULT 0,
    total INTEGER NOT NULL DEFAULT 0,
    result TEXT,
    warnings TEXT
);
CREATE INDEX IF NOT EXISTS jobs_state ON jobs(state, created);
CREATE TABLE IF NOT EXISTS events (
    job TEXT NOT NULL,
    seq INTEGER NOT NULL,
    time REAL NOT NULL,
    data TEXT NOT NULL,
    PRIMARY KEY (job, seq)
);
"""


class JobNotFoundError(KeyError):
    """No job with this id (maps to 404)."""

    def __str__(self) -> str:  # KeyError quotes its message otherwise
        return str(self.args[0]) if self.args else "job not found"


class JobStateError(ValueError):
    """The job is in a state that does not allow the operation (maps to 409)."""


class StepProgress(TypedDict):
    """Frames of one progress entry done, how many there are, and the job's step it belongs to (the step that
    announced it: :meth:`pipeline.run.Run.step_of`; the entry's own name where the work says none, and in records
    kept before steps were)."""

    done: int
    total: int
    step: NotRequired[str]


class JobRecord(BaseModel):
    """One job as stored (the API's job status is this plus its links: ``api.routers.jobs.JobStatus``)."""

    model_config = ConfigDict(frozen=True)

    id: str
    kind: str
    take: str
    steps: tuple[str, ...]
    params: dict[str, Any]
    state: Literal["queued", "running", "done", "failed", "cancelled"]
    created: float
    started: float | None
    finished: float | None
    heartbeat: float | None
    attempts: int
    error: str | None
    cancel_requested: bool
    progress: dict[str, StepProgress] = Field(default_factory=dict)
    done: int = Field(0, description="frames done, summed over steps (the SSE event id)")
    total: int = 0
    result: dict[str, Any] | None = None
    warnings: list[str] = Field(default_factory=list, description=(
        "what the job warned of, each once, in the order said, in every state: kept as they are said, so a failed "
        "or cancelled job keeps those said before it stopped (a done job's are its report's too)"))

    @classmethod
    def _from_row(cls, row: sqlite3.Row) -> "JobRecord":
        return cls(
            id=row["id"],
            kind=row["kind"],
            take=row["take"],
            steps=tuple(json.loads(row["steps"])),
            params=json.loads(row["params"]),
            state=row["state"],
            created=row["created"],
            started=row["started"],
            finished=row["finished"],
            heartbeat=row["heartbeat"],
            attempts=row["attempts"],
            error=row["error"],
            cancel_requested=bool(row["cancel"]),
            progress=json.loads(row["progress"]),
            done=row["done"],
            total=row["total"],
            result=json.loads(row["result"]) if row["result"] else None,
            warnings=_warnings_of(row),
        )

    def to_dict(self) -> dict[str, Any]:
        return {**self.model_dump(), "steps": list(self.steps)}


def result_warnings(result: Any) -> list[str]:
    """The warnings a work function's result (as JSON) holds: ``result.report.warnings`` (a processing job's
    report), else ``result.warnings``; none for any other result."""
    if not isinstance(result, dict):
        return []
    report = result.get("report")
    said = report.get("warnings") if isinstance(report, dict) else None
    said = result.get("warnings") if said is None else said
    return [w for w in said if isinstance(w, str)] if isinstance(said, list) else []


def _warnings_of(row: sqlite3.Row) -> list[str]:
    """A row's warnings; a row written before the store kept them (``NULL``) has its result's
    (:func:`result_warnings`): a done job's, none for a failed or cancelled one."""
    if row["warnings"] is not None:
        return json.loads(row["warnings"])
    return result_warnings(json.loads(row["result"]) if row["result"] else None)


class JobStore:
    """Job records in one SQLite file (WAL), safe to use from many threads and processes.

    Parameters
    ----------
    path : Path
        The database file (created with its folder).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._local = threading.local()
        con = self._con()
        con.execute("PRAGMA journal_mode=WAL")
        con.executescript(_SCHEMA)
        self._add_column(con, "warnings", "TEXT")  # a store written before the job records kept their warnings

    # -- connections -------------------------------------------------------------------------
    def _con(self) -> sqlite3.Connection:
        con = getattr(self._local, "con", None)
        if con is None:
            con = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
            con.row_factory = sqlite3.Row
            con.execute("PRAGMA synchronous=NORMAL")
            con.execute("PRAGMA busy_timeout=30000")
            self._local.con = con
        return con

    def close(self) -> None:
        """Close this thread's connection."""
        con = getattr(self._local, "con", None)
        if con is not None:
            con.close()
            self._local.con = None

    @staticmethod
    def _add_column(con: sqlite3.Connection, name: str, kind: str) -> None:
        """Add a column the jobs table of an older store lacks (its rows read ``NULL`` there)."""
        if name in {r["name"] for r in con.execute("PRAGMA table_info(jobs)")}:
            return
        try:
            con.execute(f"ALTER TABLE jobs ADD COLUMN {name} {kind}")
        except sqlite3.OperationalError as exc:  # another process opening the store added it meanwhile
            if "duplicate column" not in str(exc):
                raise

    def _tx(self, fn, *, immediate: bool = True):
        con = self._con()
        con.execute("BEGIN IMMEDIATE" if immediate else "BEGIN")
        try:
            out = fn(con)
        except BaseException:
            con.execute("ROLLBACK")
            raise
        con.execute("COMMIT")
        return out

    # -- create / read -----------------------------------------------------------------------
    def create(self, *, kind: str, take: str, steps: Iterable[str], params: dict, job_id: str | None = None) -> JobRecord:
        """Add a queued job and return it."""
        jid = job_id or uuid.uuid4().hex
        now = time.time()
        self._con().execute(
            "INSERT INTO jobs (id, kind, take, steps, params, state, created, warnings) "
            "VALUES (?, ?, ?, ?, ?, 'queued', ?, '[]')",
            (jid, kind, take, json.dumps(list(steps)), json.dumps(params, sort_keys=True), now),
        )
        return self.get(jid)

    def get(self, job_id: str) -> JobRecord:
        row = self._con().execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            raise JobNotFoundError(f"no job {job_id!r}")
        return JobRecord._from_row(row)

    def list(self, *, state: str | None = None, kind: str | None = None, take: str | None = None,
             limit: int = 100, offset: int = 0) -> list[JobRecord]:
        """Jobs, newest first, optionally filtered."""
        where, args = [], []
        for col, val in (("state", state), ("kind", kind), ("take", take)):
            if val is not None:
                where.append(f"{col} = ?")
                args.append(val)
        sql = "SELECT * FROM jobs" + (" WHERE " + " AND ".join(where) if where else "")
        sql += " ORDER BY created DESC, id LIMIT ? OFFSET ?"
        rows = self._con().execute(sql, (*args, int(limit), int(offset))).fetchall()
        return [JobRecord._from_row(r) for r in rows]

    def events(self, job_id: str, *, after: int = -1) -> list[tuple[int, dict]]:
        """Progress events with ``seq > after``, in order: ``[(seq, data), ...]``."""
        rows = self._con().execute(
            "SELECT seq, data FROM events WHERE job = ? AND seq > ? ORDER BY seq", (job_id, int(after))
        ).fetchall()
        return [(r["seq"], json.loads(r["data"])) for r in rows]

    # -- runner side -------------------------------------------------------------------------
    def claim(self, owner: str) -> JobRecord | None:
        """Atomically move the oldest queued job to running (attempts + 1) and return it."""

        def fn(con: sqlite3.Connection):
            row = con.execute("SELECT id FROM jobs WHERE state = 'queued' ORDER BY created, id LIMIT 1").fetchone()
            if row is None:
                return None
            now = time.time()
            con.execute(
                "UPDATE jobs SET state = 'running', attempts = attempts + 1, heartbeat = ?, owner = ?, "
                "started = COALESCE(started, ?), error = NULL WHERE id = ?",
                (now, owner, now, row["id"]),
            )
            return row["id"]

        jid = self._tx(fn)
        return None if jid is None else self.get(jid)

    def heartbeat(self, job_ids: Iterable[str], owner: str) -> set[str]:
        """Refresh the heartbeat of running jobs; return the ids whose cancellation was requested."""
        ids = list(job_ids)
        if not ids:
            return set()
        now = time.time()
        q = ",".join("?" * len(ids))

        def fn(con: sqlite3.Connection):
            con.execute(
                f"UPDATE jobs SET heartbeat = ? WHERE state = 'running' AND owner = ? AND id IN ({q})", (now, owner, *ids)
            )
            rows = con.execute(f"SELECT id FROM jobs WHERE cancel = 1 AND id IN ({q})", ids).fetchall()
            return {r["id"] for r in rows}

        return self._tx(fn)

    def requeue_stale(self, *, stale_after_s: float, max_attempts: int) -> list[str]:
        """Queue again running jobs whose heartbeat is older than ``stale_after_s``; fail those out of attempts.

        Returns the ids that were queued again.
        """
        limit = time.time() - stale_after_s

        def fn(con: sqlite3.Connection):
            rows = con.execute(
                "SELECT id, attempts, cancel FROM jobs WHERE state = 'running' AND (heartbeat IS NULL OR heartbeat < ?)",
                (limit,),
            ).fetchall()
            again = []
            now = time.time()
            for r in rows:
                if r["cancel"]:
                    con.execute("UPDATE jobs SET state = 'cancelled', finished = ?, owner = NULL WHERE id = ?", (now, r["id"]))
                elif r["attempts"] >= max_attempts:
                    con.execute(
                        "UPDATE jobs SET state = 'failed', finished = ?, owner = NULL, error = ? WHERE id = ?",
                        (now, f"interrupted {r['attempts']} times; giving up", r["id"]),
                    )
                else:
                    con.execute("UPDATE jobs SET state = 'queued', owner = NULL WHERE id = ?", (r["id"],))
                    again.append(r["id"])
            return again

        return self._tx(fn)

    def progress(self, job_id: str, step: str, done: int, total: int, *, of_step: str | None = None) -> None:
        """Record ``done`` of ``total`` frames of the progress entry ``step``, a part of the job's step ``of_step``
        (``step`` itself when not given); append an event when the summed count grows."""

        def fn(con: sqlite3.Connection):
            row = con.execute("SELECT progress, state FROM jobs WHERE id = ?", (job_id,)).fetchone()
            if row is None:
                return
            prog = json.loads(row["progress"])  # (in the order first reported: the pipeline's, as its steps announce
            # their entries when the run starts; a page lists them so)
            prog[step] = {"done": int(done), "total": int(total), "step": str(of_step or step)}
            sdone = sum(v["done"] for v in prog.values())
            stotal = sum(v["total"] for v in prog.values())
            con.execute(
                "UPDATE jobs SET progress = ?, done = ?, total = ?, heartbeat = ? WHERE id = ?",
                (json.dumps(prog), sdone, stotal, time.time(), job_id),
            )
            data = {"step": step, "step_done": int(done), "step_total": int(total), "done": sdone, "total": stotal,
                    "progress": prog, "state": row["state"]}
            con.execute(
                "INSERT OR IGNORE INTO events (job, seq, time, data) VALUES (?, ?, ?, ?)",
                (job_id, sdone, time.time(), json.dumps(data)),
            )

        self._tx(fn)

    def add_warnings(self, job_id: str, messages: Iterable[str]) -> None:
        """Keep ``messages`` among the job's warnings, after those it has, each once (a message it has already,
        said again by a step or by the job's next attempt, is not added twice).

        Parameters
        ----------
        job_id : str
            The job.
        messages : iterable of str
            What the job warned of, in the order said.

        Raises
        ------
        ValueError
            ``messages`` is a string, or holds something other than strings.
        JobNotFoundError
            No job ``job_id``.
        """
        if isinstance(messages, (str, bytes)):
            raise ValueError("messages must be an iterable of strings, got one string")
        said = list(messages)
        if not all(isinstance(m, str) for m in said):
            raise ValueError(f"messages must be strings, got {[type(m).__name__ for m in said]}")

        def fn(con: sqlite3.Connection):
            row = con.execute("SELECT warnings, result FROM jobs WHERE id = ?", (job_id,)).fetchone()
            if row is None:
                raise JobNotFoundError(f"no job {job_id!r}")
            kept = _warnings_of(row)
            new = [m for m in dict.fromkeys(said) if m not in kept]
            if new or row["warnings"] is None:
                con.execute("UPDATE jobs SET warnings = ? WHERE id = ?", (json.dumps(kept + new), job_id))

        self._tx(fn)

    def finish(self, job_id: str, state: str, *, error: str | None = None, result: dict | None = None) -> None:
        """Move a job to a terminal state."""
        if state not in TERMINAL:
            raise ValueError(f"state must be one of {sorted(TERMINAL)}, got {state!r}")
        self._con().execute(
            "UPDATE jobs SET state = ?, finished = ?, error = ?, result = ?, owner = NULL WHERE id = ?",
            (state, time.time(), error, json.dumps(result) if result is not None else None, job_id),
        )

    def requeue(self, job_id: str) -> None:
        """Put a running job back in the queue (its runner stopped before it finished)."""
        self._con().execute("UPDATE jobs SET state = 'queued', owner = NULL WHERE id = ? AND state = 'running'", (job_id,))

    # -- client side -------------------------------------------------------------------------
    def request_cancel(self, job_id: str) -> JobRecord:
        """Cancel a queued job at once; flag a running one (its runner stops it). Terminal jobs raise."""

        def fn(con: sqlite3.Connection):
            row = con.execute("SELECT state FROM jobs WHERE id = ?", (job_id,)).fetchone()
            if row is None:
                raise JobNotFoundError(f"no job {job_id!r}")
            if row["state"] in TERMINAL:
                raise JobStateError(f"job {job_id} is already {row['state']}")
            if row["state"] == "queued":
                con.execute("UPDATE jobs SET state = 'cancelled', cancel = 1, finished = ? WHERE id = ?", (time.time(), job_id))
            else:
                con.execute("UPDATE jobs SET cancel = 1 WHERE id = ?", (job_id,))

        self._tx(fn)
        return self.get(job_id)

    def delete(self, job_id: str) -> None:
        """Forget a terminal job (its results folder is removed by the caller)."""

        def fn(con: sqlite3.Connection):
            row = con.execute("SELECT state FROM jobs WHERE id = ?", (job_id,)).fetchone()
            if row is None:
                raise JobNotFoundError(f"no job {job_id!r}")
            if row["state"] not in TERMINAL:
                raise JobStateError(f"job {job_id} is {row['state']}; cancel it first")
            con.execute("DELETE FROM events WHERE job = ?", (job_id,))
            con.execute("DELETE FROM jobs WHERE id = ?", (job_id,))

        self._tx(fn)

    def active_for_take(self, take: str) -> list[str]:
        """Ids of queued or running jobs that use ``take``."""
        rows = self._con().execute(
            "SELECT id FROM jobs WHERE take = ? AND state IN ('queued', 'running')", (take,)
        ).fetchall()
        return [r["id"] for r in rows]
