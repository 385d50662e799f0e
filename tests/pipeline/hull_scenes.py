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


def take_with_failed_masks(path):
    """A small simulated starfish take (4 cameras, 6 frame sets, 160x120) holding the simulator's masks, but camera
    ``cam02``'s all foreground in frame sets 1, 2 and 3 (a keying gone wrong) and every camera's empty in frame set
    4 (no subject): the take's path."""
    from fake_cameras.record import record_take
    from stage.store import write_masks

    sim = simulate_take("starfish", n_cameras=4, frames=6, size=(160, 120), seed=3)
    take = record_take(sim, path)
    for c, cam in enumerate(sim.calibration.cameras):
        m = sim.masks[:, c].copy()
        if cam.name == "cam02":
            m[1:4] = True
        m[4] = False
        write_masks(take, cam.name, m)
    return take


#: what the surface step says of :func:`take_with_failed_masks`, once per kind of message
FAILED_MASKS_SAID = ["surface: camera cam02: mask is all foreground (keying failed?); ignored for this frame "
                     "(3 frame sets: 1, 2, 3)",
                     "surface: no foreground in any camera's mask: the frame is empty (1 frame set: 4)"]
