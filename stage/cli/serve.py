"""``stage serve``: run the REST API (FastAPI + uvicorn) on a data root."""

from __future__ import annotations

import argparse

ORDER = 80


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve",
        help="run the REST API (rig, takes, calibrations, processing jobs)",
        description="Serve the REST API on a data root. OpenAPI docs at http://HOST:PORT/docs. "
        "Endpoints that change anything need the token of STAGE_API_TOKEN (Authorization: Bearer ...). "
        "Jobs are durable (DATA/jobs.sqlite): after a restart, queued jobs run and interrupted ones resume.",
    )
    p.add_argument("--host", default="127.0.0.1", help="interface to listen on (default: %(default)s)")
    p.add_argument("--port", type=int, default=8000, help="port (default: %(default)s)")
    p.add_argument("--data", default=None, help="data root (default: $STAGE_DATA or ./stage-data)")
    p.add_argument("--dask", default=None, metavar="tcp://HOST:8786",
                   help="run jobs on this Dask scheduler (workers must see the data root at the same path); "
                   "'local' starts a LocalCluster; default: a local process pool")
    p.add_argument("--workers", type=int, default=None, help="processes of the local pool (default: CPU count)")
    p.add_argument("--rig", default=None, help="rig file (default: DATA/rig.toml)")
    p.add_argument("--read-protected", action="store_true", help="require the token for reading too")
    p.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        import uvicorn
    except ImportError:
        raise ValueError("stage serve needs uvicorn: pip install uvicorn") from None
    import fake_cameras  # noqa: F401 (registers the simulated rig's "fake" driver for /rig)
    from api.app import create_app
    from api.settings import Settings

    overrides = {}
    if args.data is not None:
        overrides["data"] = args.data
    if args.dask is not None:
        overrides["dask"] = args.dask
    if args.workers is not None:
        overrides["workers"] = args.workers
    if args.rig is not None:
        overrides["rig"] = args.rig
    if args.read_protected:
        overrides["read_protected"] = True
    settings = Settings(**overrides)
    if settings.dask:
        from api.executors import dask_available

        if not dask_available():
            raise ValueError("--dask needs Dask: pip install 'dask[distributed]' (the [dask] extra)")
    if settings.api_token is None and not settings.allow_anonymous_writes:
        print("stage serve: warning: STAGE_API_TOKEN is not set; every change (capture, import, jobs) is refused")
    if args.port < 0 or args.port > 65535:
        raise ValueError(f"--port must be in 0..65535, got {args.port}")
    app = create_app(settings)
    print(f"stage serve: data root {settings.data}; jobs on {'dask ' + settings.dask if settings.dask else 'a local process pool'}; "
          f"docs at http://{args.host}:{args.port}/docs", flush=True)
    uvicorn.run(app, host=args.host, port=args.port, log_level=args.log_level, timeout_graceful_shutdown=10)
    return 0
