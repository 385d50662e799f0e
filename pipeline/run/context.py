"""What the steps of one run share from the runner: the executor, progress, cancellation, timings."""

from __future__ import annotations

import concurrent.futures as cf
import inspect
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, suppress
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stage.messages import frames_named

__all__ = ["Aside", "Clock", "Run", "chunks", "forking_pool", "frame_warnings", "frames_said", "frames_said_before",
           "finished_before", "once_per_run", "pool_size", "submit_aside", "submitted_by", "warn_once"]

log = logging.getLogger(__name__)


def chunks(items: Sequence[int], n: int) -> list[list[int]]:
    """``items`` in consecutive lists of ``n`` (the last one shorter)."""
    return [list(items[i : i + n]) for i in range(0, len(items), n)]


def pool_size(executor) -> int:
    """Tasks an executor runs at once (a process pool's workers; 2 when it does not say)."""
    return int(getattr(executor, "_max_workers", 0) or 2)


def forking_pool(executor) -> bool:
    """A local process pool whose workers are forked from this process."""
    ctx = getattr(executor, "_mp_context", None)
    return isinstance(executor, cf.ProcessPoolExecutor) and (ctx is None or ctx.get_start_method(allow_none=False) == "fork")


#: a thread of this process running a task (:func:`_with_cpu`) -> the thread that submitted it
_SUBMITTED_BY: dict[int, int] = {}


def submitted_by(thread: int) -> int:
    """The thread that submitted the task thread ``thread`` of this process runs now (a thread pool's worker, through
    :func:`submit_aside` or :meth:`Run.map_tasks`; of a task a task submitted, the first submitter), or ``thread``
    itself: whose work a log record of that thread is (``logging.LogRecord.thread``)."""
    return _SUBMITTED_BY.get(thread, thread)


class _KeptWarnings(logging.Handler):
    """The warnings the ``pipeline`` and ``stage`` loggers say in this thread, kept as ``(logger, level, message,
    job_message, once)`` (``once``: said by :func:`warn_once`)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.thread, self.said = threading.get_ident(), []

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread != self.thread:  # (a Dask worker runs other tasks in its other threads)
            return
        try:
            self.said.append((record.name, record.levelno, record.getMessage(), getattr(record, "job_message", None),
                              bool(getattr(record, "said_once", False))))
        except Exception:  # a message that cannot be formatted: said as logging says it
            self.handleError(record)


#: the loggers whose warnings a frame keeps (:func:`frame_warnings`) and a worker process returns (:func:`_with_cpu`)
_WARNING_LOGGERS = ("pipeline", "stage")

#: the frame this thread (or asyncio task) works on and the warnings said in it (:func:`frame_warnings`)
_FRAME: ContextVar[tuple[int, list] | None] = ContextVar("pipeline_frame_warnings", default=None)
#: the frames the task running in this thread has worked on (:func:`frame_warnings`) and what each said: a task that
#: raises hands them on with its error (:func:`_task`, :func:`frames_said_before`)
_TASK_FRAMES: ContextVar[dict[int, list] | None] = ContextVar("pipeline_task_frames", default=None)


#: a level below every handler's (``logging.NOTSET`` is 0): a record of this level reaches none
_NO_HANDLER = -1


class _FrameWarnings(logging.Handler):
    """First handler of the ``pipeline`` and ``stage`` loggers: a warning said while this thread works on a frame
    (:func:`frame_warnings`) is kept for the frame, then goes on as a DEBUG record naming the frame where its logger
    logs DEBUG (``stage -vv``), and reaches no other handler elsewhere, as a DEBUG record would not be made there:
    a handler of no level of its own (``logging.basicConfig(level=logging.INFO)``'s) takes every record that reaches
    it. The frame's warnings are said once per kind by the step that ran the frames, not one frame at a time, on a
    terminal, in a job, in a worker. Any other record it leaves to the others; with none (logging not set up) it
    hands it to ``logging.lastResort``, as logging would without this handler."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)

    def emit(self, record: logging.LogRecord) -> None:
        kept = _FRAME.get()
        if kept is None or record.levelno != logging.WARNING:
            last = logging.lastResort  # what logging does when no handler is there (this one aside)
            if last is not None and record.levelno >= last.level and not self._others(record.name):
                last.handle(record)
            return
        frame, said = kept
        try:
            message = record.getMessage()
        except Exception:  # a message that cannot be formatted: said as logging says it
            self.handleError(record)
            return
        said.append((message, getattr(record, "job_message", None)))
        record.msg, record.args = f"frame set {frame}: {message}", None
        debug = logging.getLogger(record.name).isEnabledFor(logging.DEBUG)
        record.levelno, record.levelname = (logging.DEBUG if debug else _NO_HANDLER), logging.getLevelName(logging.DEBUG)

    def _others(self, name: str) -> bool:
        """A handler other than this one takes the records of logger ``name`` (its own or an ancestor's)."""
        c: logging.Logger | None = logging.getLogger(name)
        while c is not None:
            if any(h is not self for h in c.handlers):
                return True
            c = c.parent if c.propagate else None
        return False


_FRAME_HANDLER = _FrameWarnings()


def _first_handler() -> None:
    """:data:`_FRAME_HANDLER` first on the loggers of :data:`_WARNING_LOGGERS` (again, should logging have been
    set up anew since). The list is made anew under logging's own lock, the one ``Logger.addHandler`` and
    ``removeHandler`` hold: a job's handler added or removed meanwhile in another thread is not lost (a server runs
    several jobs at once); a thread logging meanwhile reads the old list."""
    for name in _WARNING_LOGGERS:
        logger = logging.getLogger(name)
        if logger.handlers and logger.handlers[0] is _FRAME_HANDLER:  # (every call but after logging was set up anew)
            continue
        with logging._lock:  # (the handler lists' lock; logging has no public one)
            if not logger.handlers or logger.handlers[0] is not _FRAME_HANDLER:
                logger.handlers = [_FRAME_HANDLER, *(h for h in logger.handlers if h is not _FRAME_HANDLER)]


_first_handler()


@contextmanager
def frame_warnings(frame: int) -> Iterator[list[tuple[str, str | None]]]:
    """Keep the warnings the ``pipeline`` and ``stage`` loggers say in this thread while the block works on frame
    set ``frame``, for the task to return with the frame's result, instead of saying them now.

    A per-frame task runs each frame in one (:func:`pipeline.process.tasks.surface_task`); the step that ran the
    frames says each kind of message once, with the count of frame sets and the first of them (:func:`frames_said`),
    in the run's warnings (a job's, ``report.json``'s) and on the terminal. Each frame's warning is still logged,
    at DEBUG level and prefixed with ``frame set N:``, where its logger logs DEBUG (``stage -vv``); where it does not
    (``logging.basicConfig(level=logging.INFO)``, ``stage -v``), it reaches no handler.

    Parameters
    ----------
    frame : int
        The frame set the block works on (named in the DEBUG records).

    Yields
    ------
    list of (str, str or None)
        Filled as warnings are said: the message and its ``job_message`` (``extra={"job_message": ...}``; None
        when it gave none), in the order said, repeats included.

    Raises
    ------
    ValueError
        ``frame`` is not an integer.
    """
    if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)):
        raise ValueError(f"frame must be an integer (a frame set), got {frame!r}")
    _first_handler()
    said: list[tuple[str, str | None]] = []
    task = _TASK_FRAMES.get()
    if task is not None:
        task[int(frame)] = said
    token = _FRAME.set((int(frame), said))
    try:
        yield said
    finally:
        _FRAME.reset(token)


def frames_said(step: str, said: dict[int, list[tuple[str, str | None]]], *,
                unit: str = "frame set") -> list[tuple[str, str]]:
    """One warning per kind of message the frames said (:func:`frame_warnings`): ``"{step}: {message} (N frame
    sets: a, b, c, ...)"``, the first :data:`stage.messages.FRAMES_NAMED` frame sets named
    (:func:`stage.messages.frames_named`), in the order the messages were first said (by frame set).

    Parameters
    ----------
    step : str
        What ran the frames (the warnings' prefix).
    said : dict of int to list of (str, str or None)
        Per frame set, what :func:`frame_warnings` kept.
    unit : str
        What the numbers count: ``"frame set"`` (a take's), ``"frame"`` (a mesh sequence's); an ``s`` is added for
        more than one.

    Returns
    -------
    list of (str, str)
        Per kind of message, the warning in the log's words and in a job's (the ``job_message``, where given).

    Raises
    ------
    ValueError
        ``step`` or ``unit`` is not a string (``unit`` empty), or ``said`` not a dict of frame sets to lists.
    """
    if not isinstance(step, str):
        raise ValueError(f"step must be a string, got {step!r}")
    if not isinstance(unit, str) or not unit:
        raise ValueError(f"unit must be a non-empty string, got {unit!r}")
    if not isinstance(said, dict) or not all(isinstance(v, (list, tuple)) for v in said.values()):
        raise ValueError(f"said must map frame sets to lists of (message, job_message), got {type(said).__name__}")
    frames: dict[tuple[str, str | None], list[int]] = {}
    for k in sorted(said):
        for kind in dict.fromkeys(said[k]):
            frames.setdefault(kind, []).append(int(k))
    out = []
    for (message, job_message), ks in frames.items():
        where = f" ({len(ks)} {unit}{'s' if len(ks) != 1 else ''}: {frames_named(ks)})"
        out.append((f"{step}: {message}{where}", f"{step}: {job_message or message}{where}"))
    return out


#: the thread running a run (:func:`once_per_run`) -> what :func:`warn_once` said in it, as (logger, message)
_SAID_ONCE: dict[int, set[tuple[str, str]]] = {}
_SAID_ONCE_LOCK = threading.Lock()


def _no_run_said() -> None:
    """In a process forked from this one (a pool's worker): no run, and a lock no other thread holds. A worker's
    one thread has the id of the thread that forked it, whose run's messages would otherwise silence the worker's
    in later runs (a server's pool outlives its jobs)."""
    global _SAID_ONCE_LOCK
    _SAID_ONCE_LOCK = threading.Lock()
    _SAID_ONCE.clear()


os.register_at_fork(after_in_child=_no_run_said)


@contextmanager
def once_per_run() -> Iterator[None]:
    """A run in which a warning said with :func:`warn_once` is said once, however many of its parts say it: the
    tracking's surfaces that have frame sets without one are read again by every carve round and armature round
    of one ``stage track`` or track step, which say it once. A run within a run (the rounds' own) is the outer
    one; the tasks the run submits (a thread pool's, :func:`submitted_by`; a worker process's, said again in this
    thread) are the run's.

    Yields
    ------
    None
    """
    me = submitted_by(threading.get_ident())
    with _SAID_ONCE_LOCK:
        outer = me in _SAID_ONCE
        if not outer:
            _SAID_ONCE[me] = set()
    try:
        yield
    finally:
        if not outer:
            with _SAID_ONCE_LOCK:
                _SAID_ONCE.pop(me, None)


def warn_once(logger: logging.Logger, msg: str, *args: object, **kwargs: object) -> None:
    """``logger.warning(msg, *args, **kwargs)``, unless the run this thread works for (:func:`once_per_run`) has
    said the same message on ``logger`` already; outside a run, always. In a worker process the record is said, and
    once per run in the thread that takes the task's result (:func:`submit_aside`, :meth:`Run.map_tasks`).

    Parameters
    ----------
    logger : logging.Logger
        Where it is said.
    msg : str
        The message, with ``args`` as :meth:`logging.Logger.warning` takes them (``extra``, ``exc_info``...).

    Raises
    ------
    ValueError
        ``logger`` is not a logger, ``msg`` not a string, or ``extra`` not a dict.
    """
    if not isinstance(logger, logging.Logger):
        raise ValueError(f"logger must be a logging.Logger, got {type(logger).__name__}")
    if not isinstance(msg, str):
        raise ValueError(f"msg must be a string, got {type(msg).__name__}")
    extra = kwargs.pop("extra", None) or {}
    if not isinstance(extra, dict):
        raise ValueError(f"extra must be a dict, got {type(extra).__name__}")
    with _SAID_ONCE_LOCK:
        said = _SAID_ONCE.get(submitted_by(threading.get_ident()))
        if said is not None:
            try:
                key = (logger.name, msg % args if args else msg)
            except (TypeError, ValueError):  # (a message that cannot be formatted: said as logging says it)
                key = (logger.name, f"{msg} {args!r}")
            if key in said:
                return
            said.add(key)
    logger.warning(msg, *args, extra={**extra, "said_once": True}, **kwargs)


def _task(task: Callable[[], object]) -> object:
    """``task()``; when it raises, what its frames said before (:func:`frame_warnings`: the frames it finished and the
    one it failed on) goes on with the error (``pipeline_frames_said``, :func:`frames_said_before`)."""
    token = _TASK_FRAMES.set({})
    try:
        return task()
    except Exception as exc:
        frames = {k: said for k, said in (_TASK_FRAMES.get() or {}).items() if said}
        with suppress(AttributeError):  # (an exception without a __dict__ of its own: none)
            exc.pipeline_frames_said = {**frames, **frames_said_before(exc)}  # (a task's task's first)
        raise
    finally:
        _TASK_FRAMES.reset(token)


def _check_exception(exc) -> None:
    """``ValueError`` naming ``exc`` unless it is an exception."""
    if not isinstance(exc, BaseException):
        raise ValueError(f"exc must be an exception, got {type(exc).__name__}")


def frames_said_before(exc: BaseException) -> dict[int, list[tuple[str, str | None]]]:
    """What the frames of a per-frame task that raised ``exc`` said before it failed (:func:`frame_warnings`): the
    frames it finished, whose results are lost with the task's, and the one it failed on. The task ran through
    :meth:`Run.map_tasks` or :func:`submit_aside`, here, on a thread or in another process.

    Parameters
    ----------
    exc : BaseException
        The task's error.

    Returns
    -------
    dict of int to list of (str, str or None)
        Per frame set, what :func:`frame_warnings` kept (none: ``{}``), for :func:`frames_said`.

    Raises
    ------
    ValueError
        ``exc`` is not an exception.
    """
    _check_exception(exc)
    said = getattr(exc, "pipeline_frames_said", None)
    return {int(k): [tuple(x) for x in v] for k, v in said.items()} if isinstance(said, dict) else {}


def finished_before(exc: BaseException) -> list:
    """The results of the tasks :meth:`Run.map_tasks` had not yet handed out when it stopped on ``exc`` (a task that
    failed, or the run cancelled) and that finished: a per-frame step says what their frames said.

    Parameters
    ----------
    exc : BaseException
        The error :meth:`Run.map_tasks` stopped on.

    Returns
    -------
    list
        The tasks' results, in no set order (none: ``[]``).

    Raises
    ------
    ValueError
        ``exc`` is not an exception.
    """
    _check_exception(exc)
    finished = getattr(exc, "pipeline_finished", None)
    return list(finished) if isinstance(finished, list) else []


def _with_cpu(task: Callable[[], object], origin: tuple[int, int] | None = None) -> tuple[object, float, int, list]:
    """A task's result, the CPU seconds its process spent on it, that process's id and the warnings the ``pipeline``
    loggers said in it (run in the worker). ``origin``: (process id, thread) of the caller that submitted the task.

    In another process the warnings are kept (in place of the worker's stderr, where a process pool's records go)
    and returned, for :func:`_say_again` to say them in the caller's thread; in a thread of the caller's process its
    records reach the process's handlers as they are said, and :func:`submitted_by` names the caller's thread."""
    t = time.process_time()
    if origin is not None and origin[0] == os.getpid():
        me = threading.get_ident()
        _SUBMITTED_BY[me] = origin[1]
        try:
            out = _task(task)
        finally:
            _SUBMITTED_BY.pop(me, None)
        return out, time.process_time() - t, os.getpid(), []
    keep = _KeptWarnings()
    for name in _WARNING_LOGGERS:
        logging.getLogger(name).addHandler(keep)
    try:
        out = _task(task)
    except Exception as exc:  # what it said before it failed goes back with its error (:func:`_said_before`)
        with suppress(AttributeError):  # (an exception without a __dict__ of its own: none)
            exc.pipeline_said = keep.said
        raise
    finally:
        for name in _WARNING_LOGGERS:
            logging.getLogger(name).removeHandler(keep)
    return out, time.process_time() - t, os.getpid(), keep.said


def _origin() -> tuple[int, int]:
    """(process id, thread) of the caller submitting a task: the thread whose work the caller's is
    (:func:`submitted_by`), so that a task a thread pool's task submits is the first submitter's work too."""
    return os.getpid(), submitted_by(threading.get_ident())


def _said_before(exc: BaseException) -> list:
    """What a task that raised ``exc`` in another process said before it failed (:func:`_with_cpu`)."""
    said = getattr(exc, "pipeline_said", None)
    return said if isinstance(said, list) else []


def _say_again(said: list) -> None:
    """The warnings a task said in another process (:func:`_with_cpu`), said again here, on their loggers, in this
    thread: the job's warnings (``pipeline.process.steps._job_warnings``) and the command's terminal get them as
    they get this process's own."""
    for name, level, message, job_message, once in said:
        extra = None if job_message is None else {"job_message": job_message}
        if once:  # (said once per run here too: the worker's run is this thread's)
            warn_once(logging.getLogger(name), "%s", message, extra=extra)
        else:
            logging.getLogger(name).log(level, "%s", message, extra=extra)


class Aside:
    """One task running on an executor while this process works on (:func:`submit_aside`)."""

    def __init__(self, future: cf.Future):
        self._future = future
        #: CPU seconds the task took in another process; None until it has, or when it ran in this
        #: one (a thread's seconds are already this process's)
        self.cpu_seconds: float | None = None
        self._said = False

    def wait(self, timeout: float | None = None) -> bool:
        """Wait at most ``timeout`` seconds; True once the task has finished (or failed)."""
        return bool(cf.wait([self._future], timeout=timeout).done)

    def result(self) -> object:
        """The task's result; ``concurrent.futures.BrokenExecutor`` when its worker process died. The warnings
        the task said in another process are said again in this thread, the first time (:func:`_say_again`); those
        of a task that raised, before its error is raised here."""
        try:
            out, cpu, pid, said = self._future.result()
        except Exception as exc:
            if not self._said:
                self._said = True
                _say_again(_said_before(exc))
            raise
        if pid != os.getpid():
            self.cpu_seconds = cpu
            if not self._said:
                self._said = True
                _say_again(said)
        return out


def submit_aside(executor: cf.Executor | None, task: Callable[[], object], *, unavailable: str,
                 logger: logging.Logger = log) -> Aside | None:
    """Start ``task`` (picklable for a process pool: a top-level function or a ``functools.partial`` of
    one) on ``executor`` while this process does other work, as tracking and carving split a take
    in two halves; None when there is no executor, or when its pool is broken or shut down (then
    ``unavailable``, with ``{exc}`` for the reason, is a warning on ``logger`` and the caller does the work).
    What the task's ``pipeline`` loggers warn of in another process is said again in the thread that takes its
    result (:meth:`Aside.result`); in a thread of this process, :func:`submitted_by` names the submitting thread."""
    if executor is None:
        return None
    try:
        return Aside(executor.submit(_with_cpu, task, _origin()))
    except (cf.BrokenExecutor, RuntimeError) as exc:  # a broken or shut-down pool
        logger.warning("%s", unavailable.format(exc=exc))
        return None


@dataclass
class Clock:
    """The seconds every step and part of a run took (the report's ``seconds`` and ``cpu_seconds``)."""

    wall: dict[str, float] = field(default_factory=dict)  # step or part -> wall seconds
    cpu: dict[str, float] = field(default_factory=dict)  # step or part -> CPU seconds (this process and the workers)
    worker_cpu: dict[str, float] = field(default_factory=dict)  # step -> CPU seconds of its tasks in other processes
    in_parts: dict[str, tuple[float, float]] = field(default_factory=dict)  # step -> (wall, CPU) of its parts

    def add_part(self, step: str, name: str, wall: float, cpu: float) -> None:
        """A part of ``step`` counted on its own (not in the step's seconds)."""
        self.wall[name] = self.wall.get(name, 0.0) + wall
        self.cpu[name] = self.cpu.get(name, 0.0) + cpu
        w, c = self.in_parts.get(step, (0.0, 0.0))
        self.in_parts[step] = (w + wall, c + cpu)

    def add_worker_cpu(self, step: str, cpu: float) -> None:
        """CPU seconds a task of ``step`` spent in another process."""
        self.worker_cpu[step] = self.worker_cpu.get(step, 0.0) + cpu


def _takes_of_step(fn: Callable) -> bool:
    """Whether a progress callback takes ``of_step`` (by name, or as any keyword)."""
    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):  # (a builtin without a signature: the three arguments alone)
        return False
    return any(p.name == "of_step" or p.kind is p.VAR_KEYWORD for p in params)


@dataclass(kw_only=True)
class Run:
    """The runner's side of one run: where results go, where tasks run, who is told of progress,
    how to stop, what to warn of, and the seconds every step and part took (for the report)."""

    out: Path
    executor: cf.Executor | None = None
    #: ``progress(name, done, total)`` as an entry's count changes; told ``of_step=`` too, the step the entry
    #: belongs to (:meth:`step_of`), when it takes that keyword (or any keyword)
    progress: Callable[[str, int, int], None] | None = None
    cancel: threading.Event | None = None
    warnings: list[str] = field(default_factory=list)
    #: ``on_warning(message)`` as each warning is kept (:meth:`keep_warning`): a caller keeps those said before a
    #: step fails or the run is cancelled, which no report holds
    on_warning: Callable[[str], None] | None = None
    clock: Clock = field(default_factory=Clock)
    step: str = ""  # the step running
    _reported: dict[str, tuple[int, int]] = field(default_factory=dict, init=False, repr=False)  # progress name -> (done, total)
    _planned: dict[str, list[str]] = field(default_factory=dict, init=False, repr=False)  # step -> progress names announced
    _owner: dict[str, str] = field(default_factory=dict, init=False, repr=False)  # progress name -> its step

    @contextmanager
    def part(self, name: str):
        """Count a part of the running step on its own (e.g. the surface step's grid choice): its
        wall and CPU seconds are added to ``clock.wall[name]`` and ``clock.cpu[name]`` (a part run
        several times counts every run), not to the step's."""
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.clock.add_part(self.step, name, time.perf_counter() - t0, time.process_time() - c0)

    def __post_init__(self) -> None:
        if self.on_warning is not None and not callable(self.on_warning):
            raise ValueError(f"on_warning must be a callable taking a message, or None, got {self.on_warning!r}")

    def keep_warning(self, message: str) -> None:
        """Keep ``message`` in the run's ``warnings`` (the report's, a job's) and tell ``on_warning`` at once.

        Raises
        ------
        ValueError
            ``message`` is not a string.
        """
        if not isinstance(message, str):
            raise ValueError(f"message must be a string, got {message!r}")
        self.warnings.append(message)
        if self.on_warning is not None:
            self.on_warning(message)

    def step_of(self, name: str) -> str:
        """The step a progress entry belongs to: the one that announced it (:meth:`announce`), else the step that
        first reported it (the rig step's tracking, run within it), else the entry's own name (one reported
        outside any step)."""
        return self._owner.get(name) or self.step or name

    def report_progress(self, step: str, done: int, total: int) -> None:
        self._owner.setdefault(step, self.step_of(step))
        self._reported[step] = (int(done), int(total))
        if self.progress:
            if _takes_of_step(self.progress):
                self.progress(step, done, total, of_step=self._owner[step])
            else:
                self.progress(step, done, total)

    def announce(self, step: str, items: Sequence[tuple[str, int]]) -> None:
        """Report the progress entries ``(name, total)`` a step will report as 0 done before it
        runs, so the run's summed total counts every step it will run (a job never reads n/n while
        steps are still to come); :meth:`complete` closes those the step did not report."""
        for name, total in items:
            self._planned.setdefault(step, []).append(name)
            self._owner.setdefault(name, step)
            if name not in self._reported:
                self.report_progress(name, 0, total)

    def complete(self, step: str) -> None:
        """The announced entries of a finished step at done == total (a resumed step reports none)."""
        for name in self._planned.get(step, ()):
            done, total = self._reported.get(name, (0, 0))
            if done < total:
                self.report_progress(name, total, total)

    def check_cancel(self) -> None:
        """``InterruptedError`` when the run was cancelled."""
        if self.cancel is not None and self.cancel.is_set():
            raise InterruptedError("cancelled")

    def map_tasks(self, tasks: list[Callable[[], object]]) -> Iterator[object]:
        """Results of ``tasks`` as they finish (on the executor, or here one by one); stops
        between tasks when cancelled. The CPU seconds of workers in other processes add to the
        running step's (a thread pool's are already this process's), and the warnings they said are said
        again in this thread (:func:`_say_again`), a failed task's before its error is raised here.

        When it stops (a task failed, or the run was cancelled), the tasks not yet started are cancelled and those
        already running, which cannot be stopped, are waited for: what every task that finished said is said here
        too, their results go on with the error (:func:`finished_before`) and what the frames of another task that
        failed said joins :func:`frames_said_before`'s, so that every frame set whose result a task wrote has its
        warnings said. A Dask executor's futures never say they run (``running()`` is False and a running task's
        Dask status is "pending" like a queued one's), so there every task not taken is cancelled, none waited for."""
        if self.executor is None:
            for task in tasks:
                self.check_cancel()
                yield _task(task)
            return
        futures = [self.executor.submit(_with_cpu, task, _origin()) for task in tasks]
        left = set(futures)  # (not yet taken)
        try:
            for fut in cf.as_completed(futures):
                self.check_cancel()
                left.discard(fut)
                yield self._taken(fut)
        except Exception as exc:  # (stopped: the tasks that finish anyway are taken, with what they said)
            self._take_left(left, exc)
            raise
        finally:
            for fut in futures:
                fut.cancel()

    def _taken(self, fut: cf.Future) -> object:
        """A finished task's result, what it said in another process said again here, its CPU seconds counted; a
        failed task's error, raised after what it said before (a failed job keeps it)."""
        try:
            out, cpu, pid, said = fut.result()
        except Exception as exc:
            _say_again(_said_before(exc))
            raise
        if pid != os.getpid():
            self.clock.add_worker_cpu(self.step, cpu)
            _say_again(said)
        return out

    def _take_left(self, left: set[cf.Future], exc: Exception) -> None:
        """The tasks of ``left`` (not taken when :meth:`map_tasks` stopped on ``exc``): those not started are
        cancelled, the others waited for and taken; their results go on with ``exc`` (:func:`finished_before`), the
        frames of those that failed join what ``exc``'s said (:func:`frames_said_before`)."""
        for fut in left:
            fut.cancel()
        running = [fut for fut in left if not fut.cancelled()]
        cf.wait(running)
        finished, frames = [], {}
        for fut in running:
            try:
                finished.append(self._taken(fut))
            except Exception as other:  # (another task that failed: its own error is not raised)
                frames.update(frames_said_before(other))
        with suppress(AttributeError):  # (an exception without a __dict__ of its own: none)
            exc.pipeline_finished = [*finished_before(exc), *finished]
            exc.pipeline_frames_said = {**frames, **frames_said_before(exc)}

    def run_step(self, name: str, run: Callable[[Run], None]) -> None:
        """Run one step; its wall seconds go to ``clock.wall[name]`` and its CPU seconds (this
        process's and its tasks' in other processes) to ``clock.cpu[name]``, less those of its parts
        counted on their own (:meth:`part`); its announced progress entries end at done == total
        (:meth:`complete`)."""
        self.step = name
        w, t = time.perf_counter(), time.process_time()
        run(self)
        self.complete(name)
        part_wall, part_cpu = self.clock.in_parts.get(name, (0.0, 0.0))
        self.clock.wall[name] = time.perf_counter() - w - part_wall
        self.clock.cpu[name] = time.process_time() - t - part_cpu + self.clock.worker_cpu.get(name, 0.0)
