"""The runner every step over a results directory shares (pipeline.run): the step list, the
executor fan-out with cancellation, and the start-over rule's settings and digests."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import hashlib
import logging
import threading
from functools import partial
from pathlib import Path

import numpy as np
import pytest

from pipeline.run import (
    Run,
    StepList,
    array_digest,
    changed_settings,
    chunks,
    file_digest,
    finished_before,
    frame_warnings,
    frames_said,
    frames_said_before,
    once_per_run,
    read_settings,
    submit_aside,
    submitted_by,
    warn_once,
)


def test_step_list_keeps_order_and_is_one_object():
    steps = StepList()
    seen = steps  # a name bound before a later registration sees it
    steps.register("a", lambda r: None)
    steps.register("c", lambda r: None)
    steps.register("b", lambda r: None, after="a", doc="between", totals=lambda r: [("b", 1)])
    assert tuple(seen) == ("a", "b", "c") and seen[:2] == ("a", "b") and seen.index("c") == 2 and "b" in seen
    assert steps.step("b").doc == "between" and steps.step("b").totals(None) == [("b", 1)]
    steps.register("a", lambda r: None, after="c")  # registered again: moved
    assert tuple(steps) == ("b", "c", "a")
    steps.remove("c")
    assert tuple(steps) == ("b", "a") and len(steps) == 2


def test_invalid_input():
    steps = StepList()
    with pytest.raises(ValueError, match="identifier"):
        steps.register("not a name", lambda r: None)
    with pytest.raises(ValueError, match="after: no step 'x'"):
        steps.register("a", lambda r: None, after="x")
    with pytest.raises(KeyError):
        steps.remove("a")
    for bad in (1.5, True, "3", None):
        with pytest.raises(ValueError, match="frame must be an integer"):
            with frame_warnings(bad):
                pass
    with pytest.raises(ValueError, match="step must be a string"):
        frames_said(None, {})
    with pytest.raises(ValueError, match="said must map frame sets"):
        frames_said("surface", {1: "camera cam02: ..."})
    with pytest.raises(ValueError, match="on_warning must be a callable"):
        Run(out=Path("."), on_warning="print")
    with pytest.raises(ValueError, match="message must be a string"):
        Run(out=Path(".")).keep_warning(None)
    for unit in ("", None, 1):
        with pytest.raises(ValueError, match="unit must be a non-empty string"):
            frames_said("surface", {}, unit=unit)
    with frame_warnings(np.int64(2)) as said:  # (a frame number from NumPy is one)
        pass
    assert said == []
    with pytest.raises(ValueError, match="exc must be an exception"):
        frames_said_before("frame set 4: unreadable")
    assert frames_said_before(ValueError("no frames")) == {}
    with pytest.raises(ValueError, match="exc must be an exception"):
        finished_before(["frame set 4"])
    assert finished_before(InterruptedError("cancelled")) == []
    with pytest.raises(ValueError, match="logger must be a logging.Logger"):
        warn_once("pipeline.track", "a message")
    with pytest.raises(ValueError, match="msg must be a string"):
        warn_once(logging.getLogger("pipeline.track"), None)
    with pytest.raises(ValueError, match="extra must be a dict"):
        warn_once(logging.getLogger("pipeline.track"), "a message", extra=["job_message"])


def test_a_kept_warning_is_handed_on_as_it_is_kept(tmp_path):
    """``keep_warning`` keeps a message in the run's warnings and hands it to ``on_warning`` at once, in order
    (a job's record keeps what a step said before it raised); without ``on_warning`` it is kept alone."""
    heard = []

    def step(run):
        run.keep_warning("surface: first")
        assert heard == ["surface: first"]  # (before the step goes on)
        run.keep_warning("surface: second")
        raise ValueError("the step broke")

    run = Run(out=tmp_path, on_warning=heard.append)
    with pytest.raises(ValueError, match="broke"):
        run.run_step("surface", step)
    assert heard == run.warnings == ["surface: first", "surface: second"]
    alone = Run(out=tmp_path)
    alone.keep_warning("key: third")
    assert alone.warnings == ["key: third"]


def test_map_tasks_here_and_on_a_pool_and_cancel_between_tasks(tmp_path):
    tasks = [partial(int, k) for k in range(6)]
    assert list(Run(out=tmp_path).map_tasks(tasks)) == list(range(6))
    with cf.ThreadPoolExecutor(2) as ex:
        assert sorted(Run(out=tmp_path, executor=ex).map_tasks(tasks)) == list(range(6))
    cancel = threading.Event()
    run = Run(out=tmp_path, cancel=cancel)
    got = []
    with pytest.raises(InterruptedError):
        for x in run.map_tasks(tasks):
            got.append(x)
            cancel.set()
    assert got == [0]


def _squares(n: int) -> int:
    return sum(i * i for i in range(n))


def test_a_task_aside_runs_on_the_executor_and_says_when_it_cannot(caplog):
    said = "the pool is gone ({exc}); the work is done here"
    assert submit_aside(None, partial(int, 3), unavailable=said) is None  # no executor: the caller does it
    with cf.ThreadPoolExecutor(1) as ex:
        aside = submit_aside(ex, partial(int, 3), unavailable=said)
        assert aside.wait(10) and aside.result() == 3 and aside.cpu_seconds is None  # a thread's seconds are ours
    with cf.ProcessPoolExecutor(1) as ex:
        aside = submit_aside(ex, partial(_squares, 300_000), unavailable=said)
        assert aside.result() == _squares(300_000) and aside.cpu_seconds > 0.0
    with caplog.at_level("WARNING"):
        assert submit_aside(ex, partial(int, 3), unavailable=said) is None  # shut down
    assert "the pool is gone (cannot schedule new futures after shutdown); the work is done here" in caplog.text


def _warns(k: int) -> int:
    logging.getLogger("pipeline.carve").warning("camera %d: no mask", k, extra={"job_message": f"camera {k} in a job"})
    logging.getLogger("pipeline.carve").info("not a warning")
    return k


class _Heard(logging.Handler):
    """The ``pipeline`` loggers' records: (the thread whose work each is, its message, its job_message)."""

    def __init__(self):
        super().__init__(logging.INFO)
        self.heard = []

    def emit(self, record):
        self.heard.append((submitted_by(record.thread), record.levelno, record.getMessage(),
                           getattr(record, "job_message", None)))


@contextlib.contextmanager
def _hearing(name: str = "pipeline", level: int | None = logging.INFO):
    """A :class:`_Heard` on logger ``name`` (at ``level``, unless None) for the ``with`` block; the logger as before
    after it."""
    heard, logger = _Heard(), logging.getLogger(name)
    logger.addHandler(heard)
    before = logger.level
    if level is not None:
        logger.setLevel(level)
    try:
        yield heard
    finally:
        logger.removeHandler(heard)
        logger.setLevel(before)


@pytest.mark.parametrize("pool", [cf.ProcessPoolExecutor, cf.ThreadPoolExecutor])
def test_what_a_task_warns_of_on_a_worker_is_said_in_the_callers_thread(tmp_path, pool):
    """A task aside or a mapped task that warns on the ``pipeline`` loggers: in a worker process its warnings (not its
    lower records) are said again in the thread that takes its result, once, with their ``job_message``; in a thread
    pool's thread its records are the submitting thread's work (``submitted_by``)."""
    me = threading.get_ident()
    with _hearing() as heard, pool(1) as ex:
        aside = submit_aside(ex, partial(_warns, 3), unavailable="{exc}")
        assert aside.result() == 3 and aside.result() == 3
        assert sorted(Run(out=tmp_path, executor=ex).map_tasks([partial(_warns, k) for k in (4, 5)])) == [4, 5]
    warned = [(t, m, j) for t, lv, m, j in heard.heard if lv == logging.WARNING]
    assert sorted(warned) == [(me, f"camera {k}: no mask", f"camera {k} in a job") for k in (3, 4, 5)]
    # a thread's lower records reach this process's handlers as they are said; a process's do not come back
    assert sum(lv < logging.WARNING for _, lv, _, _ in heard.heard) == (3 if pool is cf.ThreadPoolExecutor else 0)
    assert submitted_by(me) == me


def _warns_then_fails(k: int) -> int:
    _warns(k)
    raise ValueError(f"task {k} failed")


@pytest.mark.parametrize("pool", [cf.ProcessPoolExecutor, cf.ThreadPoolExecutor])
def test_what_a_task_warned_of_before_it_failed_is_said_in_the_callers_thread(tmp_path, pool):
    """A task aside or a mapped task that warns and then raises: in a worker process its warnings are said again in
    the thread that takes its result, once, with their ``job_message``, before its error is raised there (a job
    that fails keeps what its steps said before, :func:`pipeline.process.steps._job_warnings`); in a thread pool's
    thread they were said as they were said."""
    me = threading.get_ident()
    with _hearing() as heard, pool(1) as ex:
        aside = submit_aside(ex, partial(_warns_then_fails, 3), unavailable="{exc}")
        for _ in range(2):
            with pytest.raises(ValueError, match="task 3 failed"):
                aside.result()
        with pytest.raises(ValueError, match="task 4 failed"):
            list(Run(out=tmp_path, executor=ex).map_tasks([partial(_warns_then_fails, 4)]))
    warned = [(t, m, j) for t, lv, m, j in heard.heard if lv == logging.WARNING]
    assert warned == [(me, f"camera {k}: no mask", f"camera {k} in a job") for k in (3, 4)], warned


def _warns_aside(ex, k: int) -> int:
    return submit_aside(ex, partial(_warns, k), unavailable="{exc}").result()


def test_a_task_a_thread_pools_task_submits_is_the_first_submitters_work():
    """A task aside on a thread pool that itself submits a task aside on it: the inner task's records are the work
    of the thread that submitted the outer one (``submitted_by``), whose job's warnings keep them."""
    me = threading.get_ident()
    with _hearing(level=None) as heard, cf.ThreadPoolExecutor(2) as ex:
        assert submit_aside(ex, partial(_warns_aside, ex, 6), unavailable="{exc}").result() == 6
    assert [(t, m) for t, lv, m, _ in heard.heard if lv == logging.WARNING] == [(me, "camera 6: no mask")]


def test_announced_progress_is_closed_when_the_step_ends(tmp_path):
    calls = []
    run = Run(out=tmp_path, progress=lambda *a: calls.append(a))
    run.announce("s", [("s one", 4), ("s two", 2)])
    run.run_step("s", lambda r: r.report_progress("s one", 4, 4))
    assert calls == [("s one", 0, 4), ("s two", 0, 2), ("s one", 4, 4), ("s two", 2, 2)]
    assert set(run.clock.cpu) == set(run.clock.wall) == {"s"}


def test_a_progress_entry_is_told_with_the_step_that_announced_it(tmp_path):
    """An entry belongs to the step that announced it, even reported while another runs; one not announced to
    the step running when it is first reported; one reported outside any step to itself. A callback that does
    not take ``of_step`` is told the three arguments alone."""
    calls, plain = [], []
    run = Run(out=tmp_path, progress=lambda name, done, total, of_step=None: calls.append((name, done, total, of_step)))
    run.report_progress("loose", 0, 1)
    run.announce("surface", [("box", 3), ("surface", 3)])
    run.announce("refine", [("refine", 3)])
    run.run_step("key", lambda r: (r.report_progress("key", 2, 2), r.report_progress("refine", 1, 3)))
    run.run_step("rig", lambda r: (r.report_progress("track", 3, 3), r.report_progress("rig fit", 1, 3),
                                   r.report_progress("track", 3, 3)))
    assert calls == [("loose", 0, 1, "loose"), ("box", 0, 3, "surface"), ("surface", 0, 3, "surface"),
                     ("refine", 0, 3, "refine"), ("key", 2, 2, "key"), ("refine", 1, 3, "refine"),
                     ("track", 3, 3, "rig"), ("rig fit", 1, 3, "rig"), ("track", 3, 3, "rig")]
    assert [run.step_of(n) for n in ("box", "refine", "track", "loose")] == ["surface", "refine", "rig", "loose"]
    run = Run(out=tmp_path, progress=lambda *a: plain.append(a))
    run.announce("surface", [("box", 3)])
    assert plain == [("box", 0, 3)]


def test_chunks():
    assert chunks([1, 2, 3, 4, 5], 2) == [[1, 2], [3, 4], [5]] and chunks([], 3) == []


def test_digests_equal_the_reference(tmp_path):
    p = tmp_path / "f.bin"
    p.write_bytes(b"abc" * 100)
    assert file_digest(p) == hashlib.sha256(b"abc" * 100).hexdigest()
    V, F = np.arange(12, dtype=np.float32).reshape(4, 3), np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    ref = hashlib.sha256(V.astype(np.float64).tobytes() + F.astype(np.int64).tobytes()).hexdigest()
    assert array_digest(V, F) == ref == array_digest(V.astype(np.float64), F.astype(np.int64))
    assert array_digest(V + 1, F) != ref


def test_settings_compare_all_but_results_and_read_old_keys(tmp_path):
    old = {"a": 1, "b": 2, "frames": {"0": 1}}
    assert changed_settings(old, {"a": 1, "b": 2, "frames": {}}, results={"frames"}) == []
    assert changed_settings(old, {"b": 3, "a": 1, "c": 0}) == ["b", "c"]
    # a key an earlier version did not write, read as what that version did
    assert changed_settings(old, {"a": 1, "c": 0}, was=lambda o, k, new: o.get(k, 0)) == []
    assert read_settings(tmp_path / "none.json") is None
    for text in ("{not json", "[1, 2]", ""):
        (tmp_path / "s.json").write_text(text)
        assert read_settings(tmp_path / "s.json") is None  # unreadable or not settings: nothing kept
    (tmp_path / "s.json").write_text('{"a": 1}')
    assert read_settings(Path(tmp_path / "s.json")) == {"a": 1}


def _frames_warn(frames: list[int]) -> list[tuple[int, list]]:
    out = []
    for k in frames:
        with frame_warnings(k) as said:
            if k % 2:
                logging.getLogger("pipeline.hull").warning("camera %s: mask is all foreground", "cam02")
                logging.getLogger("pipeline.hull").warning("camera %s: mask is all foreground", "cam02")  # (again)
            if k == 4:
                logging.getLogger("stage.keying").warning("cam01: see --plate", extra={"job_message": "cam01: see plate"})
        out.append((k, said))
    logging.getLogger("pipeline.hull").warning("after the frames")
    return out


@pytest.mark.parametrize("pool", [None, cf.ProcessPoolExecutor, cf.ThreadPoolExecutor])
def test_what_a_frame_warns_of_comes_back_with_it_and_is_said_once_per_kind(tmp_path, pool):
    """Warnings said on the ``pipeline`` and ``stage`` loggers while a task works on a frame set (``frame_warnings``)
    come back with the task's result, wherever it ran, and reach no handler at WARNING level (a terminal's, a job's):
    in this process they are DEBUG records naming the frame set; ``frames_said`` says each kind once, with the count
    of frame sets and the first five, in the log's words and the job's. A warning outside a frame is said as ever."""
    heard = _Heard()
    heard.setLevel(logging.DEBUG)
    loggers = [logging.getLogger(n) for n in ("pipeline", "stage")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.addHandler(heard)
        lg.setLevel(logging.DEBUG)
    try:
        with pool(2) if pool else contextlib.nullcontext() as ex:
            got = [r for rs in Run(out=tmp_path, executor=ex).map_tasks([partial(_frames_warn, ch)
                                                                         for ch in chunks(range(13), 4)]) for r in rs]
    finally:
        for lg, level in zip(loggers, levels):
            lg.removeHandler(heard)
            lg.setLevel(level)
    said = dict(got)
    assert sorted(said) == list(range(13)) and said[0] == [] and said[2] == []
    assert said[3] == [("camera cam02: mask is all foreground", None)] * 2
    assert said[4] == [("cam01: see --plate", "cam01: see plate")]
    assert [m for _, lv, m, _ in heard.heard if lv == logging.WARNING] == ["after the frames"] * 4  # one per task
    debug = [m for _, lv, m, _ in heard.heard if lv == logging.DEBUG]
    if pool is cf.ProcessPoolExecutor:
        assert debug == []  # (a worker process's stay in its own log)
    else:
        assert sorted(debug) == sorted([f"frame set {k}: camera cam02: mask is all foreground" for k in range(1, 13, 2)
                                        for _ in range(2)] + ["frame set 4: cam01: see --plate"])
    mask = "camera cam02: mask is all foreground (6 frame sets: 1, 3, 5, 7, 9, ...)"
    assert frames_said("surface", said) == [(f"surface: {mask}", f"surface: {mask}"),
                                            ("surface: cam01: see --plate (1 frame set: 4)",
                                             "surface: cam01: see plate (1 frame set: 4)")]
    assert frames_said("surface", {}) == []
    assert frames_said("skeletons", {2: [("empty", None)], 5: [("empty", None)]}, unit="frame") == [
        ("skeletons: empty (2 frames: 2, 5)",) * 2]


def test_with_no_handler_set_up_a_warning_outside_a_frame_still_reaches_loggings_last_resort(monkeypatch):
    """The frames' handler on the ``pipeline`` and ``stage`` loggers does not silence a program that set no logging
    up: a warning outside a frame reaches ``logging.lastResort`` (stderr) as it would without that handler; one in
    a frame is kept for the frame."""
    from pipeline.run.context import _FRAME_HANDLER

    heard = _Heard()
    heard.setLevel(logging.WARNING)
    monkeypatch.setattr(logging, "lastResort", heard)
    for name in ("", "pipeline", "stage", "pipeline.hull", "stage.keying"):
        lg = logging.getLogger(name)
        monkeypatch.setattr(lg, "handlers", [_FRAME_HANDLER] if name in ("pipeline", "stage") else [])
    logging.getLogger("pipeline.hull").warning("outside")
    logging.getLogger("stage.keying").info("below the last resort's level")
    with frame_warnings(3) as said:
        logging.getLogger("stage.keying").warning("inside")
    assert [m for _, _, m, _ in heard.heard] == ["outside"] and said == [("inside", None)]


class _BasicConfig(logging.Handler):
    """What ``logging.basicConfig(level=...)`` installs: a handler of no level of its own on the root logger, the
    level on the root logger (the ``pipeline`` and ``stage`` loggers have none of their own)."""

    def __init__(self, level: int):
        super().__init__(logging.NOTSET)
        self.level_asked, self.lines = level, []

    def emit(self, record):
        self.lines.append((record.levelno, record.name, record.getMessage()))

    def __enter__(self):
        root = logging.getLogger()
        self._was = root.level, [(lg, lg.level) for lg in map(logging.getLogger, ("pipeline", "stage"))]
        for lg, _ in self._was[1]:
            lg.setLevel(logging.NOTSET)
        root.setLevel(self.level_asked)
        root.addHandler(self)
        return self

    def __exit__(self, *exc):
        root = logging.getLogger()
        root.removeHandler(self)
        root.setLevel(self._was[0])
        for lg, level in self._was[1]:
            lg.setLevel(level)


@pytest.mark.parametrize("pool", [None, cf.ThreadPoolExecutor])
def test_a_frames_warnings_reach_a_basic_config_at_info_not_at_all_and_at_debug_once_each(tmp_path, pool):
    """``logging.basicConfig(level=logging.INFO)`` (or ``stage -v``): what a frame warns of reaches its handler not at
    all, at no level (the step says each kind once); at DEBUG (``stage -vv``) each frame's, as a DEBUG record naming
    the frame set. A warning outside a frame reaches it either way."""
    tasks = [partial(_frames_warn, ch) for ch in chunks(range(13), 4)]
    for level in (logging.INFO, logging.DEBUG):
        with _BasicConfig(level) as basic, pool(2) if pool else contextlib.nullcontext() as ex:
            said = dict(r for rs in Run(out=tmp_path, executor=ex).map_tasks(tasks) for r in rs)
        assert said[3] == [("camera cam02: mask is all foreground", None)] * 2  # (kept for the frame either way)
        heard = [(lv, m) for lv, name, m in basic.lines if name.startswith(("pipeline", "stage"))]
        assert [m for lv, m in heard if lv >= logging.INFO] == ["after the frames"] * 4, heard
        debug = sorted(m for lv, m in heard if lv < logging.INFO)
        assert debug == ([] if level == logging.INFO else sorted(
            [f"frame set {k}: camera cam02: mask is all foreground" for k in range(1, 13, 2) for _ in range(2)]
            + ["frame set 4: cam01: see --plate"])), debug


def test_a_python_user_at_info_sees_each_kind_of_a_steps_frame_warnings_once(tmp_path):
    """``process_take`` under ``logging.basicConfig(level=logging.INFO)`` on a take whose camera cam02's masks are
    all foreground in frame sets 1-3 and whose frame set 4 is empty (surface, spine, track): each kind of what the
    frames warn of is said once, with its frame sets, and no line of the run names one frame set or is said for
    several (the per-frame lines are DEBUG, and DEBUG is off)."""
    import re

    from pipeline.process import process_take
    from tests.pipeline.hull_scenes import FAILED_MASKS_SAID, take_with_failed_masks

    take = take_with_failed_masks(tmp_path / "t.h5")
    with _BasicConfig(logging.INFO) as basic:
        process_take(take, tmp_path / "out", steps=["surface", "spine", "track"], params={"resolution": 32})
    lines = [m for lv, name, m in basic.lines if name.startswith(("pipeline", "stage"))]
    assert all(lv >= logging.INFO for lv, _, _ in basic.lines), basic.lines
    assert [m for m in lines if "foreground" in m] == FAILED_MASKS_SAID, lines
    assert not [m for m in lines if re.match(r"frame set \d+: ", m)], lines
    kinds = [re.sub(r"\d+", "#", m) for m in lines]
    assert not [k for k in set(kinds) if kinds.count(k) > 2], lines  # (no line said for frame sets 1, 2 and 3)


def _warns_once(k: int) -> int:
    """Says the message every part of a run says alike, and one of its own, once per run."""
    logger = logging.getLogger("pipeline.track")
    warn_once(logger, "%d frame sets have no surface and are tracked past", 1, extra={"job_message": "in a job"})
    warn_once(logger, "part %d: its own", k)
    return k


@pytest.mark.parametrize("pool", [None, "fork", cf.ThreadPoolExecutor])
def test_a_warning_said_once_per_run_is_said_once_by_the_run_and_its_tasks(tmp_path, pool):
    """``warn_once`` in a run (``once_per_run``): a message the run's parts say alike is said once, with its
    ``job_message``, whether said here, in a run within the run (its rounds), in a task aside or mapped on a thread
    pool or in a worker process (said again in this thread, once); outside a run, each time; the next run says it
    again, also when its task runs in a worker process forked during the run before (a pool outlives its runs)."""
    heard, logger = _Heard(), logging.getLogger("pipeline")
    logger.addHandler(heard)
    level = logger.level
    logger.setLevel(logging.INFO)
    make = None if pool is None else partial(cf.ProcessPoolExecutor, mp_context=__import__("multiprocessing").get_context(
        "fork")) if pool == "fork" else pool

    def tasks(ex, ks):
        if ex is None:
            return [_warns_once(k) for k in ks]
        aside = submit_aside(ex, partial(_warns_once, ks[0]), unavailable="{exc}")
        return [aside.result(), *sorted(Run(out=tmp_path, executor=ex).map_tasks([partial(_warns_once, k)
                                                                                   for k in ks[1:]]))]

    def said():
        out = [(m, j) for _, lv, m, j in heard.heard if lv == logging.WARNING]
        heard.heard.clear()
        return out

    gap = ("1 frame sets have no surface and are tracked past", "in a job")
    try:
        assert [_warns_once(k) for k in (0, 0)] == [0, 0]
        assert said() == [gap, ("part 0: its own", None)] * 2  # outside a run: each time
        with make() if make else contextlib.nullcontext() as ex:
            with once_per_run():
                _warns_once(1)
                with once_per_run():  # (a round's own run: the outer one)
                    _warns_once(2)
                assert tasks(ex, [3, 4, 5]) == [3, 4, 5]
                in_run = said()
            with once_per_run():  # the next run, on the same pool
                assert tasks(ex, [6, 7]) == [6, 7]
                next_run = said()
    finally:
        logger.removeHandler(heard)
        logger.setLevel(level)
    assert in_run[:3] == [gap, ("part 1: its own", None), ("part 2: its own", None)], in_run
    assert sorted(in_run[3:]) == [(f"part {k}: its own", None) for k in (3, 4, 5)], in_run
    assert next_run.count(gap) == 1 and sorted(next_run) == sorted([gap, ("part 6: its own", None),
                                                                    ("part 7: its own", None)]), next_run


def test_one_tracking_run_says_what_every_round_says_of_the_surfaces_once(tmp_path):
    """``process_take`` with the track step (a carve round, the template's labels, an armature round) on a take
    whose frame set 4 has no surface and whose spine is unusable, under ``logging.basicConfig(level=logging.INFO)``:
    the frame set tracked past and the labels that have no effect are said once (the first tracking, the carve
    round and the armature round each read the surfaces and the spine), and kept once in the report; then
    ``stage track`` of the same results with a carve round, two armature rounds and ``--labels``: once each too."""
    import json

    from pipeline.process import process_take
    from stage.cli import main
    from tests.pipeline.hull_scenes import take_with_failed_masks

    take = take_with_failed_masks(tmp_path / "t.h5")
    track = {"carve": 1, "labels": True, "armature_rounds": 1}
    with _BasicConfig(logging.INFO) as basic:
        process_take(take, tmp_path / "out", steps=["surface", "spine", "track"],
                     params={"resolution": 32, "track": track})
    lines = [m for lv, name, m in basic.lines if name == "pipeline.track" and lv == logging.WARNING]
    gap = [m for m in lines if "have no surface and are tracked past" in m]
    labels = [m for m in lines if m.startswith("labels='spine' (--labels) has no effect")]
    assert gap == ["1 frame sets have no surface and are tracked past: 4 (empty)"] and len(labels) == 1, lines
    warned = json.loads((tmp_path / "out" / "report.json").read_text())["warnings"]
    assert sum("tracked past" in w for w in warned) == 1 and sum("labels" in w for w in warned) == 1, warned
    heard, logger = _Heard(), logging.getLogger("pipeline.track")
    logger.addHandler(heard)
    try:
        assert main(["-q", "track", str(tmp_path / "out"), "--carve", "1", "--armature-rounds", "2", "--labels",
                     "--workers", "0", "--no-progress"]) == 0
    finally:
        logger.removeHandler(heard)
    said = [m for _, lv, m, _ in heard.heard if lv == logging.WARNING]
    assert sum("tracked past" in m for m in said) == 1 and sum("(--labels) has no effect" in m for m in said) == 1, said


def _frames_then_fail(frames: list[int], *, fail: int) -> list[dict]:
    """A per-frame task (as ``surface_task``): every frame set warns of camera cam02's mask; frame set ``fail`` warns
    of its own, then raises."""
    out = []
    for k in frames:
        with frame_warnings(k) as said:
            logging.getLogger("pipeline.hull").warning("camera cam02: mask is all foreground")
            if k == fail:
                logging.getLogger("pipeline.hull").warning("its images are unreadable")
                raise ValueError(f"frame set {k}: unreadable")
        out.append({"index": k, "said": said})
    return out


@pytest.mark.parametrize("pool", [None, cf.ProcessPoolExecutor, cf.ThreadPoolExecutor])
def test_what_the_frames_of_a_task_that_failed_said_goes_on_with_its_error(tmp_path, pool):
    """A per-frame task that raises on its third frame set: what its frames said before (the two it finished, whose
    results are lost with the task's, and the one it failed on) goes on with its error, here, on a thread and from
    a worker process (``frames_said_before``)."""
    with pool(1) if pool else contextlib.nullcontext() as ex:
        with pytest.raises(ValueError, match="frame set 4: unreadable") as raised:
            list(Run(out=tmp_path, executor=ex).map_tasks([partial(_frames_then_fail, [2, 3, 4], fail=4)]))
    mask, own = ("camera cam02: mask is all foreground", None), ("its images are unreadable", None)
    assert frames_said_before(raised.value) == {2: [mask], 3: [mask], 4: [mask, own]}


def test_a_step_whose_task_failed_says_what_its_frames_said_before(tmp_path):
    """``RunContext.run_frames`` over six frame sets in chunks of three, the second chunk failing on frame set 4:
    the step says what every frame set said before the error, the failed chunk's 3 and 4 too, once per kind (a job
    that fails keeps them), and the error goes on."""
    from pipeline.process import ProcessParams, RunContext
    from pipeline.process.context import TakeFacts

    take = TakeFacts(path=tmp_path / "t.h5", calibration=None, cameras=["cam02"], n_sets=6, fps=30.0, rig={})
    kept = []
    ctx = RunContext(out=tmp_path, params=ProcessParams(chunk=3), need_key=False, take=take, on_warning=kept.append)
    with pytest.raises(ValueError, match="frame set 4: unreadable"):
        ctx.run_frames("surface", partial(_frames_then_fail, fail=4), "meshes")
    assert ctx.warnings == kept == [
        "surface: camera cam02: mask is all foreground (5 frame sets: 0, 1, 2, 3, 4)",
        "surface: its images are unreadable (1 frame set: 4)"], ctx.warnings


def _wait_for(*paths: Path) -> None:
    """Until every one of ``paths`` exists (a test's tasks wait for each other; 60 s at most)."""
    for _ in range(6000):
        if all(p.exists() for p in paths):
            return
        threading.Event().wait(0.01)
    raise AssertionError(f"never written: {[str(p) for p in paths if not p.exists()]}")


def _frame_that_finishes_late_or_fails(frames: list[int], *, marks: str, fail: int | None) -> list[dict]:
    """A per-frame task (as ``surface_task``) of one frame set: each warns of camera cam02's mask and marks its
    frame set done (``marks/done_K``) before it returns; frame set ``fail`` waits until the others have started,
    marks ``marks/failing`` and raises, the others (with ``fail``) finish only once it has (and a little later: the
    caller has seen it fail)."""
    (k,) = frames
    (Path(marks) / f"started_{k}").touch()
    with frame_warnings(k) as said:
        logging.getLogger("pipeline.hull").warning("camera cam02: mask is all foreground")
        if k == fail:
            logging.getLogger("pipeline.hull").warning("its images are unreadable")
            _wait_for(*(Path(marks) / f"started_{j}" for j in range(3)))
            (Path(marks) / "failing").touch()
            raise ValueError(f"frame set {k}: unreadable")
        if fail is not None:
            _wait_for(Path(marks) / "failing")
            threading.Event().wait(0.3)
    logging.getLogger("pipeline.surface").warning("frame set %d's task ends", k)
    (Path(marks) / f"done_{k}").touch()
    return [{"index": k, "said": said}]


@pytest.mark.parametrize("pool", [cf.ProcessPoolExecutor, cf.ThreadPoolExecutor])
@pytest.mark.parametrize("stop", ["failed", "cancelled"])
def test_a_step_that_stops_says_what_every_task_that_finished_said(tmp_path, pool, stop):
    """``RunContext.run_frames`` over three frame sets, one per task, on a pool of three, stopping before it took
    the other tasks' results: frame set 0's task fails while the others still run ("failed"), or the run is
    cancelled once every task has finished but one was taken ("cancelled"). The step says what every frame set that
    finished said (their results are written), and each task's own warnings, once per kind, before the error goes
    on: a job's warnings have them all; its progress counts every frame set finished."""
    from pipeline.process import ProcessParams, RunContext
    from pipeline.process.context import TakeFacts

    marks = tmp_path / "marks"
    marks.mkdir()
    cancel = threading.Event()

    reported = []

    def progress(step, done, total):
        reported.append((step, done, total))
        if stop == "cancelled" and done == 1:  # (the first task taken: the others finish, then the run is cancelled)
            _wait_for(*(marks / f"done_{k}" for k in range(3)))
            cancel.set()

    take = TakeFacts(path=tmp_path / "t.h5", calibration=None, cameras=["cam02"], n_sets=3, fps=30.0, rig={})
    kept = []
    with pool(3) as ex, _hearing("pipeline.surface") as heard:
        ctx = RunContext(out=tmp_path, params=ProcessParams(chunk=1), need_key=False, take=take, executor=ex,
                         on_warning=kept.append, progress=progress, cancel=cancel)
        with pytest.raises(ValueError if stop == "failed" else InterruptedError):
            ctx.run_frames("surface", partial(_frame_that_finishes_late_or_fails, marks=str(marks),
                                              fail=0 if stop == "failed" else None), "meshes")
    finished = [1, 2] if stop == "failed" else [0, 1, 2]
    assert all((marks / f"done_{k}").exists() for k in finished)
    expected = ["surface: camera cam02: mask is all foreground (3 frame sets: 0, 1, 2)"]
    if stop == "failed":
        expected.append("surface: its images are unreadable (1 frame set: 0)")
    assert ctx.warnings == kept == expected, ctx.warnings
    ends = sorted(m for _, lv, m, _ in heard.heard if lv == logging.WARNING)
    assert ends == [f"frame set {k}'s task ends" for k in finished]
    assert reported[-1] == ("surface", len(finished), 3), reported  # (the step's progress counts them all)
