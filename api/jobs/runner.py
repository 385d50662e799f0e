"""The job runner: takes queued jobs from the :class:`~api.jobs.store.JobStore` and runs them.

A dispatcher thread polls the store; each claimed job runs in its own thread,
which calls the *work* function (by default :func:`pipeline.process.process_take`)
with the shared executor, a progress callback that writes to the store, and a
cancel event. The work function persists per-frame results in the job's output
folder and resumes from the unfinished frames when called again on it, so a job
interrupted by a killed server is simply queued again (its heartbeat goes stale)
and run again.

Hook for tests and plug-ins: ``JobRunner(..., work=fn)`` or the setting
``work = "module:function"``; ``fn`` has the signature of ``process_take``::

    fn(take, out, *, steps, params, executor, progress, cancel[, warn]) -> result

A work function that takes ``warn`` is handed ``warn(message)``, to call as each of its warnings is said: the job's
record keeps them (``warnings``) in every state, a failed or cancelled job those said before it stopped. A done
job's record has the warnings of its result too (``result.report.warnings``, else ``result.warnings``): all of
them for a work function without ``warn``.

If the function's module defines ``ProcessParams`` (a pydantic model) the job's
``parameters`` are validated into it, ``STEPS`` (a tuple) lists the allowed steps, and
``check_job_steps(steps)`` (raising ValueError) refuses steps a job could not run from its empty folder.
"""

from __future__ import annotations

import importlib
import inspect
import json
import logging
import threading
import uuid
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from api.executors import ExecutorHandle, make_executor
from api.jobs.store import JobRecord, JobStore, result_warnings
from api.paths import confined, data_relative
from calib.fileio import json_ready, plain

__all__ = ["JobRunner", "WorkSpec", "WorkUnavailableError", "load_work", "takes_warn", "DEFAULT_STEPS"]

log = logging.getLogger(__name__)

DEFAULT_STEPS = ("key", "surface", "spine")


class WorkUnavailableError(RuntimeError):
    """The work function cannot be imported (maps to 503)."""


@dataclass(frozen=True)
class WorkSpec:
    """A work function with what is needed to validate a job for it."""

    fn: Callable[..., Any]
    steps: tuple[str, ...] = DEFAULT_STEPS
    params_model: Any = None
    defaults: tuple[str, ...] | None = None  # steps of a job that names none (default: all)
    check_steps: Callable[[tuple[str, ...]], None] | None = None  # the module's check_job_steps, if any

    def validate(self, steps: Sequence[str] | None, params: dict | None) -> tuple[tuple[str, ...], dict]:
        """Check ``steps`` and ``params``; return them normalized (steps in canonical order, params as JSON dict).

        Raises
        ------
        ValueError
            Naming the unknown step or the bad parameter.
        """
        steps = tuple((self.defaults or self.steps) if steps is None else steps)
        if not steps:
            raise ValueError("steps must not be empty")
        unknown = [s for s in steps if s not in self.steps]
        if unknown:
            raise ValueError(f"steps: unknown step(s) {unknown}; allowed: {list(self.steps)}")
        if len(set(steps)) != len(steps):
            raise ValueError("steps: duplicate steps")
        if self.check_steps is not None:
            self.check_steps(steps)
        params = dict(params or {})
        if self.params_model is not None:
            from pydantic import ValidationError

            try:
                model = self.params_model.model_validate(params)
            except ValidationError as exc:
                # (a rule between parameters is the model's: no location, its message names them; without
                # pydantic's "Value error, " before it)
                msgs = "; ".join(f"{'.'.join(map(str, e['loc']))}: {_said(e)}" if e["loc"] else _said(e)
                                 for e in exc.errors())
                raise ValueError(f"parameters: {msgs}") from None
            params = json.loads(model.model_dump_json(exclude_defaults=True))
        return tuple(s for s in self.steps if s in steps), params

    def to_params(self, params: dict) -> Any:
        """The object handed to the work function as ``params``."""
        if self.params_model is None:
            return params or None
        return self.params_model.model_validate(params)


def _said(error: dict) -> str:
    """A pydantic error's message, a ValueError raised by a validator as it was raised (pydantic puts "Value error, "
    before it)."""
    msg = str(error.get("msg", ""))
    if error.get("type") == "value_error" and msg.startswith("Value error, "):
        return msg[len("Value error, "):]
    return msg


def load_work(spec: str | Callable[..., Any]) -> WorkSpec:
    """Resolve ``"module:function"`` (or a callable) into a :class:`WorkSpec`.

    Raises
    ------
    WorkUnavailableError
        When the module or function cannot be imported.
    """
    if callable(spec):
        mod = importlib.import_module(spec.__module__) if getattr(spec, "__module__", None) else None
        fn = spec
    else:
        modname, _, fname = str(spec).partition(":")
        if not modname or not fname:
            raise ValueError(f"work must be 'module:function', got {spec!r}")
        try:
            mod = importlib.import_module(modname)
            fn = getattr(mod, fname)
        except (ImportError, AttributeError) as exc:
            raise WorkUnavailableError(f"processing is not available: cannot import {spec} ({exc})") from None
    steps = tuple(getattr(mod, "STEPS", DEFAULT_STEPS)) if mod is not None else DEFAULT_STEPS
    model = getattr(mod, "ProcessParams", None) if mod is not None else None
    if model is not None and not hasattr(model, "model_validate"):
        model = None
    defaults = tuple(getattr(mod, "DEFAULT_STEPS", steps)) if mod is not None else None
    check = getattr(mod, "check_job_steps", None) if mod is not None else None
    return WorkSpec(fn=fn, steps=steps, params_model=model, defaults=defaults,
                    check_steps=check if callable(check) else None)


def takes_warn(fn: Callable[..., Any]) -> bool:
    """Whether a work function or job handler takes ``warn`` (by name, or as any keyword).

    Parameters
    ----------
    fn : callable
        The work function (``process_take``'s signature) or a job kind's handler.

    Returns
    -------
    bool
        True when ``fn(..., warn=...)`` is accepted: the runner then hands it the job's ``warn(message)``.
        A callable without a signature (a builtin) does not take it.

    Raises
    ------
    ValueError
        ``fn`` is not callable.
    """
    if not callable(fn):
        raise ValueError(f"fn must be a callable, got {type(fn).__name__}")
    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):  # (a callable without a signature)
        return False
    return any((p.name == "warn" and p.kind != p.POSITIONAL_ONLY) or p.kind == p.VAR_KEYWORD for p in params)


def _jsonable(obj: Any) -> Any:
    """What a work function returned, as JSON: numbers, arrays and records through
    :func:`calib.fileio.json_default`; anything else as its ``str``; a non-finite number as None (the job's record
    never fails on it, nor does the API's strict JSON when it serves the record)."""
    if obj is None:
        return None
    try:
        return plain(json_ready(obj), finite=True)
    except (TypeError, ValueError):
        pass
    try:
        return plain(json.loads(json.dumps(obj, default=str)), finite=True)
    except (TypeError, ValueError):
        return {"repr": repr(obj)}


class JobRunner:
    """Runs queued jobs; survives restarts through the store.

    Parameters
    ----------
    store : JobStore
    takes_dir, jobs_dir : Path
        Where takes are read (``<take>.h5``) and results written (``<job>/``).
    work : str or callable
        The work function (see module docstring).
    executor : ExecutorHandle or callable returning one, optional
        Default: :func:`api.executors.make_executor` with ``dask``/``workers``; created on first use.
    dask, workers
        Passed to :func:`~api.executors.make_executor`.
    heartbeat_s, stale_after_s, max_attempts, max_concurrent, poll_s
        See :class:`api.settings.Settings`.
    """

    def __init__(
        self,
        store: JobStore,
        *,
        takes_dir: Path,
        jobs_dir: Path,
        work: str | Callable[..., Any] = "pipeline.process:process_take",
        executor: ExecutorHandle | Callable[[], ExecutorHandle] | None = None,
        dask: str | None = None,
        workers: int | None = None,
        heartbeat_s: float = 2.0,
        stale_after_s: float = 10.0,
        max_attempts: int = 5,
        max_concurrent: int = 1,
        poll_s: float = 0.25,
        handlers: dict[str, Callable[..., Any]] | None = None,
    ) -> None:
        if heartbeat_s <= 0 or stale_after_s <= heartbeat_s:
            raise ValueError("stale_after_s must be larger than heartbeat_s > 0")
        self.store = store
        self.takes_dir = Path(takes_dir)
        self.jobs_dir = Path(jobs_dir)
        self.work = work
        self.handlers = dict(handlers or {})
        self._executor_arg = executor
        self._dask, self._workers = dask, workers
        self.heartbeat_s, self.stale_after_s = heartbeat_s, stale_after_s
        self.max_attempts, self.max_concurrent, self.poll_s = max_attempts, max_concurrent, poll_s
        self.owner = uuid.uuid4().hex
        self._handle: ExecutorHandle | None = None
        self._handle_lock = threading.Lock()
        self._active: dict[str, tuple[threading.Thread, threading.Event]] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None

    # -- public ------------------------------------------------------------------------------
    def work_spec(self) -> WorkSpec:
        """The resolved work function (raises :class:`WorkUnavailableError`)."""
        return load_work(self.work)

    def executor(self) -> ExecutorHandle:
        """The shared executor, created on first use."""
        with self._handle_lock:
            if self._handle is None:
                arg = self._executor_arg
                if isinstance(arg, ExecutorHandle):
                    self._handle = arg
                elif callable(arg):
                    self._handle = arg()
                else:
                    self._handle = make_executor(dask=self._dask, workers=self._workers)
                log.info("jobs run on %s", self._handle.description)
            return self._handle

    def start(self) -> None:
        """Start the dispatcher thread (idempotent)."""
        if self._thread is not None and self._thread.is_alive():
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, name="job-dispatcher", daemon=True)
        self._thread.start()

    def wake(self) -> None:
        """Look for queued jobs now rather than at the next poll."""
        self._wake.set()

    def stop(self, *, timeout: float = 30.0) -> None:
        """Stop: running jobs are asked to stop and go back to the queue (they resume on the next start).

        The dispatcher is stopped first, so no job is launched after the running ones are collected;
        a launch that races with the stop sees the stop flag under the lock and queues its job again
        (:meth:`_launch`), and every thread in the active set has been started, so each can be joined.
        """
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        with self._lock:
            active = list(self._active.items())
        for _, (_, ev) in active:
            ev.set()
        for _, (th, _) in active:
            th.join(timeout)
        self._reap()
        with self._handle_lock:
            if self._handle is not None and not isinstance(self._executor_arg, ExecutorHandle):
                self._handle.close()
            self._handle = None

    @property
    def active(self) -> list[str]:
        with self._lock:
            return list(self._active)

    # -- dispatcher --------------------------------------------------------------------------
    def _loop(self) -> None:
        import time

        last_beat = 0.0
        while not self._stop.is_set():
            try:
                now = time.monotonic()
                if now - last_beat >= self.heartbeat_s:
                    last_beat = now
                    self._beat()
                    again = self.store.requeue_stale(stale_after_s=self.stale_after_s, max_attempts=self.max_attempts)
                    for jid in again:
                        log.warning("job %s was interrupted; queued again to resume", jid)
                self._reap()
                while len(self.active) < self.max_concurrent and not self._stop.is_set():
                    rec = self.store.claim(self.owner)
                    if rec is None:
                        break
                    self._launch(rec)
            except Exception:  # the dispatcher must outlive a failing poll (e.g. a locked database)
                log.exception("job dispatcher poll failed")
            self._wake.wait(min(self.poll_s, self.heartbeat_s))
            self._wake.clear()

    def _beat(self) -> None:
        ids = self.active
        if not ids:
            return
        cancelled = self.store.heartbeat(ids, self.owner)
        with self._lock:
            for jid in cancelled:
                if jid in self._active:
                    self._active[jid][1].set()

    def _reap(self) -> None:
        with self._lock:
            for jid in [j for j, (th, _) in self._active.items() if not th.is_alive()]:
                del self._active[jid]

    def _launch(self, rec: JobRecord) -> None:
        ev = threading.Event()
        if rec.cancel_requested:
            ev.set()
        th = threading.Thread(target=self._run, args=(rec, ev), name=f"job-{rec.id[:8]}", daemon=True)
        # started under the lock: a thread in the active set is always alive or finished, never
        # "not yet started" (stop() joins it, _reap() would drop it as finished)
        with self._lock:
            stopping = self._stop.is_set()
            if not stopping:
                self._active[rec.id] = (th, ev)
                th.start()
        if stopping:  # claimed while the runner was stopping: back to the queue
            self.store.requeue(rec.id)

    def _run(self, rec: JobRecord, cancel: threading.Event) -> None:
        jid = rec.id
        log.info("job %s: %s on take %s (attempt %d)", jid, "/".join(rec.steps), rec.take, rec.attempts)
        try:
            take = self.takes_dir / f"{rec.take}.h5"
            if not take.is_file() or not confined(take, self.takes_dir):
                raise FileNotFoundError(f"take {rec.take!r} not found")
            out = self.jobs_dir / jid
            out.mkdir(parents=True, exist_ok=True)

            def progress(name: str, done: int, total: int, of_step: str | None = None) -> None:
                # (of_step: the job's step the entry belongs to, as the pipeline announced it)
                self.store.progress(jid, str(name), int(done), int(total), of_step=of_step)

            def warn(message: str) -> None:  # kept as said: a job that fails next still has it
                try:
                    self.store.add_warnings(jid, [data_relative(str(message), self.takes_dir.parent)])
                except Exception:  # (a warning never fails the job: the report keeps it if the job ends well)
                    log.exception("job %s: a warning could not be kept: %s", jid, message)

            if rec.kind == "process":
                spec = self.work_spec()
                result = spec.fn(
                    take, out, steps=tuple(rec.steps), params=spec.to_params(rec.params),
                    executor=self.executor().executor, progress=progress, cancel=cancel,
                    **({"warn": warn} if takes_warn(spec.fn) else {}),
                )
            elif rec.kind in self.handlers:
                handler = self.handlers[rec.kind]
                result = handler(take, out, params=rec.params, progress=progress, cancel=cancel, job_id=jid,
                                 take_id=rec.take, **({"warn": warn} if takes_warn(handler) else {}))
            else:
                raise ValueError(f"unknown job kind {rec.kind!r}")
        except InterruptedError:  # the work stopped on the cancel event
            self._after_stop_or_fail(jid, cancel, "interrupted")
            return
        except BrokenProcessPool as exc:
            self._reset_executor()
            self._after_stop_or_fail(jid, cancel, f"worker pool broke: {exc}", requeue=True)
            return
        except (ValueError, FileNotFoundError, WorkUnavailableError) as exc:
            # a work function's error said in a job's words (pipeline.process.ProcessError.job_message), if it has them
            self._after_stop_or_fail(jid, cancel, str(getattr(exc, "job_message", None) or exc))
            return
        except Exception as exc:  # any failure of the work must end the job with a message, not kill the runner
            log.exception("job %s failed", jid)
            self._after_stop_or_fail(jid, cancel, f"internal error: {type(exc).__name__}: {exc}")
            return
        stopped = cancel.is_set()  # (read once: a stop of the server meanwhile does not make a done job cancelled)
        if stopped and not self._user_cancelled(jid):
            self._requeue(jid)
            return
        public = self._public(result)
        self.store.add_warnings(jid, result_warnings(public))  # (a work function without ``warn``: all of them)
        if stopped:
            self.store.finish(jid, "cancelled", result=public)
        else:
            self.store.finish(jid, "done", result=public)
            log.info("job %s done", jid)

    def _public(self, result: Any) -> Any:
        """The work's result as JSON, the server's paths written as ``DATA/...``."""
        return data_relative(_jsonable(result), self.takes_dir.parent)

    def _user_cancelled(self, jid: str) -> bool:
        try:
            return self.store.get(jid).cancel_requested
        except KeyError:
            return True

    def _requeue(self, jid: str) -> None:
        # server shutting down: back to the queue, resumes on the next start
        self.store.requeue(jid)
        log.info("job %s stopped with the server; queued to resume", jid)

    def _after_stop_or_fail(self, jid: str, cancel: threading.Event, error: str, *, requeue: bool = False) -> None:
        error = data_relative(error, self.takes_dir.parent)  # never show the server's paths
        if cancel.is_set():
            if self._user_cancelled(jid):
                self.store.finish(jid, "cancelled")
            else:
                self._requeue(jid)
        elif requeue:
            self._requeue(jid)
        else:
            self.store.finish(jid, "failed", error=error)
            log.warning("job %s failed: %s", jid, error)

    def _reset_executor(self) -> None:
        with self._handle_lock:
            if self._handle is not None and not isinstance(self._executor_arg, ExecutorHandle):
                self._handle.close()
                self._handle = None
