"""Calibration file formats: aniposelib TOML, caliscope TOML, OpenCV FileStorage YAML and XML,
Qualisys ``.qca.txt``, Middlebury ``*_par.txt``, JSON, COLMAP text, nerfstudio ``transforms.json``.

``read_calibration(path)`` detects the format from the name (and content);
``write_calibration(calib, path, format=...)`` writes one.

aniposelib TOML (what ``aniposelib.cameras.CameraGroup.dump`` writes)::

    [cam_0]
    name = "cam00"
    size = [640, 480]                 # width, height
    matrix = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
    distortions = [k1, k2, p1, p2, k3]
    rotation = [rx, ry, rz]           # Rodrigues, world -> camera
    translation = [tx, ty, tz]        # world -> camera, board units
    [metadata]
    units = "mm"                      # ours; aniposelib ignores unknown metadata

OpenCV FileStorage YAML or XML (``cv2.FileStorage``, the same nodes in either syntax):
``units``, ``camera_count`` and one map ``camera_<i>`` per camera with ``name``,
``image_width``, ``image_height``, ``K`` (3x3), ``dist`` (1x5), ``R`` (3x3, world ->
camera), ``T`` (3x1). Other dialects that read:

* a single-camera file written by OpenCV's ``calibration`` sample (``camera_matrix``,
  ``distortion_coefficients``, ``image_width``, ``image_height``): one camera at the origin;
* EasyMocap's pair ``intri.yml`` (``names``, ``K_<name>``, ``dist_<name>``) and
  ``extri.yml`` (``R_<name>`` Rodrigues or ``Rot_<name>`` matrix, ``T_<name>``, world ->
  camera, metres) beside it; either file may be named, the other is read from beside it.
  Image sizes are not stored: ``(2 cx + 1, 2 cy + 1)`` rounded, with a warning
  (the importer then takes the footage's own size when it is close, see
  :mod:`stage.importer`).

Any other FileStorage file is an unknown dialect: a :class:`CalibrationFormatError`
naming the nodes it holds.

Qualisys QTM ``.qca.txt`` (XML, root ``<calibration>``): one ``<camera serial=...>`` per
camera with ``fov_video`` (the image window, inclusive pixel bounds), ``transform``
(``x, y, z``: the camera's position in mm; ``r11..r33`` its orientation) and
``intrinsic`` (focal lengths, principal point and distortion in sub-pixel units of
1/64 pixel). As Pose2Sim's ``read_qca`` / ``calib_qca_fun`` read it: ``M`` =
``[[r11, r12, r13], [r21, r22, r23], [r31, r32, r33]]`` is the world -> Qualisys-camera
rotation, whose camera y and z axes point the other way from OpenCV's, so
``R = diag(1, -1, -1) M`` and ``t = -R C``; ``fx = focalLengthU / 64``, ``cx =
centerPointU / 64 - fov_video.left`` (and v, top); ``k1, k2, k3, p1, p2`` are the
``radialDistortion*`` and ``tangentalDistortion*`` terms divided by 64 (Pose2Sim's
convention, followed as the reference; read undivided, the demo rig's terms would move
the image corners by up to 8 px, docs/calibration.md). Only video cameras (``model`` naming
``video`` or ``none``) are kept, in natural order of their serials; world units mm.

Middlebury ``*_par.txt`` (Seitz et al. 2006): a count line, then one line per
image ``name k11..k33 r11..r33 t1 t2 t3`` with projection ``K [R | t]``, in
metres (units recorded as ``"m"``); no distortion. Image sizes are read from the
images beside the file when present.

caliscope ``camera_array.toml``: tables ``[cameras.<cam_id>]`` with ``size``, ``matrix``,
``distortions`` (k1, k2, p1, p2, k3), ``rotation`` (3x3 world -> camera), ``translation``
(world -> camera, metres), ``error`` (intrinsic RMS px), ``rotation_count``. Read in
metres (units ``"m"``); written in metres. Camera ``cam_<id>`` is caliscope's ``<id>``.

COLMAP text model (a folder): ``cameras.txt`` (``OPENCV`` model, or ``FULL_OPENCV`` when
k3 is not zero), ``images.txt`` (world -> camera quaternion ``QW QX QY QZ`` and
``TX TY TZ``, one image ``<camera>.png`` per camera), an empty ``points3D.txt``. COLMAP
puts the origin of pixel coordinates at the corner of the first pixel, so its
principal point is ours + 0.5.

nerfstudio ``transforms.json``: ``camera_model = "OPENCV"``, one frame per camera with
``fl_x, fl_y, cx, cy, w, h, k1, k2, k3, p1, p2`` (principal point + 0.5, as COLMAP) and a
camera -> world ``transform_matrix`` in the OpenGL convention (x right, y up, z back), in
metres.
"""

from __future__ import annotations

import json
import logging
import os
import re
import tempfile
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from calib import _toml
from calib.calibration import Calibration
from calib.camera import Camera, matrix_to_rodrigues, rodrigues_to_matrix
from calib.fileio import atomic_write, replace_durably

__all__ = [
    "FORMATS",
    "CalibrationFormatError",
    "read_calibration",
    "write_calibration",
    "calibration_to_aniposelib",
    "calibration_from_aniposelib",
    "read_aniposelib_toml",
    "write_aniposelib_toml",
    "read_opencv_yaml",
    "write_opencv_yaml",
    "read_middlebury_par",
    "read_qualisys_qca",
    "write_qualisys_qca",
    "read_json",
    "write_json",
    "read_caliscope_toml",
    "write_caliscope_toml",
    "write_colmap",
    "read_colmap",
    "write_nerfstudio",
    "read_nerfstudio",
    "in_units",
    "detect_format",
]

log = logging.getLogger(__name__)

FORMATS = ("toml", "yaml", "json", "caliscope", "colmap", "nerfstudio", "qualisys")
_UNIT_M = {"m": 1.0, "cm": 0.01, "mm": 0.001}


class CalibrationFormatError(ValueError):
    """A calibration file could not be read (names the file and what is wrong)."""


# -- aniposelib TOML ------------------------------------------------------------------


def calibration_to_aniposelib(calib: Calibration) -> dict:
    """The dictionary ``CameraGroup.dump`` would write (``cam_i`` tables + ``metadata``)."""
    if not isinstance(calib, Calibration):
        raise ValueError(f"calib must be a Calibration, got {type(calib).__name__}")
    out: dict[str, Any] = {}
    for i, c in enumerate(calib.cameras):
        out[f"cam_{i}"] = {
            "name": c.name,
            "size": [int(c.size[0]), int(c.size[1])],
            "matrix": c.K.tolist(),
            "distortions": c.dist.tolist(),
            "rotation": matrix_to_rodrigues(c.R).tolist(),
            "translation": c.t.tolist(),
            # Not read by aniposelib (it ignores unknown keys); lets our reader round-trip R exactly.
            "rotation_matrix": c.R.tolist(),
            **({"mirror": True} if c.meta.get("mirror") else {}),
        }
    meta: dict[str, Any] = {"units": calib.units}
    if calib.meta:
        try:
            _toml.dumps({"m": _drop_none(calib.meta)})
            meta.update({k: v for k, v in _drop_none(calib.meta).items() if k != "units"})
        except ValueError:
            meta["capture_stage_meta_json"] = json.dumps(calib.meta)
    out["metadata"] = meta
    return out


def _drop_none(d: Any) -> Any:
    if isinstance(d, dict):
        return {str(k): _drop_none(v) for k, v in d.items() if v is not None}
    if isinstance(d, (list, tuple)):
        return [_drop_none(v) for v in d]
    return d


def _cam_sort_key(key: str) -> tuple[int, str]:
    m = re.fullmatch(r"cam_(\d+)", key)
    return (int(m.group(1)) if m else 1 << 30, key)


#: keys of an aniposelib camera table (``rotation_matrix`` and ``mirror`` are ours)
_ANIPOSE_KEYS = frozenset({"name", "size", "matrix", "distortions", "rotation", "rotation_matrix", "translation",
                           "fisheye", "mirror"})


def calibration_from_aniposelib(data: dict, *, source: str = "aniposelib TOML") -> Calibration:
    """Build a :class:`Calibration` from a parsed aniposelib TOML dictionary.

    Cameras are ordered by their ``cam_<i>`` index (numerically, so ``cam_10``
    follows ``cam_9``). Exact inverse of :func:`calibration_to_aniposelib` except that
    the rotation passes through Rodrigues vectors (we also write ``rotation_matrix`` so our own files round-trip exactly).
    """
    if not isinstance(data, dict):
        raise CalibrationFormatError(f"{source}: expected tables [cam_0], [cam_1], ...")
    keys = sorted((k for k in data if k != "metadata" and isinstance(data[k], dict)), key=_cam_sort_key)
    if not keys:
        raise CalibrationFormatError(f"{source}: no camera tables ([cam_0], [cam_1], ...) found")
    cams = []
    for k in keys:
        d = data[k]
        if d.get("fisheye"):
            raise CalibrationFormatError(f"{source}: [{k}] is a fisheye camera; only the pinhole model is supported")
        unknown = sorted(set(d) - _ANIPOSE_KEYS)
        if unknown:  # a misspelt key would silently fall back to a default
            raise CalibrationFormatError(f"{source}: [{k}] has unknown keys {unknown} (known: {sorted(_ANIPOSE_KEYS)})")
        missing = [f for f in ("matrix", "rotation", "translation", "size") if f not in d]
        if missing:
            raise CalibrationFormatError(f"{source}: [{k}] is missing {', '.join(missing)}")
        try:
            dist = np.asarray(d.get("distortions", [0.0] * 5), dtype=np.float64).ravel()
            cams.append(
                Camera(
                    name=str(d.get("name", k)),
                    K=np.asarray(d["matrix"], dtype=np.float64),
                    dist=dist,
                    R=_rotation(d),
                    t=np.asarray(d["translation"], dtype=np.float64),
                    size=tuple(int(s) for s in d["size"]),
                    meta={"mirror": True} if d.get("mirror") else {},
                )
            )
        except (ValueError, TypeError) as exc:
            raise CalibrationFormatError(f"{source}: [{k}]: {exc}") from None
    meta = dict(data.get("metadata", {}) or {})
    units = str(meta.pop("units", "mm"))
    if "capture_stage_meta_json" in meta:
        meta = json.loads(meta.pop("capture_stage_meta_json"))
    return Calibration(cameras=tuple(cams), units=units, meta=meta)


def _rotation(d: dict) -> np.ndarray:
    R = rodrigues_to_matrix(np.asarray(d["rotation"], dtype=np.float64))
    if "rotation_matrix" in d:
        Rm = np.asarray(d["rotation_matrix"], dtype=np.float64)
        if Rm.shape == (3, 3) and np.allclose(Rm, R, atol=1e-9):
            return Rm  # exact; the Rodrigues vector wins if someone edited it
    return R


def read_aniposelib_toml(path: str | Path) -> Calibration:
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationFormatError(f"{p}: not valid TOML: {exc}") from None
    if "cameras" in data and isinstance(data["cameras"], list):  # our JSON layout written as TOML
        return Calibration.from_dict(data)
    return calibration_from_aniposelib(data, source=str(p))


def write_aniposelib_toml(calib: Calibration, path: str | Path) -> None:
    atomic_write(Path(path), _toml.dumps(calibration_to_aniposelib(calib)), parents=False)


# -- OpenCV FileStorage YAML -------------------------------------------------------------


def write_opencv_yaml(calib: Calibration, path: str | Path) -> None:
    """Write ``calib`` with ``cv2.FileStorage`` (YAML; ``.xml`` gives XML)."""
    import cv2

    if not isinstance(calib, Calibration):
        raise ValueError(f"calib must be a Calibration, got {type(calib).__name__}")
    p = Path(path)
    suffix = p.suffix if p.suffix in (".yml", ".yaml", ".xml") else ".yml"
    fd, tmp = tempfile.mkstemp(prefix=".calib-", suffix=suffix, dir=str(p.parent or Path(".")))
    os.close(fd)
    try:
        fs = cv2.FileStorage(tmp, cv2.FILE_STORAGE_WRITE)
        fs.write("units", calib.units)
        fs.write("camera_count", len(calib))
        for i, c in enumerate(calib.cameras):
            fs.startWriteStruct(f"camera_{i}", cv2.FileNode_MAP)
            fs.write("name", c.name)
            fs.write("image_width", int(c.size[0]))
            fs.write("image_height", int(c.size[1]))
            fs.write("K", np.ascontiguousarray(c.K))
            fs.write("dist", np.ascontiguousarray(c.dist.reshape(1, 5)))
            fs.write("R", np.ascontiguousarray(c.R))
            fs.write("T", np.ascontiguousarray(c.t.reshape(3, 1)))
            fs.endWriteStruct()
        fs.release()
        replace_durably(tmp, p)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def read_opencv_yaml(path: str | Path) -> Calibration:
    """Read a file written by :func:`write_opencv_yaml` or a single-camera OpenCV calibration."""
    import cv2

    p = Path(path)
    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise CalibrationFormatError(f"{p}: not an OpenCV FileStorage file: {exc}") from None
    if not fs.isOpened():
        raise CalibrationFormatError(f"{p}: OpenCV could not open it as FileStorage YAML/XML")
    try:
        root = fs.root()
        keys = list(root.keys())
        units_node = fs.getNode("units")
        units = units_node.string() if not units_node.empty() else "mm"
        cams = []
        cam_keys = sorted((k for k in keys if re.fullmatch(r"camera_\d+", k)), key=lambda k: int(k.split("_")[1]))
        if cam_keys:
            for k in cam_keys:
                n = fs.getNode(k)
                try:
                    name = n.getNode("name").string() or k
                    K = n.getNode("K").mat()
                    dist = n.getNode("dist").mat()
                    R = n.getNode("R").mat()
                    T = n.getNode("T").mat()
                    w = int(n.getNode("image_width").real())
                    h = int(n.getNode("image_height").real())
                    if K is None or R is None or T is None:
                        raise ValueError("needs K, R and T matrices")
                    cams.append(Camera(name=name, K=K, dist=np.zeros(5) if dist is None else dist.ravel(),
                                       R=R, t=T.ravel(), size=(w, h)))
                except (ValueError, TypeError, cv2.error) as exc:
                    raise CalibrationFormatError(f"{p}: {k}: {exc}") from None
        elif "camera_matrix" in keys:
            K = fs.getNode("camera_matrix").mat()
            d = fs.getNode("distortion_coefficients").mat()
            w = int(fs.getNode("image_width").real())
            h = int(fs.getNode("image_height").real())
            units = units if not units_node.empty() else "m"
            cams.append(Camera(name=p.stem, K=K, dist=np.zeros(5) if d is None else d.ravel()[:5],
                               R=np.eye(3), t=np.zeros(3), size=(w, h)))
        elif "names" in keys or p.name.lower() in ("intri.yml", "extri.yml", "intri.yaml", "extri.yaml"):
            fs.release()
            return _read_easymocap(p)
        else:
            shown = ", ".join(keys[:12]) or "nothing"
            raise CalibrationFormatError(
                f"{p}: unknown OpenCV FileStorage dialect (it holds {shown}; expected camera_<i> maps, a "
                "camera_matrix, or EasyMocap's names / K_<name> in intri.yml with extri.yml beside it)"
            )
    finally:
        fs.release()
    return Calibration(cameras=tuple(cams), units=units, meta={"source": str(p)})


def _fs_names(fs: Any) -> list[str]:
    node = fs.getNode("names")
    return [node.at(i).string() for i in range(node.size())] if not node.empty() else []


def _read_easymocap(p: Path) -> Calibration:
    """EasyMocap's ``intri.yml`` + ``extri.yml`` (either may be named; the other is beside it)."""
    import cv2

    stem = p.name.lower()
    ext = p.suffix
    intri = p if stem.startswith("intri") else p.with_name(f"intri{ext}")
    extri = p if stem.startswith("extri") else p.with_name(f"extri{ext}")
    for f in (intri, extri):
        if not f.is_file():
            raise CalibrationFormatError(f"{p}: an EasyMocap calibration needs {intri.name} and {extri.name}; "
                                         f"{f} is missing")
    fi, fe = cv2.FileStorage(str(intri), cv2.FILE_STORAGE_READ), cv2.FileStorage(str(extri), cv2.FILE_STORAGE_READ)
    try:
        names = _fs_names(fi) or _fs_names(fe)
        if not names:
            raise CalibrationFormatError(f"{intri}: no 'names' list: not an EasyMocap calibration")
        cams = []
        for name in names:
            K, dist = fi.getNode(f"K_{name}").mat(), fi.getNode(f"dist_{name}").mat()
            rot, rvec, T = fe.getNode(f"Rot_{name}").mat(), fe.getNode(f"R_{name}").mat(), fe.getNode(f"T_{name}").mat()
            if K is None or T is None or (rot is None and rvec is None):
                raise CalibrationFormatError(f"{p}: camera {name}: needs K_{name} ({intri.name}), T_{name} and "
                                             f"R_{name} or Rot_{name} ({extri.name})")
            R = rot if rot is not None else rodrigues_to_matrix(rvec.ravel())
            d = np.zeros(5) if dist is None else np.r_[dist.ravel(), np.zeros(5)][:5]
            size = (int(round(2 * K[0, 2] + 1)), int(round(2 * K[1, 2] + 1)))
            log.warning("%s: camera %s: no image size stored; assuming %dx%d from the principal point",
                        p, name, *size)
            try:
                cams.append(Camera(name=name, K=K, dist=d, R=R, t=T.ravel(), size=size, meta={"size_guessed": True}))
            except ValueError as exc:
                raise CalibrationFormatError(f"{p}: camera {name}: {exc}") from None
    finally:
        fi.release()
        fe.release()
    return Calibration(tuple(cams), units="m", meta={"source": str(p), "format": "easymocap"})


# -- Middlebury par.txt ----------------------------------------------------------------------


def _image_size(path: Path) -> tuple[int, int] | None:
    if not path.is_file():
        return None
    try:
        from PIL import Image

        with Image.open(path) as im:
            return (int(im.size[0]), int(im.size[1]))
    except (OSError, ValueError):
        return None


def read_middlebury_par(path: str | Path, *, size: tuple[int, int] | None = None) -> Calibration:
    """Read a Middlebury multi-view ``*_par.txt`` file.

    Parameters
    ----------
    path : path-like
        The ``*_par.txt`` file.
    size : (int, int), optional
        Image ``(width, height)`` when the images are not beside the file.

    Returns
    -------
    Calibration
        One camera per line, named by the image name without extension, in
        metres (``units="m"``), zero distortion.
    """
    p = Path(path)
    if size is not None and (len(size) != 2 or min(int(s) for s in size) <= 0):
        raise ValueError(f"size must be (width, height) > 0, got {size!r}")
    lines = [ln.split() for ln in p.read_text(encoding="utf-8").splitlines() if ln.strip()]
    if not lines:
        raise CalibrationFormatError(f"{p}: empty file")
    if len(lines[0]) == 1:
        try:
            count = int(lines[0][0])
        except ValueError:
            raise CalibrationFormatError(f"{p}: first line must be the number of images") from None
        lines = lines[1:]
        if count != len(lines):
            raise CalibrationFormatError(f"{p}: header says {count} images but {len(lines)} lines follow")
    cams = []
    for i, parts in enumerate(lines):
        if len(parts) != 22:
            raise CalibrationFormatError(
                f"{p}: line {i + 2}: expected 'name k11..k33 r11..r33 t1 t2 t3' (22 fields), got {len(parts)}"
            )
        try:
            vals = np.array([float(v) for v in parts[1:]])
        except ValueError:
            raise CalibrationFormatError(f"{p}: line {i + 2}: non-numeric value") from None
        K, R, t = vals[:9].reshape(3, 3), vals[9:18].reshape(3, 3), vals[18:]
        # Re-orthonormalize R (the file stores ~17 digits; keep it a proper rotation).
        U, _, Vt = np.linalg.svd(R)
        R = U @ Vt
        img = p.parent / parts[0]
        sz = _image_size(img) or (tuple(int(s) for s in size) if size is not None else None)
        if sz is None:
            raise CalibrationFormatError(f"{p}: image {parts[0]} not found beside the file; pass size=(width, height)")
        try:
            cams.append(Camera(name=Path(parts[0]).stem, K=K, dist=np.zeros(5), R=R, t=t, size=sz,
                               meta={"image": parts[0]}))
        except ValueError as exc:
            raise CalibrationFormatError(f"{p}: line {i + 2}: {exc}") from None
    return Calibration(cameras=tuple(cams), units="m", meta={"source": str(p), "format": "middlebury"})


# -- Qualisys QTM .qca.txt ----------------------------------------------------------------------

_QCA_FLIP = np.diag([1.0, -1.0, -1.0])  # Qualisys camera axes (y, z) -> OpenCV's
_QCA_SUBPIXEL = 64.0  # QTM stores focal lengths, principal points and distortion in 1/64 pixel


def _natural_key(name: str) -> list:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _qca_float(el: Any, key: str, where: str) -> float:
    v = el.get(key)
    if v is None:
        raise CalibrationFormatError(f"{where}: attribute {key!r} is missing")
    try:
        return float(v)
    except ValueError:
        raise CalibrationFormatError(f"{where}: attribute {key}={v!r} is not a number") from None


def _qca_camera(cam: Any, source: str) -> Camera:
    name = cam.get("serial") or cam.get("name") or ""
    where = f"{source}: camera {name or '?'}"
    fov, tr, intr = cam.find("fov_video"), cam.find("transform"), cam.find("intrinsic")
    if fov is None or tr is None or intr is None:
        raise CalibrationFormatError(f"{where}: needs <fov_video>, <transform> and <intrinsic>")
    left, top = _qca_float(fov, "left", where), _qca_float(fov, "top", where)
    w = int(round(_qca_float(fov, "right", where) - left + 1))
    h = int(round(_qca_float(fov, "bottom", where) - top + 1))
    s = _QCA_SUBPIXEL
    K = np.array([[_qca_float(intr, "focalLengthU", where) / s, 0.0, _qca_float(intr, "centerPointU", where) / s - left],
                  [0.0, _qca_float(intr, "focalLengthV", where) / s, _qca_float(intr, "centerPointV", where) / s - top],
                  [0.0, 0.0, 1.0]])
    d = {k: float(intr.get(k, 0.0)) / s for k in ("radialDistortion1", "radialDistortion2", "radialDistortion3",
                                                   "tangentalDistortion1", "tangentalDistortion2")}
    dist = np.array([d["radialDistortion1"], d["radialDistortion2"], d["tangentalDistortion1"],
                     d["tangentalDistortion2"], d["radialDistortion3"]])
    M = np.array([[_qca_float(tr, f"r{i}{j}", where) for j in (1, 2, 3)] for i in (1, 2, 3)])
    C = np.array([_qca_float(tr, k, where) for k in ("x", "y", "z")])
    U, _, Vt = np.linalg.svd(M)  # the file stores ~16 digits: keep it a proper rotation
    R = _QCA_FLIP @ (U @ Vt)
    meta: dict[str, Any] = {}
    if cam.get("avg-residual") is not None:
        meta["avg_residual_mm"] = float(cam.get("avg-residual"))
    try:
        return Camera(name=name, K=K, dist=dist, R=R, t=-R @ C, size=(w, h), meta=meta)
    except ValueError as exc:
        raise CalibrationFormatError(f"{where}: {exc}") from None


def read_qualisys_qca(path: str | Path) -> Calibration:
    """Read a Qualisys QTM ``.qca.txt`` calibration (see the module docstring; mm).

    Raises
    ------
    CalibrationFormatError
        Not XML, not a ``<calibration>`` root, no video camera, a missing or non-numeric
        attribute (the message names the camera and the attribute).
    """
    import xml.etree.ElementTree as ET

    p = Path(path)
    try:
        root = ET.fromstring(p.read_bytes())
    except ET.ParseError as exc:
        raise CalibrationFormatError(f"{p}: not valid XML: {exc}") from None
    if root.tag != "calibration":
        raise CalibrationFormatError(f"{p}: root element is <{root.tag}>, a Qualisys file has <calibration>")
    cams = root.findall("cameras/camera")
    video = [c for c in cams if any(m in (c.get("model") or "").lower() for m in ("video", "none"))]
    if not video:
        raise CalibrationFormatError(f"{p}: no video camera among {len(cams)} camera(s) (model naming video or none)")
    out = sorted((_qca_camera(c, str(p)) for c in video), key=lambda c: _natural_key(c.name))
    try:
        return Calibration(tuple(out), units="mm", meta={"source": str(p), "format": "qualisys"})
    except ValueError as exc:
        raise CalibrationFormatError(f"{p}: {exc}") from None


def write_qualisys_qca(calib: Calibration, path: str | Path) -> None:
    """Write a Qualisys ``.qca.txt`` (the inverse of :func:`read_qualisys_qca`; mm; principal
    points and sizes as a full-frame ``fov_video`` at the origin)."""
    import xml.etree.ElementTree as ET

    if not isinstance(calib, Calibration):
        raise ValueError(f"calib must be a Calibration, got {type(calib).__name__}")
    c_mm = in_units(calib, "mm")
    root = ET.Element("calibration", {"type": "regular", "source": "capture-stage"})
    cams = ET.SubElement(root, "cameras")
    s = _QCA_SUBPIXEL
    for c in c_mm.cameras:
        el = ET.SubElement(cams, "camera", {"active": "1", "model": "none", "serial": c.name,
                                            "avg-residual": repr(float(c.meta.get("avg_residual_mm", 0.0)))})
        box = {"left": "0", "top": "0", "right": str(c.width - 1), "bottom": str(c.height - 1)}
        ET.SubElement(el, "fov_video", box)
        M = _QCA_FLIP @ c.R
        attrs = {f"r{i + 1}{j + 1}": repr(float(M[i, j])) for i in range(3) for j in range(3)}
        attrs.update({k: repr(float(v)) for k, v in zip("xyz", c.center)})
        ET.SubElement(el, "transform", attrs)
        k1, k2, p1, p2, k3 = (float(v) * s for v in c.dist)
        ET.SubElement(el, "intrinsic", {
            "focalLengthU": repr(float(c.K[0, 0]) * s), "focalLengthV": repr(float(c.K[1, 1]) * s),
            "centerPointU": repr(float(c.K[0, 2]) * s), "centerPointV": repr(float(c.K[1, 2]) * s),
            "radialDistortion1": repr(k1), "radialDistortion2": repr(k2), "radialDistortion3": repr(k3),
            "tangentalDistortion1": repr(p1), "tangentalDistortion2": repr(p2), "skew": "0"})
    ET.indent(root)
    atomic_write(Path(path), "<?xml version='1.0' encoding='ASCII'?>\n" + ET.tostring(root, encoding="unicode") + "\n", parents=False)


# -- JSON ---------------------------------------------------------------------------------------


def write_json(calib: Calibration, path: str | Path) -> None:
    if not isinstance(calib, Calibration):
        raise ValueError(f"calib must be a Calibration, got {type(calib).__name__}")
    atomic_write(Path(path), json.dumps(calib.to_dict(), indent=1) + "\n", parents=False)


def read_json(path: str | Path) -> Calibration:
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise CalibrationFormatError(f"{p}: not valid JSON: {exc}") from None
    try:
        return Calibration.from_dict(data)
    except ValueError as exc:
        raise CalibrationFormatError(f"{p}: {exc}") from None


# -- units ------------------------------------------------------------------------------------------


def in_units(calib: Calibration, units: str) -> Calibration:
    """The same calibration with lengths (``t``) in ``units`` (``"m"``, ``"cm"``, ``"mm"``)."""
    if units not in _UNIT_M:
        raise ValueError(f"units must be one of {sorted(_UNIT_M)}, got {units!r}")
    if calib.units not in _UNIT_M:
        raise ValueError(f"calibration units {calib.units!r} cannot be converted")
    f = _UNIT_M[calib.units] / _UNIT_M[units]
    return Calibration(tuple(c.replace(t=c.t * f) for c in calib.cameras), units=units, meta=dict(calib.meta))


# -- caliscope ------------------------------------------------------------------------------------


def _cam_id(name: str, index: int) -> int:
    m = re.search(r"(\d+)$", name)
    return int(m.group(1)) if m else index


def read_caliscope_toml(path: str | Path) -> Calibration:
    """Read caliscope's ``camera_array.toml`` (units ``"m"``; cameras ``cam_<id>``)."""
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationFormatError(f"{p}: not valid TOML: {exc}") from None
    return _from_caliscope(data, str(p))


def _from_caliscope(data: dict, source: str) -> Calibration:
    tables = data.get("cameras")
    if not isinstance(tables, dict) or not tables:
        raise CalibrationFormatError(f"{source}: no [cameras.<id>] tables (caliscope camera_array.toml)")
    cams = []
    for key in sorted(tables, key=lambda k: int(k) if str(k).isdigit() else 1 << 30):
        d = tables[key]
        if d.get("ignore"):
            continue
        missing = [f for f in ("matrix", "rotation", "translation", "size") if f not in d]
        if missing:
            raise CalibrationFormatError(f"{source}: [cameras.{key}] is missing {', '.join(missing)}")
        try:
            meta = {k: d[k] for k in ("error", "rotation_count") if k in d}
            if d.get("mirror"):
                meta["mirror"] = True
            cams.append(Camera(name=f"cam_{d.get('cam_id', key)}", K=np.asarray(d["matrix"], dtype=np.float64),
                               dist=np.asarray(d.get("distortions", [0.0] * 5), dtype=np.float64),
                               R=np.asarray(d["rotation"], dtype=np.float64),
                               t=np.asarray(d["translation"], dtype=np.float64), size=tuple(d["size"]), meta=meta))
        except (ValueError, TypeError) as exc:
            raise CalibrationFormatError(f"{source}: [cameras.{key}]: {exc}") from None
    if not cams:
        raise CalibrationFormatError(f"{source}: every camera is marked ignore = true")
    return Calibration(tuple(cams), units="m", meta={"source": "caliscope"})


def write_caliscope_toml(calib: Calibration, path: str | Path) -> None:
    """Write caliscope's ``camera_array.toml`` (metres; ``cam_id`` from the name's trailing number)."""
    if not isinstance(calib, Calibration):
        raise ValueError(f"calib must be a Calibration, got {type(calib).__name__}")
    c_m = in_units(calib, "m")
    tables: dict[str, dict] = {}
    for i, c in enumerate(c_m.cameras):
        cid = _cam_id(c.name, i)
        if str(cid) in tables:
            cid = i
        if str(cid) in tables:
            raise ValueError(f"calib: camera {c.name}: cannot give it a unique caliscope cam_id")
        err = c.meta.get("error", calib.meta.get("per_camera_rms_px", {}).get(c.name, 0.0))
        tables[str(cid)] = {"cam_id": cid, "size": [int(s) for s in c.size], "rotation_count":
                            int(c.meta.get("rotation_count", 0)), "error": float(err), "matrix": c.K.tolist(),
                            "distortions": c.dist.tolist(), "translation": c.t.tolist(), "rotation": c.R.tolist(),
                            "ignore": False, **({"mirror": True} if c.meta.get("mirror") else {})}
    atomic_write(Path(path), _toml.dumps({"cameras": tables}), parents=False)


# -- COLMAP ---------------------------------------------------------------------------------------


def _quat_from_matrix(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


def write_colmap(calib: Calibration, folder: str | Path) -> Path:
    """Write a COLMAP text model (``cameras.txt``, ``images.txt``, ``points3D.txt``) into ``folder``."""
    if not isinstance(calib, Calibration):
        raise ValueError(f"calib must be a Calibration, got {type(calib).__name__}")
    d = Path(folder)
    if d.exists() and not d.is_dir():
        raise ValueError(f"COLMAP output must be a folder, {d} is a file")
    if not d.parent.exists():
        raise FileNotFoundError(f"output folder does not exist: {d.parent}")
    d.mkdir(exist_ok=True)
    cams = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
            f"# Number of cameras: {len(calib)}"]
    imgs = ["# Image list with two lines of data per image:",
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)",
            f"# Number of images: {len(calib)}, units: {calib.units}"]
    for i, c in enumerate(calib.cameras, start=1):
        fx, fy, cx, cy = c.K[0, 0], c.K[1, 1], c.K[0, 2] + 0.5, c.K[1, 2] + 0.5
        k1, k2, p1, p2, k3 = c.dist
        if k3 != 0:
            model, params = "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]
        else:
            model, params = "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
        cams.append(f"{i} {model} {c.width} {c.height} " + " ".join(repr(float(v)) for v in params))
        q = _quat_from_matrix(c.R)
        imgs.append(f"{i} " + " ".join(repr(float(v)) for v in (*q, *c.t)) + f" {i} {c.name}.png")
        imgs.append("")
    atomic_write(d / "cameras.txt", "\n".join(cams) + "\n", parents=False)
    atomic_write(d / "images.txt", "\n".join(imgs) + "\n", parents=False)
    atomic_write(d / "points3D.txt", "# 3D point list (none: a calibration only)\n", parents=False)
    return d


def read_colmap(folder: str | Path, *, units: str = "mm") -> Calibration:
    """Read a COLMAP text model's cameras and images (pinhole, OPENCV and FULL_OPENCV models)."""
    from scipy.spatial.transform import Rotation

    d = Path(folder)
    try:
        cam_lines = [ln.split() for ln in (d / "cameras.txt").read_text().splitlines() if ln and ln[0] != "#"]
        img_text = [ln for ln in (d / "images.txt").read_text().splitlines() if not ln.startswith("#")]
        img_lines = [ln.split() for ln in img_text[0::2] if ln.strip()]  # pose lines; points lines between
    except OSError as exc:
        raise CalibrationFormatError(f"{d}: not a COLMAP text model: {exc}") from None
    intr = {}
    for parts in cam_lines:
        try:
            cid, model, w, h = int(parts[0]), parts[1], int(parts[2]), int(parts[3])
            p = [float(v) for v in parts[4:]]
        except (IndexError, ValueError):
            raise CalibrationFormatError(f"{d}/cameras.txt: bad line {' '.join(parts)!r}") from None
        if model == "PINHOLE":
            fx, fy, cx, cy, dist = *p[:4], [0.0] * 5
        elif model == "OPENCV":
            fx, fy, cx, cy, dist = *p[:4], p[4:8] + [0.0]
        elif model == "FULL_OPENCV":
            if any(v != 0 for v in p[9:12]):
                raise CalibrationFormatError(f"{d}/cameras.txt: camera {cid}: rational terms k4-k6 not supported")
            fx, fy, cx, cy, dist = *p[:4], p[4:9]
        else:
            raise CalibrationFormatError(f"{d}/cameras.txt: camera {cid}: model {model} not supported "
                                         "(PINHOLE, OPENCV, FULL_OPENCV)")
        intr[cid] = (np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1.0]]), np.array(dist), (w, h))
    cams = []
    # images.txt: a pose line then a points line (possibly empty, dropped above)
    for parts in img_lines:
        try:
            qw, qx, qy, qz, tx, ty, tz = (float(v) for v in parts[1:8])
            cid = int(parts[8])
            parts[9]
        except (ValueError, IndexError):
            raise CalibrationFormatError(f"{d}/images.txt: bad image line {' '.join(parts)!r}") from None
        if cid not in intr:
            raise CalibrationFormatError(f"{d}/images.txt: image {parts[0]} names unknown camera {cid}")
        K, dist, size = intr[cid]
        R = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()
        cams.append(Camera(Path(parts[9]).stem, K=K, dist=dist, R=R, t=np.array([tx, ty, tz]), size=size))
    if not cams:
        raise CalibrationFormatError(f"{d}/images.txt: no images")
    return Calibration(tuple(cams), units=units)


# -- nerfstudio -----------------------------------------------------------------------------------

_GL = np.diag([1.0, -1.0, -1.0])  # OpenCV camera axes -> OpenGL (x right, y up, z back)


def write_nerfstudio(calib: Calibration, path: str | Path) -> None:
    """Write nerfstudio's ``transforms.json`` (OPENCV model, metres, one frame per camera)."""
    if not isinstance(calib, Calibration):
        raise ValueError(f"calib must be a Calibration, got {type(calib).__name__}")
    c_m = in_units(calib, "m")
    frames = []
    for c in c_m.cameras:
        c2w = np.eye(4)
        c2w[:3, :3] = c.R.T @ _GL
        c2w[:3, 3] = c.center
        k1, k2, p1, p2, k3 = (float(v) for v in c.dist)
        frames.append({"file_path": f"images/{c.name}.png", "camera": c.name, "fl_x": float(c.K[0, 0]),
                       "fl_y": float(c.K[1, 1]), "cx": float(c.K[0, 2]) + 0.5, "cy": float(c.K[1, 2]) + 0.5,
                       "w": int(c.width), "h": int(c.height), "k1": k1, "k2": k2, "k3": k3, "k4": 0.0,
                       "p1": p1, "p2": p2, "transform_matrix": c2w.tolist()})
    atomic_write(Path(path), json.dumps({"camera_model": "OPENCV", "frames": frames}, indent=1) + "\n", parents=False)


def read_nerfstudio(path: str | Path, *, units: str = "m") -> Calibration:
    """Read nerfstudio's ``transforms.json`` (per-frame or shared intrinsics, OPENCV / PINHOLE)."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise CalibrationFormatError(f"{p}: not a nerfstudio transforms.json: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise CalibrationFormatError(f"{p}: no 'frames' list")
    if data.get("camera_model", "OPENCV") not in ("OPENCV", "PINHOLE"):
        raise CalibrationFormatError(f"{p}: camera_model {data['camera_model']!r} not supported (OPENCV, PINHOLE)")
    cams = []
    for i, f in enumerate(data["frames"]):
        g = {**data, **f}
        try:
            K = np.array([[g["fl_x"], 0, g["cx"] - 0.5], [0, g["fl_y"], g["cy"] - 0.5], [0, 0, 1.0]])
            dist = np.array([g.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")], dtype=np.float64)
            c2w = np.asarray(g["transform_matrix"], dtype=np.float64)
            Rcw = (c2w[:3, :3] @ _GL).T
            name = str(f.get("camera", Path(str(f.get("file_path", f"cam_{i}"))).stem))
            cams.append(Camera(name, K=K, dist=dist, R=Rcw, t=-Rcw @ c2w[:3, 3], size=(int(g["w"]), int(g["h"]))))
        except (KeyError, ValueError, TypeError) as exc:
            raise CalibrationFormatError(f"{p}: frame {i}: {exc}") from None
    return Calibration(tuple(cams), units=units)


# -- dispatch -------------------------------------------------------------------------------------


def _xml_dialect(p: Path) -> str:
    """``"yaml"`` (OpenCV FileStorage) or ``"qualisys"`` from an XML file's root element."""
    if not p.is_file():
        return "yaml"  # a file to write: FileStorage XML
    head = p.read_bytes()[:4096].decode("utf-8", errors="replace")
    m = re.search(r"<([A-Za-z_][\w.-]*)[\s>/]", re.sub(r"<\?.*?\?>|<!--.*?-->", "", head, flags=re.S))
    root = m.group(1) if m else ""
    if root == "opencv_storage":
        return "yaml"
    if root == "calibration":
        return "qualisys"
    raise CalibrationFormatError(
        f"{p}: unknown XML calibration dialect (root element <{root or '?'}>; expected <opencv_storage> "
        "from OpenCV FileStorage or <calibration> from Qualisys QTM)"
    )


def detect_format(path: str | Path) -> str:
    """``"toml"``, ``"yaml"``, ``"qualisys"``, ``"json"``, ``"middlebury"``... from the file name
    (and, for ``.xml``, the root element)."""
    p = Path(path)
    name = p.name.lower()
    if p.is_dir() or name in ("cameras.txt", "images.txt") or (not p.exists() and not p.suffix):
        return "colmap"
    if name == "transforms.json":
        return "nerfstudio"
    if name == "camera_array.toml":
        return "caliscope"
    if name.endswith(".toml"):
        if p.is_file() and re.search(r"^\[cameras\.", p.read_text(encoding="utf-8", errors="replace"), re.M):
            return "caliscope"
        return "toml"
    if name.endswith(".qca.txt") or name.endswith(".qca"):
        return "qualisys"
    if name.endswith(".xml"):
        return _xml_dialect(p)
    if name.endswith((".yml", ".yaml")):
        return "yaml"
    if name.endswith(".json"):
        return "json"
    if name.endswith(".txt"):
        return "middlebury"
    raise CalibrationFormatError(
        f"{p}: unknown calibration format (expected .toml, .yml/.yaml/.xml, .json or a Middlebury *_par.txt)"
    )


def read_calibration(path: str | Path, **kwargs: Any) -> Calibration:
    """Read a calibration in any supported format (detected from the file name).

    Parameters
    ----------
    path : path-like
        ``.toml`` (aniposelib), ``.yml``/``.yaml``/``.xml`` (OpenCV FileStorage),
        ``.json`` (:meth:`Calibration.to_dict`), ``*_par.txt`` (Middlebury).
    **kwargs
        Passed to the reader (``size=`` for Middlebury).

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    CalibrationFormatError
        The file cannot be parsed (a ``ValueError``; the message names the file).
    """
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"path must be a file path, got {type(path).__name__}")
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"calibration file not found: {p}")
    fmt = detect_format(p)
    if fmt == "colmap":
        return read_colmap(p if p.is_dir() else p.parent, **kwargs)
    if fmt == "nerfstudio":
        return read_nerfstudio(p, **kwargs)
    if fmt == "caliscope":
        return read_caliscope_toml(p)
    if fmt == "qualisys":
        return read_qualisys_qca(p)
    if fmt == "toml":
        return read_aniposelib_toml(p)
    if fmt == "yaml":
        return read_opencv_yaml(p)
    if fmt == "json":
        return read_json(p)
    return read_middlebury_par(p, **kwargs)


def write_calibration(calib: Calibration, path: str | Path, *, format: str | None = None) -> Path:
    """Write ``calib`` atomically (a temporary file renamed into place).

    Parameters
    ----------
    calib : Calibration
    path : path-like
    format : {"toml", "yaml", "json", "caliscope", "colmap", "nerfstudio"}, optional
        Default: from the file name (a folder or ``cameras.txt``: COLMAP;
        ``transforms.json``: nerfstudio; ``camera_array.toml``: caliscope).

    Returns
    -------
    Path
        The written file.
    """
    if not isinstance(calib, Calibration):
        raise ValueError(f"calib must be a Calibration, got {type(calib).__name__}")
    p = Path(path)
    fmt = format if format is not None else detect_format(p)
    if fmt == "yml":
        fmt = "yaml"
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {', '.join(FORMATS)} (Middlebury is read-only), got {fmt!r}")
    if not p.parent.exists():
        raise FileNotFoundError(f"output folder does not exist: {p.parent}")
    if fmt == "colmap":
        return write_colmap(calib, p)
    if fmt == "nerfstudio":
        write_nerfstudio(calib, p)
    elif fmt == "caliscope":
        write_caliscope_toml(calib, p)
    elif fmt == "qualisys":
        write_qualisys_qca(calib, p)
    elif fmt == "toml":
        write_aniposelib_toml(calib, p)
    elif fmt == "yaml":
        write_opencv_yaml(calib, p)
    else:
        write_json(calib, p)
    return p
