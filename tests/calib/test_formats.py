"""Calibration file formats (calib.formats)."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from calib.calibration import Calibration
from calib.camera import rodrigues_to_matrix
from calib.formats import (
    CalibrationFormatError,
    calibration_from_aniposelib,
    read_calibration,
    read_middlebury_par,
    write_calibration,
)
from tests.calib.calibrations import random_calibration
from tests.conftest import shared_dataset


@pytest.mark.parametrize("ext", ["toml", "yml", "json"])
def test_round_trip_exact(tmp_path, ext):
    c = random_calibration()
    p = write_calibration(c, tmp_path / f"c.{ext}")
    c2 = read_calibration(p)
    assert c2 == c  # Camera.__eq__ is exact (array_equal) on K, dist, R, t, size, name
    assert c2.units == "mm" and c2.names == c.names


def test_toml_is_aniposelib_layout(tmp_path):
    c = random_calibration(n=11)
    p = write_calibration(c, tmp_path / "c.toml")
    d = tomllib.loads(p.read_text())
    assert [k for k in d if k.startswith("cam_")] == [f"cam_{i}" for i in range(11)]
    cam = d["cam_3"]
    assert set(cam) >= {"name", "size", "matrix", "distortions", "rotation", "translation"}
    assert cam["size"] == [640, 480] and len(cam["rotation"]) == 3
    np.testing.assert_allclose(rodrigues_to_matrix(cam["rotation"]), c[3].R, atol=1e-12)
    # a file as aniposelib writes it (no rotation_matrix): Rodrigues only, numeric camera order
    for k in list(d):
        if k.startswith("cam_"):
            d[k].pop("rotation_matrix")
    c2 = calibration_from_aniposelib(d)
    assert c2.names == c.names
    for a, b in zip(c2, c):
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_array_equal(a.t, b.t)


def test_middlebury_dino_bounding_box_projects_inside():
    root = shared_dataset("middlebury_dino_sparse_ring")
    calib = read_calibration(root / "dinoSR_par.txt")
    assert len(calib) == 16 and calib.units == "m"
    text = (root / "README.txt").read_text()
    import re

    lo, hi = (np.array([float(v) for v in m.split()]) for m in re.findall(r"\(([-\d.\s]+)\)", text)[:2])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    import cv2

    # The README warns the dino leaves the field of view in some images, so the box's
    # corners cannot all be inside; what must hold: the box centre projects into every
    # image, in front of the camera, and every object pixel (the README's silhouette
    # threshold 0.19) lies inside the projected box.
    for cam in calib:
        assert cam.size == (640, 480)
        uv, z = cam.project(corners, return_depth=True)
        assert np.all(z > 0), cam.name
        assert cam.in_image(cam.project((lo + hi) / 2)).all(), cam.name
        gray = cv2.imread(str(root / cam.meta["image"]), cv2.IMREAD_GRAYSCALE)
        obj = gray > 0.19 * 255
        poly = np.zeros_like(gray)
        cv2.fillConvexPoly(poly, np.round(cv2.convexHull(uv.astype(np.float32))).astype(np.int32).reshape(-1, 2), 1)
        inside = (obj & (poly > 0)).sum() / obj.sum()
        assert obj.sum() > 10000 and inside > 0.995, (cam.name, inside)
    line = (root / "dinoSR_par.txt").read_text().splitlines()[1].split()
    v = np.array([float(x) for x in line[1:]])
    P = v[:9].reshape(3, 3) @ np.hstack([v[9:18].reshape(3, 3), v[18:, None]])
    # (R is re-orthonormalized on import: the file stores it to ~1e-7)
    np.testing.assert_allclose(calib[0].P, P, atol=1e-6 * np.abs(P).max())


def test_opencv_single_camera_yaml_reads():
    root = shared_dataset("opencv_stereo_9x6")
    c = read_calibration(root / "left_intrinsics.yml")
    assert len(c) == 1 and c[0].size == (640, 480)
    np.testing.assert_allclose(c[0].K[0, 0], 535.9157, atol=1e-3)


def test_invalid_input(tmp_path):
    c = random_calibration(n=2)
    with pytest.raises(FileNotFoundError):
        read_calibration(tmp_path / "nope.toml")
    with pytest.raises(ValueError, match="path"):
        read_calibration(42)
    (tmp_path / "x.abc").write_text("")
    with pytest.raises(CalibrationFormatError, match="unknown calibration format"):
        read_calibration(tmp_path / "x.abc")
    (tmp_path / "bad.toml").write_text("[cam_0]\nname = 'a'\n")
    with pytest.raises(CalibrationFormatError, match="missing"):
        read_calibration(tmp_path / "bad.toml")
    (tmp_path / "empty.toml").write_text("")
    with pytest.raises(CalibrationFormatError, match="no camera"):
        read_calibration(tmp_path / "empty.toml")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(CalibrationFormatError, match="JSON"):
        read_calibration(tmp_path / "bad.json")
    (tmp_path / "bad_par.txt").write_text("1\nimg.png 1 2 3\n")
    with pytest.raises(CalibrationFormatError, match="22 fields"):
        read_middlebury_par(tmp_path / "bad_par.txt", size=(10, 10))
    with pytest.raises(ValueError, match="format"):
        write_calibration(c, tmp_path / "c.toml", format="xml")
    with pytest.raises(ValueError, match="calib"):
        write_calibration({"cameras": []}, tmp_path / "c.toml")
    with pytest.raises(FileNotFoundError):
        write_calibration(c, tmp_path / "no" / "dir" / "c.toml")
    assert not (tmp_path / "c.toml").exists()


# -- caliscope, COLMAP, nerfstudio --------------------------------------------------------------


def _close(a: Calibration, b: Calibration, *, t_scale: float = 1.0, atol: float = 1e-9) -> None:
    assert a.names == b.names
    for ca, cb in zip(a, b):
        assert ca.size == cb.size
        np.testing.assert_allclose(ca.K, cb.K, atol=atol)
        np.testing.assert_allclose(ca.dist, cb.dist, atol=atol)
        np.testing.assert_allclose(ca.R, cb.R, atol=1e-12)
        np.testing.assert_allclose(ca.t * t_scale, cb.t, atol=atol * 1e3)


def _named(calib: Calibration) -> Calibration:
    return Calibration(tuple(c.replace(name=f"cam_{i}") for i, c in enumerate(calib)), units=calib.units)


@pytest.mark.parametrize("where", ["camera_array.toml", "colmap", "transforms.json"])
def test_round_trip_new_formats(tmp_path, where):
    cal = _named(random_calibration(5))
    out = write_calibration(cal, tmp_path / where)
    back = read_calibration(out if where != "colmap" else tmp_path / "colmap", **({"units": "mm"} if where
                                                                                 == "colmap" else {}))
    # caliscope and nerfstudio are metres, COLMAP keeps the unit it was given
    _close(cal, back, t_scale=1.0 if where == "colmap" else 1e-3)


def test_colmap_layout_and_pixel_convention(tmp_path):
    cal = _named(random_calibration(2))
    write_calibration(cal, tmp_path / "model", format="colmap")
    lines = [ln for ln in (tmp_path / "model" / "cameras.txt").read_text().splitlines() if not ln.startswith("#")]
    parts = lines[0].split()
    assert parts[1] == "FULL_OPENCV" and len(parts) == 4 + 12
    assert float(parts[6]) == pytest.approx(cal[0].K[0, 2] + 0.5)  # COLMAP: origin at the pixel corner
    img = [ln for ln in (tmp_path / "model" / "images.txt").read_text().splitlines() if not ln.startswith("#")]
    q = np.array([float(v) for v in img[0].split()[1:5]])
    assert np.linalg.norm(q) == pytest.approx(1.0) and q[0] >= 0


def test_nerfstudio_pose_is_camera_to_world_opengl(tmp_path):
    cal = _named(random_calibration(1))
    write_calibration(cal, tmp_path / "transforms.json")
    import json

    f = json.loads((tmp_path / "transforms.json").read_text())["frames"][0]
    c2w = np.array(f["transform_matrix"])
    cam = cal[0]
    np.testing.assert_allclose(c2w[:3, 3], cam.center / 1000.0, atol=1e-12)
    # the camera looks down its -z axis (OpenGL): -z of c2w is the optical axis in the world
    np.testing.assert_allclose(-c2w[:3, 2], cam.R[2], atol=1e-12)


def test_reads_caliscope_reference_file():
    root = shared_dataset("caliscope_4cam")
    cal = read_calibration(root / "camera_array.toml")
    assert cal.units == "m" and cal.names == ["cam_0", "cam_1", "cam_2", "cam_3"]
    assert cal["cam_0"].K[0, 0] == pytest.approx(894.5288733178912)
    np.testing.assert_allclose(cal["cam_1"].t, [0.00043375420342479525, -0.0019919458836723174, 0.0025865337259615363])


def test_mirror_flag_round_trips(tmp_path):
    cal = _named(random_calibration(2))
    cal = Calibration((cal[0].replace(meta={"mirror": True}), cal[1]), units="mm")
    for name in ("a.toml", "camera_array.toml", "a.json"):
        back = read_calibration(write_calibration(cal, tmp_path / name))
        assert back[0].meta.get("mirror") is True and not back[1].meta.get("mirror")


def test_invalid_input_new_formats(tmp_path):
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "cameras.txt").write_text("1 SIMPLE_RADIAL 640 480 500 320 240 0.1\n")
    (tmp_path / "bad" / "images.txt").write_text("")
    with pytest.raises(CalibrationFormatError, match="SIMPLE_RADIAL"):
        read_calibration(tmp_path / "bad")
    (tmp_path / "transforms.json").write_text('{"camera_model": "OPENCV_FISHEYE", "frames": []}')
    with pytest.raises(CalibrationFormatError, match="OPENCV_FISHEYE"):
        read_calibration(tmp_path / "transforms.json")
    (tmp_path / "camera_array.toml").write_text("[cameras.0]\ncam_id = 0\n")
    with pytest.raises(CalibrationFormatError, match="missing"):
        read_calibration(tmp_path / "camera_array.toml")
    with pytest.raises(ValueError, match="units"):
        from calib.formats import in_units

        in_units(random_calibration(1), "furlong")


# -- Qualisys .qca.txt, OpenCV FileStorage XML, EasyMocap -----------------------------------------


def _pose2sim_reference(xml_text: str) -> dict:
    """Pose2Sim's read_qca + calib_qca_fun, written out step by step (homogeneous matrices):
    a slow reference for the reader, independent of its code."""
    import xml.etree.ElementTree as ET

    out = {}
    for cam in ET.fromstring(xml_text).findall("cameras/camera"):
        tr, intr, fov = cam.find("transform"), cam.find("intrinsic"), cam.find("fov_video")
        g = lambda el, k: float(el.get(k))  # noqa: E731
        by_col = np.array([g(tr, f"r{i}{j}") for i in (1, 2, 3) for j in (1, 2, 3)]).reshape(3, 3).T
        T = np.array([g(tr, k) for k in "xyz"])
        r, t = by_col.T, -(by_col.T @ T)  # world_to_camera_persp
        rt = np.eye(4)
        rt[:3, :3], rt[:3, 3] = r, t
        rx = np.eye(4)
        rx[1:3, 1:3] = [[np.cos(np.pi), -np.sin(np.pi)], [np.sin(np.pi), np.cos(np.pi)]]
        rt = rx @ rt  # rotate_cam(ang_x=pi)
        K = np.array([[g(intr, "focalLengthU") / 64, 0, g(intr, "centerPointU") / 64 - g(fov, "left")],
                      [0, g(intr, "focalLengthV") / 64, g(intr, "centerPointV") / 64 - g(fov, "top")], [0, 0, 1]])
        size = (int(g(fov, "right") - g(fov, "left") + 1), int(g(fov, "bottom") - g(fov, "top") + 1))
        out[cam.get("serial")] = (K, rt[:3, :3], rt[:3, 3], size)
    return out


def test_qualisys_demo_matches_pose2sim_and_projects_the_person():
    root = shared_dataset("pose2sim_demo")
    path = root / "Calib.qca.txt"
    calib = read_calibration(path)
    assert calib.names == ["cam01", "cam02", "cam03", "cam04"] and calib.units == "mm"
    ref = _pose2sim_reference(path.read_text())
    for cam in calib:
        K, R, t, size = ref[cam.name]
        assert cam.size == size == (1088, 1920)
        np.testing.assert_allclose(cam.K, K, atol=1e-9)
        np.testing.assert_allclose(cam.R, R, atol=1e-9)  # re-orthonormalized: the file stores 16 digits
        np.testing.assert_allclose(cam.t, t, atol=1e-6 * np.abs(t).max())
    # projection check (README): the cameras stand 1.7-2.1 m high around the origin, look in and
    # down, and the box that holds the standing person projects into every image, in front
    centres = np.array([c.center for c in calib])
    assert np.all((centres[:, 2] > 1600) & (centres[:, 2] < 2200))
    person_lo, person_hi = np.array([-1550.0, -900.0, 0.0]), np.array([-450.0, 400.0, 1700.0])
    corners = np.array([[x, y, z] for x in (person_lo[0], person_hi[0]) for y in (person_lo[1], person_hi[1])
                        for z in (person_lo[2], person_hi[2])])
    for cam in calib:
        axis = cam.R[2]  # the optical axis in the world
        assert axis[2] < -0.2, cam.name  # looks down
        to_person = (person_lo + person_hi) / 2 - cam.center
        assert axis @ to_person / np.linalg.norm(to_person) > 0.9, cam.name  # within ~25 deg of the axis
        uv, z = cam.project(corners, return_depth=True)
        # the README's box is the 50 mm voxels seen by all four cameras (loose): its centre in the
        # image, its corners within a tenth of the image's size from it
        assert np.all(z > 0) and cam.in_image(cam.project((person_lo + person_hi) / 2)).all(), cam.name
        assert np.all(np.abs(uv - np.array(cam.size) / 2) < 0.6 * np.array(cam.size)), cam.name
        # world z up appears as image up: the person's head above its feet
        head, feet = cam.project(np.array([[-1000.0, -250.0, 1700.0], [-1000.0, -250.0, 0.0]]))
        assert head[1] < feet[1] - 500, cam.name


def test_qualisys_round_trip_and_video_cameras_only(tmp_path):
    c = random_calibration(n=3)
    p = write_calibration(c, tmp_path / "rig.qca.txt")
    c2 = read_calibration(p)
    _close(c2, c, atol=1e-9)
    assert c2.units == "mm" and c2.meta["format"] == "qualisys"
    # a marker camera (no video) is left out; natural order of the serials
    text = p.read_text().replace('model="none" serial="cam01"', 'model="Oqus 700+" serial="cam01"')
    p.write_text(text.replace('serial="cam02"', 'serial="cam10"'))
    c3 = read_calibration(p)
    assert c3.names == ["cam00", "cam10"]


def test_opencv_xml_round_trip_and_easymocap(tmp_path):
    import cv2

    c = random_calibration(n=4)
    p = write_calibration(c, tmp_path / "c.xml")
    assert "<opencv_storage>" in p.read_text()
    assert read_calibration(p) == c  # FileStorage XML writes doubles exactly, as YAML does
    # EasyMocap's intri.yml / extri.yml pair (metres, Rodrigues R_<name>)
    fi = cv2.FileStorage(str(tmp_path / "intri.yml"), cv2.FILE_STORAGE_WRITE)
    fe = cv2.FileStorage(str(tmp_path / "extri.yml"), cv2.FILE_STORAGE_WRITE)
    names = [cam.name for cam in c]
    fi.write("names", names)
    fe.write("names", names)
    for cam in c:
        fi.write(f"K_{cam.name}", cam.K)
        fi.write(f"dist_{cam.name}", cam.dist.reshape(1, 5))
        fe.write(f"R_{cam.name}", cam.rvec.reshape(3, 1))
        fe.write(f"T_{cam.name}", cam.t.reshape(3, 1) / 1000)
    fi.release()
    fe.release()
    for f in ("intri.yml", "extri.yml"):
        e = read_calibration(tmp_path / f)
        assert e.names == names and e.units == "m"
        for a, b in zip(e, c):
            np.testing.assert_allclose(a.K, b.K, atol=1e-9)
            np.testing.assert_allclose(a.R, b.R, atol=1e-9)
            np.testing.assert_allclose(a.t * 1000, b.t, atol=1e-6)
            assert a.size == (round(2 * b.K[0, 2] + 1), round(2 * b.K[1, 2] + 1)) and a.meta["size_guessed"]


def test_invalid_input_qualisys_and_dialects(tmp_path):
    import cv2

    (tmp_path / "x.xml").write_text("<?xml version='1.0'?>\n<scene><camera/></scene>\n")
    with pytest.raises(CalibrationFormatError, match="unknown XML calibration dialect.*<scene>"):
        read_calibration(tmp_path / "x.xml")
    fs = cv2.FileStorage(str(tmp_path / "other.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("focal", 1.0)
    fs.release()
    with pytest.raises(CalibrationFormatError, match="unknown OpenCV FileStorage dialect.*focal"):
        read_calibration(tmp_path / "other.yml")
    (tmp_path / "bad.qca.txt").write_text("<calibration><cameras>")
    with pytest.raises(CalibrationFormatError, match="not valid XML"):
        read_calibration(tmp_path / "bad.qca.txt")
    p = write_calibration(random_calibration(n=2), tmp_path / "ok.qca.txt")
    p.write_text(p.read_text().replace(' focalLengthU="', ' focalLengthX="'))
    with pytest.raises(CalibrationFormatError, match="camera cam00: attribute 'focalLengthU' is missing"):
        read_calibration(p)
    p.write_text(p.read_text().replace('model="none"', 'model="Oqus"'))
    with pytest.raises(CalibrationFormatError, match="no video camera"):
        read_calibration(p)
    (tmp_path / "intri.yml").write_text("%YAML:1.0\n---\nnames: [a]\n")
    with pytest.raises(CalibrationFormatError, match="extri.yml is missing"):
        read_calibration(tmp_path / "intri.yml")
