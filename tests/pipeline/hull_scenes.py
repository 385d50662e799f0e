"""Scenes the reconstruction tests share (hull, surface, TSDF): the analytic dome of
:mod:`tests.pipeline.simrig` and one frame of the simulated dome, each built once per process."""

from __future__ import annotations

from functools import lru_cache

from fake_cameras.take import simulate_take
from pipeline.volume import Grid, grid_from_volume
from stage.rig import Volume
from tests.pipeline import simrig


@lru_cache(maxsize=None)
def analytic():
    """4 distorted cameras around a capsule creature, exact silhouettes by sphere tracing."""
    cal = simrig.dome(6, size=(96, 72), seed=3)
    creature = simrig.Creature()
    masks, depth = simrig.render(cal, creature.sdf)
    return cal, creature, masks, depth


@lru_cache(maxsize=None)
def sim_take():
    """One frame of the simulated dome (fake_cameras renderer), ground-truth masks."""
    return simulate_take("starfish", n_cameras=8, frames=1, size=(160, 120), seed=1, depth=True)


def sim_grid(res: int = 48) -> Grid:
    return grid_from_volume(Volume().bounds, res)
