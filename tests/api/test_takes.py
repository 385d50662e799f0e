"""/takes: upload (raw and multipart), import from a path in the data root, info, frames and masks, delete."""

from __future__ import annotations

import cv2
import numpy as np

from stage.store import TakeReader
from tests.api.conftest import AUTH, add_take
from tests.api.fakework import make_take_file, small_calibration, write_legacy_masks


def test_upload_raw_and_multipart_then_read(client, tmp_path, data_root):
    # an upload is the capture file alone: masks travel with it only in the older layout (inside the take)
    src = make_take_file(tmp_path / "a.h5", 3, calibration=small_calibration())
    m = np.zeros((3, 24, 32), bool)
    m[:, 6:18, 8:24] = True
    for c in ("cam00", "cam01"):
        write_legacy_masks(src, c, m)
    r = client.put("/takes/a", content=src.read_bytes(), headers={**AUTH, "Content-Type": "application/x-hdf5"})
    assert r.status_code == 201, r.text
    assert r.json()["id"] == "a" and r.json()["size_bytes"] == src.stat().st_size
    r = client.post("/takes", files={"file": ("b.h5", src.read_bytes(), "application/x-hdf5")}, data={"take": "b"},
                    headers=AUTH)
    assert r.status_code == 201, r.text
    assert [t["id"] for t in client.get("/takes").json()] == ["a", "b"]
    info = client.get("/takes/a").json()
    assert info["frames"] == 3 and [c["id"] for c in info["cameras"]] == ["cam00", "cam01"]
    assert info["cameras"][0]["width"] == 32 and info["masks"] == ["cam00", "cam01"]
    assert info["calibration"]["cameras"][1]["name"] == "cam01"
    # a frame and its mask, decoded back and compared with the store
    png = client.get("/takes/a/frames/2/cam01/image.png")
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    img = cv2.imdecode(np.frombuffer(png.content, np.uint8), cv2.IMREAD_COLOR)
    with TakeReader(data_root / "takes" / "a.h5") as rd:
        np.testing.assert_array_equal(img, rd.frame("cam01", 2))
        mask_ref = rd.masks("cam01")[2]
    jpg = client.get("/takes/a/frames/0/cam00/image.jpg")
    assert jpg.status_code == 200 and jpg.content[:2] == b"\xff\xd8"
    m = client.get("/takes/a/frames/2/cam01/mask.png")
    mask = cv2.imdecode(np.frombuffer(m.content, np.uint8), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(mask > 127, mask_ref)


def test_import_from_path_and_delete(client, data_root):
    (data_root / "incoming").mkdir(parents=True)
    make_take_file(data_root / "incoming" / "x.h5", 2)
    r = client.post("/takes/import", json={"take": "x", "path": "incoming/x.h5"}, headers=AUTH)
    assert r.status_code == 201, r.text
    assert client.get("/takes/x").json()["frames"] == 2
    assert client.delete("/takes/x", headers=AUTH).status_code == 204
    assert client.get("/takes/x").status_code == 404
    assert client.delete("/takes/x", headers=AUTH).status_code == 404


def test_delete_refused_while_a_job_uses_the_take(make_client, data_root):
    c = make_client(work="tests.api.fakework:process_take")
    add_take(data_root, "busy", frames=30)
    job = c.post("/jobs", json={"take": "busy", "parameters": {"delay_s": 0.05}}, headers=AUTH).json()
    r = c.delete("/takes/busy", headers=AUTH)
    assert r.status_code == 409 and job["id"] in r.json()["detail"]
    c.post(f"/jobs/{job['id']}/cancel", headers=AUTH)


def test_invalid_input(client, tmp_path, data_root):
    src = make_take_file(tmp_path / "a.h5", 2)
    body = src.read_bytes()
    h5 = {"Content-Type": "application/x-hdf5"}
    # token
    assert client.put("/takes/a", content=body, headers=h5).status_code == 401
    assert client.put("/takes/a", content=body, headers={**h5, "Authorization": "Bearer x"}).status_code == 403
    assert client.delete("/takes/a").status_code == 401
    assert client.post("/takes/import", json={"take": "a", "path": "a.h5"}).status_code == 401
    # content
    assert client.put("/takes/a", content=b"hello", headers={**AUTH, **h5}).status_code == 400
    fake = b"\x89HDF\r\n\x1a\n" + b"\0" * 100
    r = client.put("/takes/a", content=fake, headers={**AUTH, **h5})
    assert r.status_code == 400 and str(data_root) not in r.text
    assert client.put("/takes/a", content=body, headers={**AUTH, "Content-Type": "text/plain"}).status_code == 415
    big = b"\0" * (2 << 20)  # limit is 1 MiB in the tests
    assert client.put("/takes/a", content=big, headers={**AUTH, **h5}).status_code == 413

    def chunks():
        for _ in range(3):
            yield b"\0" * (512 << 10)

    assert client.put("/takes/a", content=chunks(), headers={**AUTH, **h5}).status_code == 413  # no Content-Length
    assert client.post("/takes", files={"file": ("a.h5", big)}, data={"take": "a"}, headers=AUTH).status_code == 413
    assert client.post("/takes", data={"take": "a"}, headers=AUTH).status_code in (415, 422)
    assert client.post("/takes", files={"file": ("a.h5", body)}, headers=AUTH).status_code == 422
    assert client.post("/takes", files={"file": ("a.h5", body)}, data={"take": "../a"}, headers=AUTH).status_code == 400
    assert list((data_root / "takes").iterdir()) == []  # nothing left behind
    # exists
    assert client.put("/takes/a", content=body, headers={**AUTH, **h5}).status_code == 201
    assert client.put("/takes/a", content=body, headers={**AUTH, **h5}).status_code == 409
    # traversal and bad ids
    for bad in ("..%2F..%2Fetc%2Fpasswd", ".hidden", "a..b", "%2e%2e", "a%00b"):
        assert client.get(f"/takes/{bad}").status_code in (400, 404), bad
    (tmp_path / "outside.h5").write_bytes(body)
    for path in ("../outside.h5", str(tmp_path / "outside.h5"), "takes/../../outside.h5", ""):
        r = client.post("/takes/import", json={"take": "o", "path": path}, headers=AUTH)
        assert r.status_code in (400, 422), (path, r.status_code)
    (data_root / "link.h5").symlink_to(tmp_path / "outside.h5")
    assert client.post("/takes/import", json={"take": "o", "path": "link.h5"}, headers=AUTH).status_code == 400
    assert client.post("/takes/import", json={"take": "o", "path": "nope.h5"}, headers=AUTH).status_code == 404
    # unknown take, camera, frame, view name
    assert client.get("/takes/nope").status_code == 404
    assert client.get("/takes/a/frames/0/cam09/image.png").status_code == 404
    assert client.get("/takes/a/frames/5/cam00/image.png").status_code == 404
    assert client.get("/takes/a/frames/0/cam00/mask.png").status_code == 404  # not keyed
    assert client.get("/takes/a/frames/0/cam00/image.gif").status_code in (400, 422)
    assert client.get("/takes/a/frames/-1/cam00/image.png").status_code in (400, 422)


def test_import_from_path_with_masks(client, data_root):
    """Silhouettes made elsewhere come with the take (one folder per camera); bad ones are one
    error naming the camera and file, and nothing is imported."""
    from calib.calibration import Calibration
    from calib.camera import Camera

    cams = tuple(Camera(f"cam{i:02d}", K=[[30, 0, 16], [0, 30, 12], [0, 0, 1]], dist=np.zeros(5), R=np.eye(3),
                        t=[i * 10.0, 0, 100], size=(32, 24)) for i in range(2))
    inc = data_root / "incoming"
    inc.mkdir(parents=True)
    make_take_file(inc / "m.h5", 3, calibration=Calibration(cams))
    for c in ("cam00", "cam01"):
        (inc / "m_masks" / c).mkdir(parents=True)
        for k in range(3):
            a = np.zeros((24, 32), np.uint8)
            a[5 + k : 15, 8:20] = 255
            cv2.imwrite(str(inc / "m_masks" / c / f"{k}.png"), a)
    cv2.imwrite(str(inc / "m_masks" / "cam01" / "2.png"), np.zeros((20, 32), np.uint8))
    r = client.post("/takes/import", json={"take": "m", "path": "incoming/m.h5", "masks": "incoming/m_masks"},
                    headers=AUTH)
    assert r.status_code == 400 and "camera cam01" in r.text and "2.png is 32x20" in r.text, r.text
    assert client.get("/takes/m").status_code == 404
    a = np.zeros((24, 32), np.uint8)
    a[7:15, 8:20] = 255
    cv2.imwrite(str(inc / "m_masks" / "cam01" / "2.png"), a)
    r = client.post("/takes/import", json={"take": "m", "path": "incoming/m.h5", "masks": "incoming/m_masks"},
                    headers=AUTH)
    assert r.status_code == 201, r.text
    assert client.get("/takes/m").json()["masks"] == ["cam00", "cam01"]
    with TakeReader(data_root / "takes" / "m.h5") as rd:
        np.testing.assert_array_equal(rd.masks("cam01")[2], a > 0)
