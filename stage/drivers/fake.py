"""The ``fake`` driver: a camera of the simulated rig (:mod:`fake_cameras.device`)."""

from __future__ import annotations

from fake_cameras.device import FakeCamera, take_for_rig

__all__ = ["FakeCamera", "take_for_rig"]
