"""A control room served in-process for the tests (:class:`LiveServer`): ``create_app`` over a running
stage session, uvicorn on a free port in a thread."""

from __future__ import annotations

import threading
import time
from pathlib import Path

from api.app import create_app
from api.control import ControlRoom
from api.settings import Settings
from stage.session import StageSession

TOKEN = "control-token"


class LiveServer:
    """``create_app`` with a control room, served by uvicorn on a free port in a thread."""

    def __init__(self, tmp: Path, session: StageSession, *, read_protected: bool = False) -> None:
        import uvicorn

        from tests.api.served import free_port

        settings = Settings(data=tmp / "data", api_token=TOKEN, read_protected=read_protected, workers=1)
        self.room = ControlRoom(session.open(), preview_fps=10.0)
        self.app = create_app(settings, control=self.room, start_runner=False)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.server = uvicorn.Server(uvicorn.Config(self.app, host="127.0.0.1", port=self.port, log_level="warning"))
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.takes = settings.takes_dir

    def __enter__(self) -> "LiveServer":
        self.thread.start()
        t0 = time.monotonic()
        while not self.server.started:
            if time.monotonic() - t0 > 20:
                raise RuntimeError("the server did not start")
            time.sleep(0.05)
        return self

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(30)
        assert self.room.session.closed  # the app closed the session at shutdown
