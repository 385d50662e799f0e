"""SIGKILL of ``stage process`` at three moments: 5 s later no process it started is alive (its
pool's workers, the forkserver, the resource tracker).

The command runs under a small supervisor that makes itself a child subreaper
(``PR_SET_CHILD_SUBREAPER``), so every orphan of the killed command becomes the supervisor's
child and can be counted, however deep it was started."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_CHILD_SUBREAPER is Linux's")]

SUPERVISOR = textwrap.dedent(r'''
    import ctypes, json, os, signal, subprocess, sys, time
    from pathlib import Path
    ctypes.CDLL(None, use_errno=True).prctl(36, 1, 0, 0, 0)  # PR_SET_CHILD_SUBREAPER
    take, out, moment = sys.argv[1], Path(sys.argv[2]), sys.argv[3]

    def descendants():
        kids = {}
        for d in Path("/proc").iterdir():
            if d.name.isdigit():
                try:
                    stat = (d / "stat").read_bytes().rsplit(b")", 1)[1].split()
                except OSError:
                    continue
                if stat[0] != b"Z":
                    kids.setdefault(int(stat[1]), []).append(int(d.name))
        found, todo = [], [os.getpid()]
        while todo:
            for c in kids.get(todo.pop(), []):
                found.append(c)
                todo.append(c)
        return found

    cmd = [sys.executable, "-m", "stage", "-q", "process", take, "--out", str(out), "--workers", "2"]
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 120 and p.poll() is None:
        n = len(descendants())
        if moment == "pool" and n >= 3:  # the forkserver and a worker have started
            break
        if moment == "key" and any(out.parent.glob("*.derived.h5")) or moment == "key" and (out / "frames").is_dir():
            break
        if moment == "surface" and any((out / "meshes").glob("frame_*.ply")):
            break
        time.sleep(0.02)
    running = p.poll() is None
    before = len(descendants())
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    time.sleep(5.0)
    left = descendants()
    while True:  # reap what exited
        try:
            if os.waitpid(-1, os.WNOHANG)[0] == 0:
                break
        except ChildProcessError:
            break
    info = [Path(f"/proc/{q}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")[:120] for q in left]
    print(json.dumps({"killed_running": running, "before": before, "left": info}))
    for q in left:
        os.kill(q, signal.SIGKILL)
''')


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    import os

    d = tmp_path_factory.mktemp("kill")
    os.environ.setdefault("CAPTURE_STAGE_CACHE", str(d / "cache"))
    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take

    return record_take(simulate_take("starfish", n_cameras=4, frames=6, size=(128, 96), seed=2), d / "s.h5")


@pytest.mark.parametrize("moment", ["pool", "key", "surface"])
def test_a_killed_process_command_leaves_no_process_behind(take, tmp_path, moment):
    res = subprocess.run([sys.executable, "-c", SUPERVISOR, str(take), str(tmp_path / "r"), moment],
                         capture_output=True, text=True, timeout=180)
    assert res.returncode == 0, res.stderr[-2000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["killed_running"] and out["before"] >= 1, out
    assert out["left"] == [], out
