"""Paced test cameras for the capture tests (also imported by the child process they kill): frame k
at t0 + k / fps on each camera's own clock, with offsets, jitter, dropped frames and disconnects."""

from __future__ import annotations

import time

import numpy as np

from stage.drivers.base import CameraDisconnectedError, Granted
from stage.frame import Frame
from stage.rig import parse_rig

W, H = 160, 120


def pattern(cam: int, k: int) -> np.ndarray:
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 0] = cam * 50
    img[..., 1] = k % 256
    img[..., 2] = (k // 256) % 256
    return img


class PacedCamera:
    """A camera that delivers frame k at t0 + k / fps on its own clock (offset, jitter),
    skipping frames listed in ``drop`` (sequence gaps) and disconnecting after ``disconnect_after``."""

    def __init__(self, camera_id, cam, fps, *, offset_ns=0, jitter_ms=0.0, drop=(), disconnect_after=None, seed=0, start=None):
        self.camera_id, self.cam, self.fps = camera_id, cam, fps
        self.offset_ns, self.jitter_ms, self.drop = offset_ns, jitter_ms, set(drop)
        self.disconnect_after = disconnect_after
        self.rng = np.random.default_rng(seed)
        self.k = 0
        self.start = start if start is not None else {}  # shared by the cameras of one rig: same exposure instants
        self.opened = self.closed = False

    def open(self):
        self.opened = True

    def configure(self):
        return Granted(W, H, self.fps)

    def grab(self):
        t0 = self.start.setdefault("t0", time.monotonic_ns())
        while True:
            k = self.k
            self.k += 1
            if self.disconnect_after is not None and k >= self.disconnect_after:
                raise CameraDisconnectedError(f"camera {self.camera_id}: USB device went away")
            due = t0 + int(k * 1e9 / self.fps)
            wait = due - time.monotonic_ns()
            if wait > 0:
                time.sleep(wait / 1e9)
            if k in self.drop:
                continue
            dev = due + self.offset_ns + int(self.rng.normal(0, self.jitter_ms * 1e6))
            return Frame(pattern(self.cam, k), self.camera_id, k, dev, time.monotonic_ns())

    def close(self):
        self.closed = True


def rig_for(ids, fps=60.0):
    cams = [{"id": c, "driver": "opencv", "device": 0, "width": W, "height": H} for c in ids]
    return parse_rig({"name": "t", "fps": fps, "cameras": cams})


def make_drivers(ids, fps=60.0, **per_cam):
    start: dict = {}
    return {
        c: PacedCamera(c, i, fps, offset_ns=(i * 7_777_777_777) % 10**10, jitter_ms=0.3, seed=i, start=start, **per_cam.get(c, {}))
        for i, c in enumerate(ids)
    }
