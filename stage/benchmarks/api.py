"""``stage bench api``: the REST API under load, and a take's frames/s on the local pool vs Dask.

1. Starts ``stage serve`` on loopback with a temporary data root, imports a take,
   starts a job, and while it runs a *second process* (an asyncio httpx client loop,
   bounded in requests and time) hammers ``GET /jobs/{id}`` with N concurrent clients:
   requests per second, p50/p99 latency, errors.
2. Processes the same take through the local process pool and through a Dask
   ``LocalCluster`` with 2 workers, in this run: frames per second of each.

The work is :func:`pipeline.process.process_take` on a simulated take when
both exist; otherwise a synthetic CPU-bound stand-in with the same contract
(:func:`synthetic_process`), and the output says so.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

NAME = "api"
HELP = "REST API: job-status requests/s and p50/p99 latency under 50 concurrent clients; frames/s local pool vs Dask"

ROOT = Path(__file__).resolve().parents[2]
TOKEN = "bench-token"

__all__ = ["NAME", "HELP", "add_arguments", "run", "synthetic_process", "load_client"]


# -- the work --------------------------------------------------------------------------------------
def _synthetic_frame(take: str, index: int, work: int) -> float:
    """One frame's CPU work: reads the take's frame set and does ``work`` rounds of array math."""
    from stage.store import TakeReader

    with TakeReader(take) as r:
        imgs = [img for img in r.frame_set(index).values() if img is not None]
    acc = 0.0
    for img in imgs:
        a = img.astype(np.float32)
        for _ in range(work):
            a = np.sqrt(a * 1.0001 + 1.0)
        acc += float(a.mean())
    return acc


def synthetic_process(take: str | Path, out: str | Path, *, steps: Sequence[str] = ("key", "surface", "spine"),
                      params: Any = None, executor: Any = None, progress: Callable[[str, int, int], None] | None = None,
                      cancel: threading.Event | None = None) -> dict:
    """A stand-in for ``process_take`` (same contract): per-frame work fanned out, persisted, resumable."""
    import concurrent.futures as cf

    from stage.store import TakeReader

    out = Path(out)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    with TakeReader(take) as r:
        n = len(r)
    work = int((params or {}).get("work", 20)) if isinstance(params, dict) else 20
    todo = [i for i in range(n) if not (out / "frames" / f"{i:06d}.json").is_file()]
    done = n - len(todo)
    if progress:
        progress("surface", done, n)
    ex = executor or cf.ThreadPoolExecutor(1)
    futs = {ex.submit(_synthetic_frame, str(take), i, work): i for i in todo}
    for f in cf.as_completed(futs):
        i = futs[f]
        (out / "frames" / f"{i:06d}.json").write_text(json.dumps({"value": f.result()}))
        done += 1
        if progress:
            progress("surface", done, n)
        if cancel is not None and cancel.is_set():
            for g in futs:
                g.cancel()
            return {"cancelled": True}
    spine = {"frames": [json.loads((out / "frames" / f"{i:06d}.json").read_text()) for i in range(n)]}
    (out / "spine.json").write_text(json.dumps(spine, sort_keys=True))
    return {"frames": n}


def _real_work_available() -> tuple[bool, str]:
    try:
        import pipeline.process  # noqa: F401
    except ImportError as exc:
        return False, f"pipeline.process is not available ({exc})"
    try:
        from fake_cameras.take import simulate_take  # noqa: F401
    except ImportError as exc:
        return False, f"fake_cameras.take is not available ({exc})"
    return True, ""


# -- load generator (runs in a second process) ----------------------------------------------------
async def _load(url: str, clients: int, duration_s: float, max_requests: int, token: str | None) -> dict:
    import httpx

    lat: list[float] = []
    errors = 0
    codes: dict[int, int] = {}
    deadline = time.perf_counter() + duration_s
    budget = [max_requests]
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)

    async def one(client: httpx.AsyncClient) -> None:
        nonlocal errors
        while time.perf_counter() < deadline and budget[0] > 0:
            budget[0] -= 1
            t0 = time.perf_counter()
            try:
                r = await client.get(url, headers=headers)
                codes[r.status_code] = codes.get(r.status_code, 0) + 1
                if r.status_code != 200:
                    errors += 1
            except httpx.HTTPError:
                errors += 1
                continue
            lat.append(time.perf_counter() - t0)

    async with httpx.AsyncClient(limits=limits, timeout=30.0) as client:
        t0 = time.perf_counter()
        await asyncio.gather(*(one(client) for _ in range(clients)))
        elapsed = time.perf_counter() - t0
    a = np.asarray(lat) * 1e3 if lat else np.zeros(1)
    return {"requests": len(lat), "errors": errors, "codes": codes, "elapsed_s": elapsed,
            "rps": len(lat) / elapsed if elapsed > 0 else 0.0,
            "p50_ms": float(np.percentile(a, 50)), "p99_ms": float(np.percentile(a, 99)), "max_ms": float(a.max())}


def load_client(argv: list[str] | None = None) -> int:
    """Entry point of the load process: ``python -m stage.benchmarks.api URL CLIENTS DURATION MAX``."""
    p = argparse.ArgumentParser(prog="stage.benchmarks.api")
    p.add_argument("url")
    p.add_argument("clients", type=int)
    p.add_argument("duration", type=float)
    p.add_argument("max_requests", type=int)
    a = p.parse_args(argv)
    res = asyncio.run(_load(a.url, a.clients, a.duration, a.max_requests, os.environ.get("STAGE_API_TOKEN")))
    print(json.dumps(res))
    return 0


# -- the benchmark ---------------------------------------------------------------------------------
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--clients", type=int, default=50, help="concurrent clients (default: %(default)s)")
    p.add_argument("--duration", type=float, default=5.0, help="seconds of load (default: %(default)s)")
    p.add_argument("--max-requests", type=int, default=50_000, help="stop the load after this many requests")
    p.add_argument("--frames", type=int, default=12, help="frames of the simulated take (default: %(default)s)")
    p.add_argument("--cameras", type=int, default=6, help="cameras of the simulated take (default: %(default)s)")
    p.add_argument("--size", default="160x120", help="image size WxH (default: %(default)s)")
    p.add_argument("--workers", type=int, default=2, help="local pool processes / Dask workers (default: %(default)s)")
    p.add_argument("--synthetic", action="store_true", help="use the synthetic work even if pipeline.process exists")
    p.add_argument("--skip-dask", action="store_true", help="only the local pool")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _make_take(path: Path, *, frames: int, cameras: int, size: tuple[int, int]) -> None:
    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take

    sim = simulate_take("starfish", n_cameras=max(4, cameras), frames=frames, size=size, seed=0)
    record_take(sim, path)


def _serve(data: Path, port: int, work: str, workers: int) -> subprocess.Popen:
    import httpx

    env = dict(os.environ, STAGE_API_TOKEN=TOKEN, STAGE_WORK=work,
               PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-m", "stage", "-q", "serve", "--port", str(port), "--data", str(data),
                             "--workers", str(workers), "--log-level", "warning"], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 60:
        if proc.poll() is not None:
            raise RuntimeError(f"stage serve exited: {proc.stderr.read().decode(errors='replace')[-2000:]}")
        try:
            if httpx.get(f"http://127.0.0.1:{port}/health", timeout=1).status_code == 200:
                return proc
        except httpx.HTTPError:
            time.sleep(0.2)
    proc.kill()
    raise RuntimeError("stage serve did not start in 60 s")


def _cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of one process (Linux /proc), or None."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def _frames_per_s(take: Path, fn: Callable, handle: Any, params: Any, tmp: Path, label: str) -> tuple[float, float]:
    from stage.store import TakeReader

    with TakeReader(take) as r:
        n = len(r)
    out = tmp / f"out-{label}"
    t0 = time.perf_counter()
    fn(take, out, params=params, executor=handle.executor)
    dt = time.perf_counter() - t0
    return n / dt, dt


def _throughput(take: Path, tmp: Path, real: bool, args: argparse.Namespace) -> None:
    """Frames/s of the same take and work through the local pool and a Dask LocalCluster."""
    from api.executors import dask_available, dask_executor, local_pool

    if real:
        from pipeline.process import process_take as fn

        params = None
    else:
        fn, params = synthetic_process, {"work": 200}
    pool = local_pool(args.workers)
    try:
        pool.executor.submit(int, 0).result()  # start the workers before timing
        fps, dt = _frames_per_s(take, fn, pool, params, tmp, "pool")
        print(f"local process pool ({args.workers} workers): {fps:.2f} frames/s ({dt:.1f} s)")
    finally:
        pool.close()
    if args.skip_dask:
        print("dask: skipped (--skip-dask)")
    elif not dask_available():
        print("dask: NOT INSTALLED - the optional extra [dask] (pip install 'dask[distributed]') is missing; no Dask figure")
    else:
        dh = dask_executor("local", n_workers=args.workers)
        try:
            dh.executor.submit(int, 0).result()
            fps, dt = _frames_per_s(take, fn, dh, params, tmp, "dask")
            print(f"dask LocalCluster ({args.workers} workers): {fps:.2f} frames/s ({dt:.1f} s)")
        finally:
            dh.close()


def _status_load(take: Path, tmp: Path, work: str, real: bool, args: argparse.Namespace) -> None:
    """Job-status requests from a second process while a job runs in ``stage serve``."""
    import httpx

    data = tmp / "data"
    port = _free_port()
    srv = _serve(data, port, work, args.workers)
    base = f"http://127.0.0.1:{port}"
    auth = {"Authorization": f"Bearer {TOKEN}"}
    try:
        r = httpx.put(f"{base}/takes/bench", content=take.read_bytes(),
                      headers={**auth, "Content-Type": "application/x-hdf5"}, timeout=120)
        r.raise_for_status()
        params = {} if real else {"work": 4000}  # long enough to still run during the load
        r = httpx.post(f"{base}/jobs", json={"take": "bench", "parameters": params}, headers=auth, timeout=30)
        r.raise_for_status()
        jid = r.json()["id"]
        cpu0 = _cpu_s(srv.pid)
        load = subprocess.run(
            [sys.executable, "-m", "stage.benchmarks.api", f"{base}/jobs/{jid}", str(args.clients),
             str(args.duration), str(args.max_requests)],
            cwd=ROOT, capture_output=True, text=True, timeout=args.duration + 120,
            env=dict(os.environ, PYTHONPATH=str(ROOT)),
        )
        if load.returncode != 0:
            raise RuntimeError(f"load process failed: {load.stderr[-2000:]}")
        res = json.loads(load.stdout.strip().splitlines()[-1])
        cpu1 = _cpu_s(srv.pid)
        st = httpx.get(f"{base}/jobs/{jid}", timeout=10).json()
        httpx.post(f"{base}/jobs/{jid}/cancel", headers=auth, timeout=10)
        print(f"GET /jobs/{{id}} with {args.clients} concurrent clients (second process, loopback) while the job "
              f"runs (job {st['state']}, {st['done']}/{st['total']} frame-steps done when the load ended):")
        print(f"  {res['rps']:.0f} requests/s over {res['elapsed_s']:.1f} s ({res['requests']} requests, "
              f"{res['errors']} errors)  p50 {res['p50_ms']:.1f} ms  p99 {res['p99_ms']:.1f} ms  max {res['max_ms']:.1f} ms")
        if cpu0 is not None and cpu1 is not None and res["requests"]:
            print(f"  server process CPU: {1e3 * (cpu1 - cpu0) / res['requests']:.2f} ms per request "
                  f"(its own threads, job thread included; pool workers excluded)")
    finally:
        srv.terminate()
        try:
            srv.wait(20)
        except subprocess.TimeoutExpired:
            srv.kill()


def run(args: argparse.Namespace) -> int:
    try:
        import httpx  # noqa: F401
    except ImportError:
        print("stage bench api: needs httpx (pip install httpx)")
        return 2
    import logging

    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "error")  # quiet workers too (read when dask is imported)
    for name in ("distributed", "tornado", "asyncio"):
        logging.getLogger(name).setLevel(logging.CRITICAL)  # cluster start/stop chatter
    w, _, h = args.size.partition("x")
    size = (int(w), int(h))
    if args.clients < 1 or args.duration <= 0 or args.frames < 1 or args.workers < 1:
        raise ValueError("--clients, --duration, --frames and --workers must be positive")
    real, why = _real_work_available()
    if args.synthetic:
        real, why = False, "--synthetic"
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at start")
    with tempfile.TemporaryDirectory(prefix="stage-bench-api-") as tmpd:
        tmp = Path(tmpd)
        take = tmp / "take.h5"
        t0 = time.perf_counter()
        _make_take(take, frames=args.frames, cameras=args.cameras, size=size)
        print(f"take: {args.frames} frames x {args.cameras} cameras {args.size} ({time.perf_counter() - t0:.1f} s to make)")
        print("work: " + ("pipeline.process.process_take" if real else f"synthetic stand-in ({why})"))
        try:
            _throughput(take, tmp, real, args)
        except ImportError as exc:
            if not real:
                raise
            real = False
            print(f"process_take cannot run yet ({exc}); using the synthetic stand-in")
            _throughput(take, tmp, real, args)
        work = "pipeline.process:process_take" if real else "stage.benchmarks.api:synthetic_process"
        _status_load(take, tmp, work, real, args)
    return 0


if __name__ == "__main__":  # the load process
    sys.exit(load_client())
