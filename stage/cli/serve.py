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
        "Jobs are durable (DATA/jobs.sqlite): after a restart, queued jobs run and interrupted ones resume. "
        "With a rig file (--rig, or DATA/rig.toml) its cameras are opened once and keep running: the control "
        "room at http://HOST:PORT/ui/stage shows them live, records takes from them, guides a board "
        "calibration (--board) and draws a live 3-D preview.",
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
    p.add_argument("--no-cameras", action="store_true",
                   help="do not open the rig's cameras (no stage session, no control room at /ui/stage)")
    p.add_argument("--preview-fps", type=float, default=5.0,
                   help="frames per second of each camera's live preview (default: %(default)s)")
    p.add_argument("--preview-width", type=int, default=320,
                   help="previews are downscaled to at most this width in pixels (default: %(default)s)")
    p.add_argument("--board", default=None, metavar="BOARD.toml",
                   help="the calibration board of the control room's board sessions")
    p.add_argument("--calibration", default=None, metavar="CAL",
                   help="calibration of the rig for the live 3-D preview (default: the simulated rig's own)")
    p.add_argument("--no-live3d", action="store_true", help="no live 3-D preview")
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
    control = _open_stage(args, settings)
    try:
        app = create_app(settings, control=control)
    except BaseException:
        if control is not None:
            control.close()
            control.session.close()
        raise
    print(f"stage serve: data root {settings.data}; jobs on {'dask ' + settings.dask if settings.dask else 'a local process pool'}; "
          f"docs at http://{args.host}:{args.port}/docs"
          + (f"; control room at http://{args.host}:{args.port}/ui/stage" if control is not None else ""), flush=True)
    config = uvicorn.Config(app, host=args.host, port=args.port, log_level=args.log_level, timeout_graceful_shutdown=10)
    _server_class()(config, control).run()
    return 0


def _open_stage(args: argparse.Namespace, settings):
    """The stage session and its control room when there is a rig (None otherwise)."""
    if args.no_cameras or not settings.rig_path.is_file():
        if args.rig is not None and not args.no_cameras:
            raise FileNotFoundError(f"--rig: {args.rig} not found")
        return None
    if not args.preview_fps > 0 or args.preview_fps > 60:
        raise ValueError(f"--preview-fps must be in (0, 60], got {args.preview_fps}")
    if args.preview_width < 16:
        raise ValueError(f"--preview-width must be >= 16, got {args.preview_width}")
    from api.control import ControlRoom
    from api.live3d import Live3D
    from stage.discovery import check_bus_load, discover, rig_camera_loads
    from stage.rig import load_rig
    from stage.session import StageSession

    rig = load_rig(settings.rig_path)
    board = calibration = None
    if args.board is not None:
        from calib.boards import load_board

        board = load_board(args.board)
    if args.calibration is not None:
        from calib.formats import read_calibration

        calibration = read_calibration(args.calibration)
    buses = []
    if any(c.driver != "fake" for c in rig.cameras):
        inv = discover()
        loads, _ = rig_camera_loads(rig, inv)
        buses = check_bus_load(loads, inv.bus_speeds)
        for rep in buses:
            if rep.warning():
                print(f"stage serve: warning: {rep.warning()}")
    session = StageSession(rig, settings.takes_dir, bus_loads=buses)
    print(f"stage serve: opening the {len(rig.cameras)} cameras of rig {rig.name!r}...", flush=True)
    session.open()
    for cid, live in session.cameras.items():
        if live.state != "running":
            print(f"stage serve: warning: camera {cid}: {live.error}")
    room = ControlRoom(session, board=board, calibration=calibration, preview_width=args.preview_width,
                       preview_fps=args.preview_fps)
    if not args.no_live3d:
        room.live3d = Live3D(room).start()
    return room


def _server_class():
    """uvicorn.Server with the control room's shutdown (uvicorn is imported only when serving)."""
    import uvicorn

    class Server(uvicorn.Server):
        """uvicorn's server; on Ctrl-C / SIGTERM the control room's preview streams end first, so that
        the graceful shutdown does not wait for browsers that would watch forever."""

        def __init__(self, config, control) -> None:
            super().__init__(config)
            self.control = control

        def handle_exit(self, sig, frame) -> None:
            if self.control is not None:
                self.control.closing.set()
            super().handle_exit(sig, frame)

    return Server
