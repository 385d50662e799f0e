"""aniposelib side of ``stage bench calib``, run in aniposelib's own virtual environment.

Not a benchmark (no ``run``): ``stage/benchmarks/calib.py`` starts it as
``ANIPOSE_PYTHON -I _anipose_worker.py IN.npz OUT.json`` so that aniposelib and the
OpenCV build it wants never enter the project's environment. It imports only numpy
and aniposelib (never the project).

IN.npz holds ``names`` (C,) str, ``sizes`` (C, 2) int, ``board`` (a JSON string:
``type``, ``corners`` or ``squares``, ``square_mm``, ``marker_mm``, ``marker_bits``,
``dict_size``) and per camera ``i``: ``corners_i`` (M, 2) float, ``ids_i`` (M,) int,
``view_i`` (M,) int (which detection the corner belongs to) and ``frame_i`` (V,) int
(that detection's frame number). OUT.json gets ``seconds`` (``calibrate_rows`` only),
``error`` (aniposelib's final reprojection error), ``versions`` and ``cameras``
(``{"cam_0": Camera.get_dict(), ...}``, aniposelib's TOML layout) — or ``failed``.

Setup (once)::

    python3.11 -m venv ~/.cache/capture-stage/anipose-venv
    ~/.cache/capture-stage/anipose-venv/bin/pip install --no-deps aniposelib
    ~/.cache/capture-stage/anipose-venv/bin/pip install opencv-contrib-python-headless numba pandas scipy toml tqdm jax
"""

from __future__ import annotations

import contextlib
import io
import json
import sys
import time
import traceback


def _rows(data, n_cams: int):
    import numpy as np

    rows = []
    for i in range(n_cams):
        corners = data[f"corners_{i}"].astype(np.float32)
        ids = data[f"ids_{i}"].astype(np.int32)
        view = data[f"view_{i}"]
        frames = data[f"frame_{i}"]
        r = []
        for v, frame in enumerate(frames):
            sel = view == v
            r.append({"framenum": (0, int(frame)), "corners": corners[sel].reshape(-1, 1, 2),
                      "ids": ids[sel].reshape(-1, 1)})
        rows.append(r)
    return rows


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print("usage: _anipose_worker.py IN.npz OUT.json", file=sys.stderr)
        return 2
    src, dst = argv
    out: dict = {}
    try:
        import aniposelib
        import aniposelib.boards as ab
        import cv2
        import numpy as np
        from aniposelib.cameras import CameraGroup

        data = np.load(src, allow_pickle=False)
        names = [str(n) for n in data["names"]]
        sizes = data["sizes"]
        b = json.loads(str(data["board"]))
        if b["type"] == "chessboard":
            board = ab.Checkerboard(int(b["corners"][0]), int(b["corners"][1]), square_length=float(b["square_mm"]))
        else:
            board = ab.CharucoBoard(int(b["squares"][0]), int(b["squares"][1]), square_length=float(b["square_mm"]),
                                    marker_length=float(b["marker_mm"]), marker_bits=int(b["marker_bits"]),
                                    dict_size=int(b["dict_size"]))
        rows = _rows(data, len(names))
        cg = CameraGroup.from_names(names)
        for cam, size in zip(cg.cameras, sizes):
            cam.set_size((int(size[0]), int(size[1])))
        chatter = io.StringIO()  # calibrate_rows prints unconditionally
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(chatter):
            error = cg.calibrate_rows(rows, board, init_intrinsics=True, init_extrinsics=True, verbose=False)
        out["seconds"] = time.perf_counter() - t0
        out["error"] = float(error)
        out["cameras"] = {f"cam_{i}": cam.get_dict() for i, cam in enumerate(cg.cameras)}
        out["versions"] = {"aniposelib": getattr(aniposelib, "__version__", "?"), "opencv": cv2.__version__,
                           "numpy": np.__version__, "python": sys.version.split()[0]}
    except Exception as exc:  # noqa: BLE001 - report any failure to the parent process
        out = {"failed": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
    with open(dst, "w", encoding="utf-8") as fh:
        json.dump(out, fh)
    return 0 if "failed" not in out else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
