"""The durable job store and the runner, without HTTP: claim, heartbeat, stale requeue, resume after a crash."""

from __future__ import annotations

import concurrent.futures as cf
import json
import time

import numpy as np
import pytest

from api.executors import ExecutorHandle
from api.jobs import JobNotFoundError, JobRunner, JobStateError, JobStore, load_work
from api.jobs.runner import takes_warn
from tests.api import fakework


def _age(store: JobStore, jid: str, seconds: float) -> None:
    store._con().execute("UPDATE jobs SET heartbeat = ? WHERE id = ?", (time.time() - seconds, jid))


def test_claim_heartbeat_requeue_and_give_up(tmp_path):
    store = JobStore(tmp_path / "jobs.sqlite")
    a = store.create(kind="process", take="t", steps=["key"], params={})
    b = store.create(kind="process", take="t", steps=["key"], params={})
    assert store.claim("me").id == a.id  # oldest first
    assert store.get(a.id).state == "running" and store.get(a.id).attempts == 1
    assert store.heartbeat([a.id], "me") == set()
    assert store.requeue_stale(stale_after_s=60, max_attempts=3) == []  # fresh heartbeat: left alone
    _age(store, a.id, 120)
    assert store.requeue_stale(stale_after_s=60, max_attempts=3) == [a.id]
    assert store.get(a.id).state == "queued"
    # the same job is claimed again (still the oldest); after max_attempts interruptions it fails
    for attempt in (2, 3):
        assert store.claim("me").id == a.id and store.get(a.id).attempts == attempt
        _age(store, a.id, 120)
        store.requeue_stale(stale_after_s=60, max_attempts=3)
    st = store.get(a.id)
    assert st.state == "failed" and "interrupted 3 times" in st.error
    # cancel flags reach the heartbeat; a stale cancelled job ends cancelled
    assert store.claim("me").id == b.id
    store.request_cancel(b.id)
    assert store.heartbeat([b.id], "me") == {b.id}
    _age(store, b.id, 120)
    store.requeue_stale(stale_after_s=60, max_attempts=3)
    assert store.get(b.id).state == "cancelled"


def test_progress_events_are_monotonic_and_unique(tmp_path):
    store = JobStore(tmp_path / "jobs.sqlite")
    j = store.create(kind="process", take="t", steps=["key", "surface"], params={})
    for step, done in (("key", 0), ("key", 1), ("surface", 1), ("key", 2), ("key", 1), ("surface", 2)):
        store.progress(j.id, step, done, 2, **({"of_step": "surface"} if step == "surface" else {}))
    ev = store.events(j.id)
    assert [s for s, _ in ev] == [0, 1, 2, 3]  # one event per new total; a lower total adds none
    assert store.events(j.id, after=2) == ev[3:]
    # (an entry's step: the one told, else the entry's own name)
    assert store.get(j.id).progress == {"key": {"done": 1, "total": 2, "step": "key"},
                                        "surface": {"done": 2, "total": 2, "step": "surface"}}


def test_progress_keeps_its_entries_in_the_order_first_reported(tmp_path):
    """A job's progress entries, in its record and its events, in the order they were first reported (the pipeline's:
    its steps announce them when the run starts), not sorted by name: a page lists key, box, surface, ... as they
    run."""
    store = JobStore(tmp_path / "jobs.sqlite")
    j = store.create(kind="process", take="t", steps=["key", "surface", "spine"], params={})
    order = ["key", "box", "surface", "skeleton", "spine"]
    for step in order:
        store.progress(j.id, step, 0, 2)
    for step in reversed(order):
        store.progress(j.id, step, 2, 2)
    assert list(store.get(j.id).progress) == order
    assert all(list(data["progress"]) == order for _, data in store.events(j.id)[1:])
    assert list(JobStore(tmp_path / "jobs.sqlite").get(j.id).progress) == order  # (as read back from the file)


def test_runner_resumes_an_interrupted_job_with_the_same_output(tmp_path):
    takes, jobs = tmp_path / "takes", tmp_path / "jobs"
    takes.mkdir()
    fakework.make_take_file(takes / "t.h5", 8)
    ref = tmp_path / "ref"
    fakework.process_take(takes / "t.h5", ref)

    store = JobStore(tmp_path / "jobs.sqlite")
    j = store.create(kind="process", take="t", steps=["key", "surface", "spine"], params={})
    # a crash mid-job: the job is 'running' with a stale heartbeat and half of its frames on disk
    store.claim("dead-server")
    _age(store, j.id, 3600)
    out = jobs / j.id
    (out / "frames").mkdir(parents=True)
    for i in range(4):
        (out / "frames" / f"key_{i:06d}.txt").write_text((ref / "frames" / f"key_{i:06d}.txt").read_text())

    calls = []
    orig = fakework._frame

    def counting(step, index, salt, delay):
        calls.append((step, index))
        return orig(step, index, salt, delay)

    handle = ExecutorHandle(cf.ThreadPoolExecutor(2), "threads", "test")
    fakework._frame = counting
    runner = JobRunner(store, takes_dir=takes, jobs_dir=jobs, work=fakework.process_take, executor=handle,
                       heartbeat_s=0.05, stale_after_s=0.2, poll_s=0.02)
    try:
        runner.start()
        t0 = time.monotonic()
        while store.get(j.id).state != "done" and time.monotonic() - t0 < 20:
            time.sleep(0.02)
    finally:
        runner.stop()
        fakework._frame = orig
        handle.close()
    st = store.get(j.id)
    assert st.state == "done" and st.attempts == 2
    assert sorted(i for s, i in calls if s == "key") == [4, 5, 6, 7]  # only the unfinished frames
    assert json.loads((out / "spine.json").read_text()) == json.loads((ref / "spine.json").read_text())


def test_invalid_input(tmp_path):
    store = JobStore(tmp_path / "jobs.sqlite")
    with pytest.raises(JobNotFoundError):
        store.get("0" * 32)
    with pytest.raises(JobNotFoundError):
        store.request_cancel("0" * 32)
    j = store.create(kind="process", take="t", steps=["key"], params={})
    with pytest.raises(JobStateError):
        store.delete(j.id)  # still queued
    with pytest.raises(ValueError, match="state"):
        store.finish(j.id, "running")
    for bad in ("one string", [1], [None, "a"]):
        with pytest.raises(ValueError, match="messages must be"):
            store.add_warnings(j.id, bad)
    with pytest.raises(JobNotFoundError):
        store.add_warnings("0" * 32, ["a warning"])
    with pytest.raises(ValueError, match="stale_after_s"):
        JobRunner(store, takes_dir=tmp_path, jobs_dir=tmp_path, heartbeat_s=1, stale_after_s=0.5)
    with pytest.raises(ValueError, match="module:function"):
        load_work("nocolon")
    from api.jobs import WorkUnavailableError

    with pytest.raises(WorkUnavailableError):
        load_work("no_such_module_xyz:fn")
    spec = load_work("tests.api.fakework:process_take")
    assert spec.steps == ("key", "surface", "spine")
    assert spec.validate(["spine", "key"], {}) == (("key", "spine"), {})
    for steps, params in ((["x"], {}), ([], {}), (["key", "key"], {}), (None, {"delay_s": "slow"})):
        with pytest.raises(ValueError):
            spec.validate(steps, params)
    with pytest.raises(ValueError, match="fn must be a callable"):
        takes_warn("process_take")


def test_takes_warn_reads_the_signature():
    def named(take, out, *, warn=None): ...
    def keywords(take, out, **hooks): ...
    def without(take, out, *, steps=()): ...
    def positional_only(warn, /): ...

    assert [takes_warn(f) for f in (named, keywords, without, positional_only, len)] == [True, True, False, False,
                                                                                         False]


def test_graceful_stop_puts_the_running_job_back_in_the_queue(tmp_path):
    takes, jobs = tmp_path / "takes", tmp_path / "jobs"
    takes.mkdir()
    fakework.make_take_file(takes / "t.h5", 30)
    store = JobStore(tmp_path / "jobs.sqlite")
    j = store.create(kind="process", take="t", steps=["key", "surface", "spine"], params={"delay_s": 0.05})
    handle = ExecutorHandle(cf.ThreadPoolExecutor(2), "threads", "test")
    runner = JobRunner(store, takes_dir=takes, jobs_dir=jobs, work=fakework.process_take, executor=handle,
                       heartbeat_s=0.05, stale_after_s=0.2, poll_s=0.02)
    runner.start()
    t0 = time.monotonic()
    while store.get(j.id).done < 2 and time.monotonic() - t0 < 20:
        time.sleep(0.01)
    runner.stop()
    handle.close()
    st = store.get(j.id)
    assert st.state == "queued" and not st.cancel_requested and 2 <= st.done < 60


def test_start_stop_under_stress_loses_no_job_and_joins_every_thread(tmp_path):
    """200 start/stop cycles while jobs are being claimed and launched: no error, no job left running.

    A stop that races a launch used to join a thread that had not started yet (RuntimeError) or let
    the reaper drop it; every job must end queued (stopped with the runner) or done, never running.
    """
    takes, jobs = tmp_path / "takes", tmp_path / "jobs"
    takes.mkdir()
    fakework.make_take_file(takes / "t.h5", 1)
    store = JobStore(tmp_path / "jobs.sqlite")
    ran: list[str] = []

    def work(take, out, *, params, progress, cancel, job_id, take_id):
        ran.append(job_id)
        cancel.wait(0.002 * params.get("n", 0))
        if cancel.is_set():
            raise InterruptedError
        return {"ok": True}

    runner = JobRunner(store, takes_dir=takes, jobs_dir=jobs, handlers={"noop": work},
                       heartbeat_s=0.05, stale_after_s=0.2, poll_s=0.001, max_concurrent=3)
    rng = np.random.default_rng(0)
    ids = []
    for i in range(200):
        ids.append(store.create(kind="noop", take="t", steps=["noop"], params={"n": i % 4}).id)
        runner.start()
        runner.wake()
        time.sleep(float(rng.uniform(0, 0.004)))
        runner.stop(timeout=10)
        assert runner.active == []
        assert not [j for j in ids if store.get(j).state == "running"], f"cycle {i}: a job was left running"
    assert ran, "no job was ever launched: the stress did not exercise a launch"
    runner.start()
    try:
        t0 = time.monotonic()
        while any(store.get(j).state != "done" for j in ids) and time.monotonic() - t0 < 30:
            time.sleep(0.01)
    finally:
        runner.stop()
    assert {store.get(j).state for j in ids} == {"done"}


def test_a_jobs_warnings_are_kept_as_said_in_every_state(tmp_path):
    """A work function's warnings are in the job's record as it says them: a job that fails or is cancelled next
    keeps them (no result holds them); each once, the server's paths as ``DATA/...``; a done job has its result's
    too, and a work function that takes no ``warn`` has its result's alone."""
    from tests.polling import wait_until

    takes, jobs = tmp_path / "takes", tmp_path / "jobs"
    takes.mkdir()
    fakework.make_take_file(takes / "t.h5", 1)
    store = JobStore(tmp_path / "jobs.sqlite")

    def fails(take, out, *, params, progress, cancel, job_id, take_id, warn):
        warn("surface: camera cam02: mask is all foreground (3 frame sets: 1, 2, 3)")
        warn(f"surface: {out} holds results of other parameters")
        warn("surface: camera cam02: mask is all foreground (3 frame sets: 1, 2, 3)")  # said again: kept once
        raise ValueError("the step broke")

    def cancelled(take, out, *, params, progress, cancel, job_id, take_id, warn):
        warn("key: cam01: mask invalid in 2 frames (2, 3): black")
        cancel.wait(20)
        raise InterruptedError

    def done(take, out, *, params, progress, cancel, job_id, take_id, warn):
        warn("track: said while running")
        return {"report": {"warnings": ["track: said while running", "rig: in the report alone"]}}

    def no_warn(take, out, *, params, progress, cancel, job_id, take_id):
        return {"warnings": ["in the result"]}

    runner = JobRunner(store, takes_dir=takes, jobs_dir=jobs, heartbeat_s=0.05, stale_after_s=0.2, poll_s=0.01,
                       max_concurrent=4, handlers={"fails": fails, "cancelled": cancelled, "done": done,
                                                   "no_warn": no_warn})
    ids = {k: store.create(kind=k, take="t", steps=[k], params={}).id for k in ("fails", "cancelled", "done", "no_warn")}
    runner.start()
    try:
        wait_until(lambda: store.get(ids["cancelled"]).warnings, timeout=20, what="the cancelled job's warning")
        store.request_cancel(ids["cancelled"])
        wait_until(lambda: all(store.get(j).state in ("done", "failed", "cancelled") for j in ids.values()),
                   timeout=20, what="every job finished")
    finally:
        runner.stop()
    st = {k: store.get(j) for k, j in ids.items()}
    assert st["fails"].state == "failed" and st["fails"].error == "the step broke" and st["fails"].result is None
    assert st["fails"].warnings == ["surface: camera cam02: mask is all foreground (3 frame sets: 1, 2, 3)",
                                    f"surface: DATA/jobs/{ids['fails']} holds results of other parameters"]
    assert st["cancelled"].state == "cancelled"
    assert st["cancelled"].warnings == ["key: cam01: mask invalid in 2 frames (2, 3): black"]
    assert st["done"].state == "done" and st["done"].warnings == ["track: said while running", "rig: in the report alone"]
    assert st["no_warn"].state == "done" and st["no_warn"].warnings == ["in the result"]
    assert JobStore(tmp_path / "jobs.sqlite").get(ids["fails"]).warnings == st["fails"].warnings  # (durable)


def test_a_job_queued_again_keeps_the_warnings_of_its_earlier_attempt(tmp_path):
    """A server killed mid-job: the job queued again keeps what its first attempt said; said again by the second,
    each is kept once."""
    store = JobStore(tmp_path / "jobs.sqlite")
    j = store.create(kind="process", take="t", steps=["key"], params={})
    store.claim("dead-server")
    store.add_warnings(j.id, ["surface: first"])
    _age(store, j.id, 3600)
    assert store.requeue_stale(stale_after_s=10, max_attempts=5) == [j.id]
    assert store.claim("next-server").warnings == ["surface: first"]
    store.add_warnings(j.id, ["surface: first", "track: second"])
    store.finish(j.id, "done", result={"report": {"warnings": ["surface: first", "track: second"]}})
    assert store.get(j.id).warnings == ["surface: first", "track: second"]


def test_a_store_written_before_the_warnings_were_kept_still_loads(tmp_path):
    """A store whose jobs table has no ``warnings`` (written by an earlier version) opens: a done job's warnings are
    its report's, a failed job's none; warnings said now are kept for its jobs too, after the report's."""
    import sqlite3

    path = tmp_path / "jobs.sqlite"
    con = sqlite3.connect(path)
    con.executescript("""
        CREATE TABLE jobs (id TEXT PRIMARY KEY, kind TEXT NOT NULL, take TEXT NOT NULL, steps TEXT NOT NULL,
            params TEXT NOT NULL, state TEXT NOT NULL, created REAL NOT NULL, started REAL, finished REAL,
            heartbeat REAL, attempts INTEGER NOT NULL DEFAULT 0, error TEXT, cancel INTEGER NOT NULL DEFAULT 0,
            owner TEXT, progress TEXT NOT NULL DEFAULT '{}', done INTEGER NOT NULL DEFAULT 0,
            total INTEGER NOT NULL DEFAULT 0, result TEXT);
        CREATE TABLE events (job TEXT NOT NULL, seq INTEGER NOT NULL, time REAL NOT NULL, data TEXT NOT NULL,
            PRIMARY KEY (job, seq));
    """)
    report = {"report": {"warnings": ["surface: an old warning", 3]}}
    for jid, state, result in (("a" * 32, "done", json.dumps(report)), ("b" * 32, "failed", None),
                               ("c" * 32, "done", json.dumps({"report": {"frames": 2}}))):
        con.execute("INSERT INTO jobs (id, kind, take, steps, params, state, created, attempts, result) "
                    "VALUES (?, 'process', 't', '[\"key\"]', '{}', ?, 1.0, 1, ?)", (jid, state, result))
    con.commit()
    con.close()
    store = JobStore(path)
    assert store.get("a" * 32).warnings == ["surface: an old warning"]
    assert store.get("b" * 32).warnings == [] and store.get("c" * 32).warnings == []
    store.add_warnings("a" * 32, ["rig: a new one", "surface: an old warning"])
    assert JobStore(path).get("a" * 32).warnings == ["surface: an old warning", "rig: a new one"]
    assert store.create(kind="process", take="t", steps=["key"], params={}).warnings == []
    assert [j.id for j in store.list(state="done")] == ["a" * 32, "c" * 32]
