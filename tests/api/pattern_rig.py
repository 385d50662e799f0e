"""A two-camera rig file and a driver that films a known flat image per camera at the rig's fps,
for the API's rig and capture tests."""

from __future__ import annotations

import time

import numpy as np

from stage.drivers.base import CameraDisconnectedError, Granted
from stage.frame import Frame

RIG = """
name = "testrig"
fps = 50

[[cameras]]
id = "left"
driver = "opencv"
device = 0
width = 32
height = 24

[[cameras]]
id = "right"
driver = "opencv"
device = 1
width = 32
height = 24
"""


class PatternCamera:
    """A driver that returns a known image per camera at the requested fps."""

    def __init__(self, config, rig) -> None:
        self.camera_id = config.id
        self.w, self.h, self.fps = config.width, config.height, rig.fps
        self.value = 40 if config.id == "left" else 200
        self.i = 0
        self.t0 = None

    def open(self) -> None:
        self.t0 = time.monotonic_ns()

    def configure(self) -> Granted:
        return Granted(self.w, self.h, self.fps)

    def grab(self) -> Frame:
        if self.t0 is None:
            raise CameraDisconnectedError("not open")
        t = self.t0 + int(self.i * 1e9 / self.fps)
        delay = (t - time.monotonic_ns()) / 1e9
        if delay > 0:
            time.sleep(delay)
        img = np.full((self.h, self.w, 3), self.value, np.uint8)
        f = Frame(img, self.camera_id, self.i, t, t)
        self.i += 1
        return f

    def close(self) -> None:
        self.t0 = None
