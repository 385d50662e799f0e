"""Every id form on every route: a bad id is 400 (or 404 when it is well formed but unknown),
never a 5xx, and no request reaches a file outside the data root or a file kept beside a take
(``TAKE.derived.h5``, its masks: ``DELETE /takes/X.derived`` must not delete them)."""

from __future__ import annotations

import re
from urllib.parse import quote

import pytest

from api.paths import InvalidIdError, OutsideDataRootError, check_take_id, inside
from api.routers import calibrations, jobs, pages, rig, takes
from tests.api.conftest import AUTH, add_take

#: id forms a hostile client sends (raw; each is URL-quoted before it is sent)
FORMS = [
    "take1.derived", "take1.DERIVED", "take1.gt", "take1.template", "take1.part", "x.tmp",
    ".", "..", "...", ".hidden", "../take1", "../../etc/passwd", "a/b", "a\\b", "take1\x00", "\x00",
    "é" * 200, "é" * 64, "a" * 129, "a" * 300, " ", "take1 ", "-take1", "take1.h5", "0" * 32, "g" * 32,
    "%2e%2e", "take1%00",
]
#: a valid value for every other path parameter
VALID = {"take_id": "take1", "job_id": "0" * 32, "cal_id": "0" * 32, "index": "0", "camera": "cam0",
         "name": "image.png", "fmt": "toml", "camera_id": "cam0"}


def _routes():
    out = []
    for mod in (takes, jobs, calibrations, rig, pages):
        for r in mod.router.routes:
            params = re.findall(r"{(\w+)}", r.path)
            for m in sorted(r.methods or ()):
                if params and m != "HEAD":
                    out.append((m, r.path, params))
    return out


ROUTES = _routes()
#: a valid JSON body for the routes that take one (the others get an empty raw body), so that what is judged is the id
BODIES = {("PUT", "/takes/{take_id}/calibration"): {"calibration": "0" * 32}}


def _quoted(form: str) -> str:
    """URL-quoted; a segment of dots alone as %2E (a client would resolve ``.``/``..`` itself)."""
    q = quote(form, safe="")
    return q.replace(".", "%2E") if set(form) <= {"."} else q


def test_every_route_with_an_id_is_covered():
    paths = {p for _, p, _ in ROUTES}
    assert {"/takes/{take_id}", "/jobs/{job_id}", "/calibrations/{cal_id}", "/ui/takes/{take_id}",
            "/takes/{take_id}/frames/{index}/{camera}/{name}"} <= paths
    assert {m for m, p, _ in ROUTES if p == "/takes/{take_id}"} == {"GET", "PUT", "DELETE"}


def test_every_id_form_on_every_route_is_400_or_404(client, data_root, tmp_path):
    take = add_take(data_root, "take1")
    derived = take.with_name("take1.derived.h5")
    derived.write_bytes(take.read_bytes())  # stands for the take's masks
    for name in ("derived", "gt", "template"):
        take.with_name(f"take1.{name}").write_bytes(b"x")
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "passwd.h5").write_bytes(b"secret")
    before = sorted(p.name for p in tmp_path.rglob("*") if not p.is_relative_to(data_root))
    seen = 0
    for method, path, params in ROUTES:
        for param in params:
            if param not in ("take_id", "job_id", "cal_id", "camera", "camera_id"):
                continue
            for form in FORMS:
                url = path
                for p in params:
                    url = url.replace("{" + p + "}", _quoted(form) if p == param else VALID[p])
                body = BODIES.get((method, path))
                if body is None:
                    r = client.request(method, url, headers={**AUTH, "Content-Type": "application/x-hdf5"}, content=b"")
                else:
                    r = client.request(method, url, headers=AUTH, json=body)
                seen += 1
                no_rig = path.startswith("/rig") and r.status_code == 503 and "no rig file" in r.text  # none set up
                assert r.status_code < 500 or no_rig, (method, url, r.status_code, r.text[:200])
                if form != "0" * 32 or param not in ("job_id", "cal_id"):
                    assert no_rig or r.status_code in (400, 404) or (
                        method == "PUT" and r.status_code in (400, 409)), (method, url, r.status_code, r.text[:200])
                assert derived.is_file() and take.is_file(), (method, url)
    assert seen > 300
    # a malformed id with a body that is wrong too is a bad request (the URL names nothing), not an unprocessable body
    r = client.put("/takes/take1.derived/calibration", headers=AUTH, json={})
    assert r.status_code == 400 and "take_id" in r.json()["detail"] and "body" not in r.text, r.text
    assert sorted(p.name for p in tmp_path.rglob("*") if not p.is_relative_to(data_root)) == before
    assert (outside / "passwd.h5").read_bytes() == b"secret"
    # the take's own routes still work: the rule refuses only what it must
    assert client.get("/takes/take1", headers=AUTH).status_code == 200
    assert [t["id"] for t in client.get("/takes", headers=AUTH).json()] == ["take1"]


def test_delete_of_the_derived_file_is_refused_and_the_masks_stay(client, data_root):
    take = add_take(data_root, "starfish")
    derived = take.with_name("starfish.derived.h5")
    derived.write_bytes(take.read_bytes())
    r = client.delete("/takes/starfish.derived", headers=AUTH)
    assert r.status_code == 400 and ".derived" in r.json()["detail"]
    assert derived.is_file()
    r = client.put("/takes/starfish.derived", headers={**AUTH, "Content-Type": "application/x-hdf5"}, content=b"x")
    assert r.status_code == 400 and derived.is_file()


def test_body_limits_per_route(client, data_root):
    """``POST /takes/import`` is a small JSON document: a 2 MiB body is 413 before it is read
    (the upload limit of the test app is 1 MiB; the real default is 8 GiB)."""
    big = b'{"take": "t", "path": "' + b"a" * (2 << 20) + b'"}'
    r = client.post("/takes/import", headers={**AUTH, "Content-Type": "application/json"}, content=big)
    assert r.status_code == 413
    r = client.post("/jobs", headers={**AUTH, "Content-Type": "application/json"}, content=big)
    assert r.status_code == 413
    # a long multibyte path in a small body: 400, not "File name too long"
    r = client.post("/takes/import", headers=AUTH, json={"take": "t2", "path": "é" * 200 + ".h5"})
    assert r.status_code == 400, r.text
    r = client.post("/takes/import", headers=AUTH, json={"take": "t2.derived", "path": "x.h5"})
    assert r.status_code == 422, r.text


def test_check_take_id_invalid_input():
    assert check_take_id("take_1.b-2") == "take_1.b-2"
    for bad in ("x.derived", "X.Derived", "x.gt", "..", "a/b", "é", "a" * 129, "", "x\x00", 3):
        with pytest.raises(InvalidIdError):
            check_take_id(bad)


def test_inside_counts_bytes(tmp_path):
    assert inside(tmp_path, "é" * 126 + ".h5").name.startswith("é")  # 255 bytes: a file name the disk takes
    with pytest.raises(OutsideDataRootError, match="bytes"):
        inside(tmp_path, "é" * 127 + ".h5")  # 257 bytes in 130 characters
    with pytest.raises(OutsideDataRootError):
        inside(tmp_path, "a\x00b")


def test_a_malformed_path_parameter_is_said_as_what_it_is(client, data_root):
    """A path parameter that fails its pattern is a 400 saying what the parameter is (its description) or what it
    looks like (its examples), with the value sent, not the regular expression; ``errors`` keeps pydantic's."""
    add_take(data_root, "take1")
    jid = client.post("/jobs", json={"take": "take1", "steps": ["key"]}, headers=AUTH).json()["id"]
    for url, said in (
            ("/jobs/xyz", "path.job_id: 'xyz' is not a job id (32 hex digits)"),
            ("/jobs/xyz/events", "path.job_id: 'xyz' is not a job id (32 hex digits)"),
            ("/calibrations/zz.json", "path.cal_id: 'zz' is not a calibration id (32 hex digits)"),
            ("/takes/take1/frames/0/cam%20x/image.png", "path.camera: 'cam x' is not a camera id (1 to 64 letters, "
                                                        "digits, _ . -)"),
            (f"/jobs/{jid}/results/meshes/zero.ply",
             "path.name: 'zero.ply' does not look like any of 'frame_000000.ply', '3.glb'"),
            (f"/jobs/{jid}/results/rig/posed/1.ply", "path.name: '1.ply' does not look like '000003.ply'"),
            (f"/jobs/{jid}/results/tracked/3.ply", "path.name: '3.ply' does not look like any of '000003.ply', "
                                                   "'track.json', 'labels.npy', 'rig_segments.npy'")):
        r = client.get(url)
        assert r.status_code == 400 and r.json()["detail"] == said, (url, r.json())
        assert [e["type"] for e in r.json()["errors"]] == ["string_pattern_mismatch"], r.json()
