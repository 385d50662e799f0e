"""Rig files for the simulated rig (``driver = "fake"``), for ``stage demo``, tests and benchmarks."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stage.rig import Rig, Volume, parse_rig

__all__ = ["simulated_rig_dict", "simulated_rig", "write_simulated_rig", "dumps_toml", "thin_tail_setup"]


def simulated_rig_dict(
    n_cameras: int = 4,
    *,
    subject: str = "starfish",
    fps: float = 30.0,
    frames: int = 30,
    size: tuple[int, int] = (640, 480),
    seed: int = 0,
    noise: float = 2.0,
    clock_offsets_ms: float = 20.0,
    jitter_ms: float = 0.5,
    drop_rate: float = 0.0,
    depth: bool = False,
    store: str = "raw",
    dome_cameras: int | None = None,
    name: str = "simulated",
    volume=None,
) -> dict:
    """A rig dictionary (as read from TOML) of ``n_cameras`` simulated cameras.

    Parameters
    ----------
    n_cameras : int
        Cameras in the rig file (1..``dome_cameras``); they are cameras ``0..n-1`` of the dome.
    subject : str
        What the rig films (``fake_cameras.device.Simulation.subject``).
    clock_offsets_ms : float
        Each camera's clock offset is drawn uniformly from +-this (seeded).
    jitter_ms, drop_rate, depth, store
        Copied to every camera.
    dome_cameras : int, optional
        Cameras of the simulated dome (default ``max(4, n_cameras)``).
    volume : stage.rig.Volume, optional
        The capture volume (default ``Volume()``: centre (0, 0, 375), 750 mm cube).

    Returns
    -------
    dict
        Valid for :func:`stage.rig.parse_rig`.
    """
    dome = max(4, n_cameras) if dome_cameras is None else int(dome_cameras)
    if not 1 <= n_cameras <= dome:
        raise ValueError(f"n_cameras must be within 1..{dome} (the dome's cameras), got {n_cameras!r}")
    w, h = (int(s) for s in size)
    vol = Volume() if volume is None else volume
    rng = np.random.default_rng(seed)
    cams = []
    for i in range(n_cameras):
        c = {
            "id": f"cam{i:02d}",
            "driver": "fake",
            "index": i,
            "width": w,
            "height": h,
            "clock_offset_ms": round(float(rng.uniform(-clock_offsets_ms, clock_offsets_ms)), 3),
            "jitter_ms": float(jitter_ms),
            "drop_rate": float(drop_rate),
            "store": store,
        }
        if depth:
            c["depth"] = True
        cams.append(c)
    data = {
        "name": name,
        "fps": float(fps),
        "volume": {"center": [float(v) for v in vol.center], "size": [float(v) for v in vol.size]},
        "backdrop": {"key_mode": "chroma", "color": "green"},
        "simulation": {"subject": subject, "n_cameras": dome, "frames": int(frames), "seed": int(seed), "noise": float(noise)},
        "cameras": cams,
    }
    parse_rig(data, source="simulated rig")  # validate now: errors name the parameter's key
    return data


def simulated_rig(n_cameras: int = 4, **kw) -> Rig:
    """:func:`simulated_rig_dict`, validated into a :class:`stage.rig.Rig`."""
    return parse_rig(simulated_rig_dict(n_cameras, **kw), source="simulated rig")


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise ValueError(f"cannot write {type(v).__name__} to TOML")


def dumps_toml(data: dict) -> str:
    """TOML text of a rig dictionary (scalars, arrays, tables, arrays of tables)."""
    def is_table(v) -> bool:
        return isinstance(v, dict) or (isinstance(v, list) and bool(v) and isinstance(v[0], dict))

    lines = [f"{k} = {_value(v)}" for k, v in data.items() if not is_table(v)]
    for k, v in data.items():
        if isinstance(v, dict):
            lines += ["", f"[{k}]"] + [f"{kk} = {_value(vv)}" for kk, vv in v.items()]
    for k, v in data.items():
        if isinstance(v, list) and v and isinstance(v[0], dict):
            for item in v:
                lines += ["", f"[[{k}]]"] + [f"{kk} = {_value(vv)}" for kk, vv in item.items()]
    return "\n".join(lines) + "\n"


def write_simulated_rig(path: str | Path, n_cameras: int = 4, **kw) -> Path:
    """Write a simulated rig TOML file (see :func:`simulated_rig_dict`); returns the path."""
    p = Path(path)
    p.write_text(dumps_toml(simulated_rig_dict(n_cameras, **kw)), encoding="utf-8")
    return p


def thin_tail_setup(size: tuple[int, int] = (480, 360)) -> dict:
    """Keywords of :func:`fake_cameras.take.simulate_take` for the thin-limb case.

    The ``tailed_quadruped`` at 1.6x (about 840 mm long; its 144 mm tail stays 36 -> 16 mm
    thick) in a 900 x 600 x 640 mm capture volume, filmed by ten 480x360 cameras of a dome
    framed on the animal (fitted to a 640 x 360 x 480 mm box): a pixel covers about 2.6 mm
    at the subject (median over the cameras), so the tail's thin end is about 6 pixels wide,
    and the subject's box is about 880 mm long (a 96-voxel grid along it has 9.2 mm voxels).
    """
    from fake_cameras.dome import make_dome

    framing = Volume(center=(0.0, 0.0, 240.0), size=(640.0, 360.0, 480.0))
    return dict(
        subject="tailed_quadruped", scale=1.6,
        volume=Volume(center=(0.0, 0.0, 320.0), size=(900.0, 600.0, 640.0)),
        calibration=make_dome(10, size=size, volume=framing, seed=0),
    )
