"""Jobs over the API with the fake work (contract of pipeline.process.process_take): create, status, SSE, cancel, results."""

from __future__ import annotations

import io
import json
import re
from types import SimpleNamespace

import numpy as np

from api.jobs.store import JobStore
from tests.api.conftest import AUTH, add_take, wait_job


def test_job_runs_to_done_with_progress_and_results(client, data_root):
    add_take(data_root, "take1", frames=5)
    r = client.post("/jobs", json={"take": "take1", "steps": ["key", "surface", "spine"]}, headers=AUTH)
    assert r.status_code == 202, r.text
    job = r.json()
    assert r.headers["location"] == f"/jobs/{job['id']}"
    assert job["state"] in ("queued", "running")
    st = wait_job(client, job["id"])
    assert st["state"] == "done", st
    assert st["progress"] == {"key": {"done": 5, "total": 5, "step": "key"},
                              "surface": {"done": 5, "total": 5, "step": "surface"},
                              "spine": {"done": 5, "total": 5, "step": "spine"}}
    assert st["done"] == st["total"] == 15
    assert st["attempts"] == 1 and st["error"] is None
    listing = client.get(f"/jobs/{job['id']}/results/").json()
    assert listing["files"] == ["spine.json", "report.json"] and listing["meshes"] == [0, 1, 2, 3, 4]
    spine = client.get(f"/jobs/{job['id']}/results/spine.json")
    assert spine.status_code == 200 and len(spine.json()["frames"]) == 5
    assert client.get(f"/jobs/{job['id']}/results/report.json").json()["frames"] == 5
    ply = client.get(f"/jobs/{job['id']}/results/meshes/frame_000002.ply")
    assert ply.status_code == 200 and ply.content.startswith(b"ply")
    glb = client.get(f"/jobs/{job['id']}/results/meshes/2.glb")
    assert glb.status_code == 200 and glb.content[:4] == b"glTF"
    sg = client.get(f"/jobs/{job['id']}/results/spine.glb")
    assert sg.status_code == 200 and sg.content[:4] == b"glTF"
    assert client.get(f"/jobs/{job['id']}/results/meshes/frame_000009.ply").status_code == 404
    # listed
    assert [j["id"] for j in client.get("/jobs").json()] == [job["id"]]
    assert client.get("/jobs", params={"state": "queued"}).json() == []


def _parse_sse(text: str) -> list[dict]:
    events = []
    for block in text.strip().split("\n\n"):
        ev = {}
        for line in block.splitlines():
            if line.startswith(":"):
                continue
            k, _, v = line.partition(": ")
            ev[k] = v if k != "data" else json.loads(v)
        if ev:
            events.append(ev)
    return events


def test_sse_stream_and_resume_with_last_event_id(client, data_root):
    add_take(data_root, "t", frames=4)
    job = client.post("/jobs", json={"take": "t", "parameters": {"delay_s": 0.01}}, headers=AUTH).json()
    with client.stream("GET", f"/jobs/{job['id']}/events") as r:
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
        text = "".join(r.iter_text())
    events = _parse_sse(text)
    assert events[0]["event"] == "status"
    prog = [e for e in events if e.get("event") == "progress"]
    ids = [int(e["id"]) for e in prog]
    assert ids == sorted(ids) and len(set(ids)) == len(ids)
    assert ids[-1] == 12
    for e in prog:
        assert int(e["id"]) == e["data"]["done"]
    assert events[-1]["event"] == "end" and events[-1]["data"]["state"] == "done"
    # reconnect after id 6: only later events, then end
    with client.stream("GET", f"/jobs/{job['id']}/events", headers={"Last-Event-ID": "6"}) as r:
        again = _parse_sse("".join(r.iter_text()))
    later = [int(e["id"]) for e in again if e.get("event") == "progress"]
    assert later == [i for i in ids if i > 6]
    assert again[-1]["event"] == "end"


def test_cancel_running_and_queued(client, data_root):
    add_take(data_root, "t", frames=40)
    a = client.post("/jobs", json={"take": "t", "parameters": {"delay_s": 0.05}}, headers=AUTH).json()
    b = client.post("/jobs", json={"take": "t"}, headers=AUTH).json()
    wait_job(client, a["id"], states=("running",))
    rb = client.post(f"/jobs/{b['id']}/cancel", headers=AUTH)
    assert rb.status_code == 200 and rb.json()["state"] == "cancelled"
    ra = client.post(f"/jobs/{a['id']}/cancel", headers=AUTH)
    assert ra.status_code == 200 and ra.json()["cancel_requested"]
    st = wait_job(client, a["id"])
    assert st["state"] == "cancelled"
    assert client.post(f"/jobs/{a['id']}/cancel", headers=AUTH).status_code == 409
    # deleting a take in use is refused while a job is active; finished jobs can be deleted
    assert client.delete(f"/jobs/{a['id']}", headers=AUTH).status_code == 204
    assert client.get(f"/jobs/{a['id']}").status_code == 404
    assert not (data_root / "jobs" / a["id"]).exists()


def test_failed_job_reports_error(client, data_root):
    (data_root / "takes").mkdir(parents=True, exist_ok=True)
    (data_root / "takes" / "bad.h5").write_bytes(b"\x89HDF\r\n\x1a\nnot really")
    job = client.post("/jobs", json={"take": "bad"}, headers=AUTH).json()
    st = wait_job(client, job["id"])
    assert st["state"] == "failed" and st["error"].startswith("take: not readable")
    assert "Traceback" not in st["error"]


def test_invalid_input(client, data_root):
    add_take(data_root, "t", frames=2)
    # auth
    assert client.post("/jobs", json={"take": "t"}).status_code == 401
    assert client.post("/jobs", json={"take": "t"}, headers={"Authorization": "Bearer nope"}).status_code == 403
    assert client.post("/jobs", json={"take": "t"}, headers={"Authorization": "Basic abc"}).status_code == 401
    # bad body
    assert client.post("/jobs", json={"take": "../etc"}, headers=AUTH).status_code == 422
    assert client.post("/jobs", json={"take": "t", "steps": ["fly"]}, headers=AUTH).status_code == 400
    assert client.post("/jobs", json={"take": "t", "steps": []}, headers=AUTH).status_code == 400
    r = client.post("/jobs", json={"take": "t", "parameters": {"delay_s": -1}}, headers=AUTH)
    assert r.status_code == 400 and "delay_s" in r.json()["detail"]
    assert client.post("/jobs", json={"take": "t", "parameters": {"nope": 1}}, headers=AUTH).status_code == 400
    assert client.post("/jobs", json={"take": "t", "extra": 1}, headers=AUTH).status_code == 422
    assert client.post("/jobs", json={"take": "missing"}, headers=AUTH).status_code == 404
    # unknown / malformed ids
    unknown = "0" * 32
    for path in (f"/jobs/{unknown}", f"/jobs/{unknown}/events", f"/jobs/{unknown}/results/",
                 f"/jobs/{unknown}/results/spine.json"):
        assert client.get(path).status_code == 404, path
    assert client.post(f"/jobs/{unknown}/cancel", headers=AUTH).status_code == 404
    for bad in ("abc", "%2e%2e%2fetc", "A" * 32):  # a bare ".." is normalised to "/" by the client
        assert client.get(f"/jobs/{bad}").status_code in (400, 404), bad
    job = client.post("/jobs", json={"take": "t"}, headers=AUTH).json()
    wait_job(client, job["id"])
    for name in ("..%2Fjobs.sqlite", "%2e%2e", "secret.txt", "meshes/..%2F..%2Fjobs.sqlite"):
        r = client.get(f"/jobs/{job['id']}/results/{name}")
        assert r.status_code in (400, 404), (name, r.status_code)
        assert b"SQLite" not in r.content
    # errors are JSON with a message
    r = client.get(f"/jobs/{unknown}")
    assert r.headers["content-type"] == "application/json" and "no job" in r.json()["detail"]


def test_read_protected(make_client, data_root):
    c = make_client(read_protected=True)
    assert c.get("/jobs").status_code == 401
    assert c.get("/jobs", headers=AUTH).status_code == 200
    assert c.get("/takes").status_code == 401
    assert c.get("/health").status_code == 200


def test_no_token_configured_refuses_writes(make_client, data_root):
    c = make_client(api_token=None)
    add_take(data_root, "t", frames=1)
    r = c.post("/jobs", json={"take": "t"}, headers=AUTH)
    assert r.status_code == 403 and "STAGE_API_TOKEN" in r.json()["detail"]
    assert c.get("/jobs").status_code == 200


def test_queued_jobs_survive_restart(make_client, data_root):
    add_take(data_root, "t", frames=3)
    # an app that only queues (runner off), then a new one on the same data root runs the job
    from fastapi.testclient import TestClient

    from api.app import create_app
    from tests.api.conftest import make_settings

    app = create_app(make_settings(data_root), work="tests.api.fakework:process_take", start_runner=False)
    with TestClient(app) as c1:
        jid = c1.post("/jobs", json={"take": "t"}, headers=AUTH).json()["id"]
        assert c1.get(f"/jobs/{jid}").json()["state"] == "queued"
    assert JobStore(data_root / "jobs.sqlite").get(jid).state == "queued"
    c2 = make_client()
    assert wait_job(c2, jid)["state"] == "done"


def test_a_process_job_checks_its_track_options(make_client, data_root):
    """``parameters.track`` are ``stage track``'s options (pipeline.process.TrackParams), checked when the
    job is submitted."""
    add_take(data_root, "t", frames=2)
    c = make_client(work="pipeline.process:process_take")
    for bad in ({"carve": -1}, {"carve": 99}, {"carve_margin": -1}, {"shape_memory": "sometimes"}, {"rounds": 2}):
        r = c.post("/jobs", json={"take": "t", "steps": ["surface", "track"], "parameters": {"track": bad}}, headers=AUTH)
        assert r.status_code == 400 and "track" in r.json()["detail"], (bad, r.json())
    # the armature rounds: bounds, and stage track's rules in the parameters' names
    for bad, said in (({"armature_rounds": 9}, "track.armature_rounds"), ({"armature_rounds": "often"}, "armature_rounds"),
                      ({"spine_armature": True, "armature_rounds": 0},
                       "track.spine_armature needs track.armature_rounds ("),
                      ({"carve_margin": 1.0}, "track.carve_margin needs track.carve ("),
                      ({"armature_rounds": 1, "armature_parts": "limbs"}, "track.armature_parts 'limbs' needs "
                                                                          "track.labels (")):
        r = c.post("/jobs", json={"take": "t", "steps": ["surface", "track"], "parameters": {"track": bad}}, headers=AUTH)
        assert r.status_code == 400 and r.json()["detail"].startswith("parameters: ") and said in r.json()["detail"], \
            (bad, r.json())
        assert "parameters: parameters" not in r.json()["detail"]
    # the rig's parts from the limbs: the tracking has the labels, so the rounds may take their parts from them too
    limbs = {"track": {"armature_parts": "limbs"}, "rig": {"parts": "limbs"}}  # one armature round: the default
    r = c.post("/jobs", json={"take": "t", "steps": ["surface", "track", "rig"], "parameters": limbs}, headers=AUTH)
    assert r.status_code == 202 and r.json()["params"] == limbs, r.json()
    ok = {"track": {"carve": 2, "shape_memory": True, "colour": True, "labels": True}}
    r = c.post("/jobs", json={"take": "t", "steps": ["surface", "track"], "parameters": ok}, headers=AUTH)
    assert r.status_code in (200, 201, 202) and r.json()["params"]["track"]["carve"] == 2, r.json()
    assert r.json()["params"]["track"]["labels"] is True
    fast = {"track": {"labels": True, "colour": True, "armature_rounds": 1, "armature_parts": "limbs"}}  # docs/tracking.md
    r = c.post("/jobs", json={"take": "t", "steps": ["surface", "track"], "parameters": fast}, headers=AUTH)
    # the job keeps the parameters that are not the defaults: one armature round is
    assert r.status_code == 202 and r.json()["params"] == {"track": {"labels": True, "colour": True,
                                                                     "armature_parts": "limbs"}}, r.json()
    r = c.post("/jobs", json={"take": "t", "steps": ["surface", "rig"], "parameters": {"rig": {"parts": "bones"}}}, headers=AUTH)
    assert r.status_code == 400 and "rig" in r.json()["detail"], r.json()
    r = c.post("/jobs", json={"take": "t", "steps": ["surface", "rig"], "parameters": {"rig": {"parts": "limbs"}}}, headers=AUTH)
    assert r.status_code in (200, 201, 202) and r.json()["params"]["rig"]["parts"] == "limbs", r.json()
    # stage armature's --lambda-thr, --samples, --reference, checked by its bounds in the parameters' names
    # a rest frame past the take's frame sets (2) is refused when submitted, naming the parameter; one within them
    # is queued
    for reference, code in ((2, 400), (1, 202)):
        r = c.post("/jobs", json={"take": "t", "steps": ["surface", "rig"], "parameters": {"rig": {"reference": reference}}},
                   headers=AUTH)
        assert r.status_code == code, r.json()
    assert r.json()["params"] == {"rig": {"reference": 1}}
    r = c.post("/jobs", json={"take": "t", "steps": ["surface", "rig"], "parameters": {"rig": {"reference": 2}}}, headers=AUTH)
    assert r.json()["detail"] == ("parameters: rig.reference must be a position within 0..1 (take 't' has 2 frame sets, "
                                  "the most frames a tracking has), got 2"), r.json()
    # (a check's own message, as the command says it: without pydantic's "Value error, " before it)
    for bad, said in (({"samples": 1}, "rig.samples: samples must be >= 2, got 1"),
                      ({"samples": 10**6}, "rig.samples: Input should be less than or equal to 5000"),
                      ({"lambda_thr": 2.5}, "rig.lambda_thr: lambda_thr must be within (0, 2), got 2.5"),
                      ({"reference": -1}, "rig.reference: reference must be a position >= 0")):
        r = c.post("/jobs", json={"take": "t", "steps": ["surface", "rig"], "parameters": {"rig": bad}}, headers=AUTH)
        assert r.status_code == 400 and said in r.json()["detail"], (bad, r.json())
        assert "Value error" not in r.json()["detail"], r.json()
    r = c.post("/jobs", json={"take": "t", "steps": ["surface", "track"],
                              "parameters": {"track": {"carve_margin": 2}}}, headers=AUTH)
    assert r.status_code == 400 and r.json()["detail"] == (
        "parameters: track.carve_margin needs track.carve (the margin of the carving's silhouettes)"), r.json()
    rig = {"rig": {"lambda_thr": 0.98, "samples": 300, "reference": 1}}
    r = c.post("/jobs", json={"take": "t", "steps": ["surface", "rig"], "parameters": rig}, headers=AUTH)
    assert r.status_code == 202 and r.json()["params"] == rig, r.json()


def test_a_jobs_warnings_say_what_its_tracking_fell_back_to(make_client, tmp_path, monkeypatch):
    """An API user who asked for ``armature_parts`` 'limbs' and ``spine_armature`` and got neither reads it in the
    job's warnings, in its parameters, as ``stage track`` prints it to the terminal: the job runs in the runner's
    thread, whose warnings the track step keeps (the tracking stands in: the armature rounds' real fallbacks)."""
    import pipeline.carve as carve
    import pipeline.track_armature as ta
    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take
    from pipeline.track_armature_labels import _limb_chain
    from pipeline.track_armature_models import _spine_rig

    def carving(src, rounds, **k):
        return {"frames": {}, "skipped": []}

    def rounds(src, **k):
        _spine_rig(src, [0, 1], np.zeros((3, 3)), np.zeros((1, 3), np.int64), 0)  # spine.json of other frames
        _limb_chain(src, None, 0, 2)  # no labels from the spine
        return {"frames": {}, "rig_prior": {}}

    monkeypatch.setattr(carve, "track_with_carving", carving)
    monkeypatch.setattr(ta, "track_with_armature", rounds)
    data = tmp_path / "data"
    (data / "takes").mkdir(parents=True)
    record_take(simulate_take("starfish", n_cameras=4, frames=2, size=(160, 120), seed=3), data / "takes" / "t.h5")
    c = make_client(work="pipeline.process:process_take", data=data)
    fast = {"resolution": 32, "track": {"labels": True, "armature_rounds": 1, "spine_armature": True,
                                        "armature_parts": "limbs"}}
    jid = c.post("/jobs", json={"take": "t", "steps": ["key", "surface", "track"], "parameters": fast},
                 headers=AUTH).json()["id"]
    st = wait_job(c, jid, timeout=120)
    assert st["state"] == "done", st
    said = [w for w in st["result"]["report"]["warnings"] if w.startswith("track: ")]
    assert len(said) == 2 and said[0].startswith("track: parameters track.spine_armature: the first armature is built "
                                                 "from the tracking: no usable spine in "), said
    assert said[1] == ("track: parameters track.armature_parts 'limbs': the armature's parts come from the motion: "
                       "no labels")
    assert f"no usable spine in DATA/jobs/{jid}/spine.json" in said[0]  # (the server's folders as the job's results)
    report = json.loads((data / "jobs" / jid / "report.json").read_text())
    assert any(w.startswith("track: ") for w in report["warnings"])


def test_a_jobs_warnings_and_page_say_what_its_frames_warned_of_once_per_kind(make_client, tmp_path):
    """A take whose camera cam02's masks are all foreground in frame sets 1-3 and whose frame set 4 is empty: the
    job's record (``result.report.warnings``) and its page say each once, with the frame sets, as ``stage process``
    says it (tests/pipeline/test_process.py); the page's list is the record's, in order."""
    import html

    from tests.pipeline.hull_scenes import FAILED_MASKS_SAID, take_with_failed_masks

    data = tmp_path / "data"
    (data / "takes").mkdir(parents=True)
    take_with_failed_masks(data / "takes" / "t.h5")
    c = make_client(work="pipeline.process:process_take", data=data)
    jid = c.post("/jobs", json={"take": "t", "steps": ["surface"], "parameters": {"resolution": 32}},
                 headers=AUTH).json()["id"]
    st = wait_job(c, jid, timeout=120)
    assert st["state"] == "done", st
    warned = st["result"]["report"]["warnings"]
    assert [w for w in warned if "silhouette consistency" not in w] == FAILED_MASKS_SAID, warned
    assert st["warnings"] == warned  # (the record's own, in every state)
    page = c.get(f"/ui/jobs/{jid}", headers=AUTH).text
    shown = re.search(r'<ul id="warning-list">(.*?)</ul>', page, re.S).group(1)
    assert [html.unescape(w) for w in re.findall(r"<li>(.*?)</li>", shown)] == warned
    assert f'<span id="nwarn">{len(warned)}</span>' in page


def test_a_failed_jobs_record_and_page_keep_the_warnings_said_before_it_stopped(make_client, tmp_path):
    """The surface step warns of the failed masks' frame sets, then the rig's rest frame past the surfaces (position
    5 of the take's 6 frame sets, of which 5 get a surface) stops the job before it tracks: the failed job (no
    result, no report) has those warnings in its record, in the order said, and its page lists them, as a done
    job's."""
    import html

    from tests.pipeline.hull_scenes import FAILED_MASKS_SAID, take_with_failed_masks

    data = tmp_path / "data"
    (data / "takes").mkdir(parents=True)
    take_with_failed_masks(data / "takes" / "t.h5")
    c = make_client(work="pipeline.process:process_take", data=data)
    jid = c.post("/jobs", json={"take": "t", "steps": ["surface", "track", "rig"],
                                "parameters": {"resolution": 32, "rig": {"reference": 5}}}, headers=AUTH).json()["id"]
    st = wait_job(c, jid, timeout=120)
    assert st["state"] == "failed" and "rig.reference" in st["error"] and st["result"] is None, st
    warned = st["warnings"]
    assert [w for w in warned if "silhouette consistency" not in w] == FAILED_MASKS_SAID, warned
    assert c.get("/jobs", params={"state": "failed"}).json()[0]["warnings"] == warned
    page = c.get(f"/ui/jobs/{jid}", headers=AUTH).text
    shown = re.search(r'<section id="warnings"([^>]*)>.*?<ul id="warning-list">(.*?)</ul>', page, re.S)
    assert "hidden" not in shown.group(1)
    assert [html.unescape(w) for w in re.findall(r"<li>(.*?)</li>", shown.group(2))] == warned
    assert f'<span id="nwarn">{len(warned)}</span>' in page


def test_a_job_on_results_of_other_parameters_starts_over_without_their_tracking_and_rig(make_client, tmp_path):
    """The API's job path (the real work): a job whose folder holds results of other parameters
    removes the tracked frames and the rig built on them, and its result carries the one warning;
    a job of the same parameters on them keeps tracked/ and rig/ untouched."""
    import shutil
    import uuid

    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take

    data = tmp_path / "data"
    (data / "takes").mkdir(parents=True)
    record_take(simulate_take("starfish", n_cameras=4, frames=3, size=(160, 120), seed=3), data / "takes" / "t.h5")
    c = make_client(work="pipeline.process:process_take", data=data)
    steps = ["key", "surface", "spine", "track", "rig"]
    first = c.post("/jobs", json={"take": "t", "steps": steps, "parameters": {"resolution": 32}}, headers=AUTH).json()["id"]
    assert wait_job(c, first, timeout=120)["state"] == "done"
    assert c.get(f"/jobs/{first}/results/spine_rig.glb", headers=AUTH).status_code == 200  # cached in the job's folder
    store = JobStore(data / "jobs.sqlite")

    def job_on_a_copy(params: dict) -> tuple[str, dict]:
        jid = uuid.uuid4().hex
        shutil.copytree(data / "jobs" / first, data / "jobs" / jid)
        store.create(kind="process", take="t", steps=["key", "surface", "spine"], params=params, job_id=jid)
        st = wait_job(c, jid, timeout=120)
        assert st["state"] == "done", st
        return jid, st

    stamps = {p.relative_to(data / "jobs" / first): p.stat().st_mtime_ns
              for s in ("tracked", "rig") for p in (data / "jobs" / first / s).rglob("*") if p.is_file()}
    def warned(st: dict) -> list[str]:
        # set aside: the silhouette consistency's warning (this take's camera 2 is keyed half as much
        # again as its true silhouette at 160x120, and the warning rightly names it every run)
        return [w for w in st["result"]["report"]["warnings"] if "silhouette consistency" not in w]

    same, st = job_on_a_copy({"resolution": 32})
    assert warned(st) == []
    assert {p: (data / "jobs" / same / p).stat().st_mtime_ns for p in stamps} == stamps and len(stamps) >= 9
    other, st = job_on_a_copy({"resolution": 28})
    assert warned(st) == [
        f"DATA/jobs/{other} holds results of other parameters or another take; starting over; removed spine_rig.glb; "
        f"removed the frames tracked on the old surfaces (DATA/jobs/{other}/tracked); "
        f"removed the rig built on them (DATA/jobs/{other}/rig)"]
    d = data / "jobs" / other
    assert not (d / "tracked").exists() and not (d / "rig").exists() and not (d / "spine_rig.glb").exists()
    assert c.get(f"/jobs/{other}/results/spine_rig.glb", headers=AUTH).status_code == 200  # made again, from the new spine


def test_tracked_and_rig_files_are_listed_and_served(client, data_root):
    """What the track and rig steps write (tracked/, rig/rig.json, rig.glb, rig.bvh, rig/posed/): listed
    under /results/ with the rig's segments and joints, and downloadable; absent files are 404."""
    from pipeline.results import ply_bytes
    from stage.cli import main
    from tests.pipeline.shapes import two_bars

    add_take(data_root, "take1", frames=3)
    jid = client.post("/jobs", json={"take": "take1", "steps": ["key", "surface", "spine"]}, headers=AUTH).json()["id"]
    assert wait_job(client, jid)["state"] == "done"
    job_dir = data_root / "jobs" / jid
    assert client.get(f"/jobs/{jid}/results/rig/rig.json").status_code == 404
    assert client.get(f"/jobs/{jid}/results/tracked/000000.ply").status_code == 404
    V, F, _ = two_bars(8)
    (job_dir / "tracked").mkdir()
    for i, v in enumerate(V):
        (job_dir / "tracked" / f"{i:06d}.ply").write_bytes(ply_bytes(v, F))
    assert main(["-q", "rig", str(job_dir), "--samples", "300"]) == 0
    listing = client.get(f"/jobs/{jid}/results/").json()
    assert listing["tracked"] == list(range(8)) and listing["posed"] == list(range(8))
    assert {"rig/rig.json", "rig/rig.glb", "rig/rig.bvh", "rig/segments.npy"} <= set(listing["files"])
    assert listing["rig"]["segments"] == 2 and listing["rig"]["articulations"] == 1
    assert [j["kind"] for j in listing["rig"]["joints"]].count("joint") == 1
    for url in (listing["links"]["rig/rig.json"], listing["links"]["rig/rig.bvh"], listing["links"]["rig/rig.glb"],
                listing["tracked_url"].format(index=3), listing["posed_url"].format(index=7)):
        assert client.get(url).status_code == 200, url
    assert client.get(listing["links"]["rig/rig.json"]).json()["format"] == "capture-stage/rig@1"
    assert client.get(listing["links"]["rig/rig.bvh"]).text.startswith("HIERARCHY")
    assert client.get(listing["links"]["rig/rig.glb"]).content[:4] == b"glTF"
    assert client.get(listing["tracked_url"].format(index=3)).content[:3] == b"ply"
    for bad in ("tracked/000099.ply", "rig/posed/000099.ply", "tracked/3.ply", "rig/other.json", "rig/posed/rig.json"):
        assert client.get(f"/jobs/{jid}/results/{bad}").status_code in (400, 404, 422), bad
    # a name these routes do not serve is refused naming those they do, not with a pattern
    for bad, said in (("rig/rig.fbx", "path.name: Input should be 'rig.json', 'rig.glb', 'rig.bvh' or 'segments.npy'"),
                      ("report.html", "path.name: Input should be 'spine.json', 'report.json', 'spine.glb' or "
                                      "'spine_rig.glb'")):
        r = client.get(f"/jobs/{jid}/results/{bad}")
        assert r.status_code == 400 and r.json()["detail"] == said, r.json()


def test_what_the_tracking_did_is_listed_and_served(client, data_root):
    """``tracked/track.json`` (the tracking's options, reference frame, kept armature round), ``tracked/labels.npy``
    (a tracking with the template's labels) and ``tracked/rig_segments.npy`` (the kept round's limbs armature's
    segments): listed under /results/ once written, served as they are with their media types; absent, 404; other
    names under tracked/ are refused."""
    add_take(data_root, "take1", frames=2)
    jid = client.post("/jobs", json={"take": "take1", "steps": ["key", "surface"]}, headers=AUTH).json()["id"]
    assert wait_job(client, jid)["state"] == "done"
    base = f"/jobs/{jid}/results"
    for name in ("track.json", "labels.npy", "rig_segments.npy"):
        r = client.get(f"{base}/tracked/{name}")
        assert r.status_code == 404 and f"tracked/{name} is not available" in r.json()["detail"], r.json()
    assert not any(f.startswith("tracked/") for f in client.get(f"{base}/").json()["files"])
    tracked = data_root / "jobs" / jid / "tracked"
    tracked.mkdir()
    report = {"mode": "multi-view", "reference_frame": 1, "colour_tracks": True, "rig_rounds": 1,
              "rig_prior": {"kept_round": 1, "parts": "limbs"}, "frames": {"0": {}, "1": {}}}
    (tracked / "track.json").write_text(json.dumps(report))
    listing = client.get(f"{base}/").json()
    assert "tracked/track.json" in listing["files"] and "tracked/labels.npy" not in listing["files"]
    r = client.get(listing["links"]["tracked/track.json"])
    assert r.status_code == 200 and r.headers["content-type"].startswith("application/json") and r.json() == report
    assert client.get(f"{base}/tracked/labels.npy").status_code == 404  # a tracking without labels
    labels = np.array([-1, 0, 0, 1], dtype=np.int64)
    with (tracked / "labels.npy").open("wb") as f:
        np.save(f, labels)
    listing = client.get(f"{base}/").json()
    assert {"tracked/track.json", "tracked/labels.npy"} <= set(listing["files"])
    r = client.get(listing["links"]["tracked/labels.npy"])
    assert r.status_code == 200 and r.headers["content-type"] == "application/octet-stream"
    assert np.array_equal(np.load(io.BytesIO(r.content)), labels)
    r = client.get(f"{base}/tracked/rig_segments.npy")  # a tracking without a limbs armature round
    assert r.status_code == 404 and "no armature round with the limbs' parts" in r.json()["detail"], r.json()
    assert "tracked/rig_segments.npy" not in listing["files"]
    segments = np.array([0, 0, 1, 2], dtype=np.int64)
    with (tracked / "rig_segments.npy").open("wb") as f:
        np.save(f, segments)
    listing = client.get(f"{base}/").json()
    assert {"tracked/track.json", "tracked/labels.npy", "tracked/rig_segments.npy"} <= set(listing["files"])
    r = client.get(listing["links"]["tracked/rig_segments.npy"])
    assert r.status_code == 200 and r.headers["content-type"] == "application/octet-stream"
    assert np.array_equal(np.load(io.BytesIO(r.content)), segments)
    for bad in ("other.json", "track.json.bak", "labels.npz", "rig.json", "segments.npy", "rig_segments.npyx"):
        assert client.get(f"{base}/tracked/{bad}").status_code in (400, 404), bad


def test_a_work_result_with_non_finite_numbers_is_served_as_strict_json():
    """A work function's result holding NaN or an infinity (a figure with nothing to measure) is kept with null
    there: the API serves job records as strict JSON (no NaN), which would otherwise fail on every GET of the job;
    every other value is kept as JSON reads it back."""
    from api.jobs.runner import _jsonable

    got = _jsonable({"rms": float("nan"), "per": [1.5, np.float32(np.inf)], "arr": np.array([0.0, -np.inf]),
                     "n": np.int64(3)})
    assert got == {"rms": None, "per": [1.5, None], "arr": [0.0, None], "n": 3}
    json.dumps(got, allow_nan=False)
    odd = _jsonable({"other": object, "rms": float("-inf")})  # no JSON form: its str, the number null all the same
    assert odd == {"other": str(object), "rms": None}


def test_a_process_job_that_cannot_run_says_what_to_do_in_the_words_of_a_job(make_client, data_root):
    """The API's job path (the real work) on takes it cannot process: no calibration, a damaged frame, masks
    without a subject. The job's error names the job's parameters and the API, never a command line option or
    ``stage`` command; ``stage process`` (the same ProcessError) keeps its own words."""
    import h5py
    import pytest

    from pipeline.process import ProcessError, process_take
    from stage.store import write_masks
    from tests.api.fakework import make_take_file, ring_calibration, small_calibration

    takes = data_root / "takes"
    takes.mkdir(parents=True)
    make_take_file(takes / "nocal.h5", 2)
    bad = make_take_file(takes / "bad.h5", 3, calibration=small_calibration())
    with h5py.File(bad, "r") as f:  # flip 16 bytes in the middle of camera cam01's frame 1
        info = f["cameras/cam01/image"].id.get_chunk_info_by_coord((1, 0, 0, 0))
    with open(bad, "r+b") as fh:
        fh.seek(info.byte_offset + info.size // 2)
        data = fh.read(16)
        fh.seek(info.byte_offset + info.size // 2)
        fh.write(bytes(x ^ 0xFF for x in data))
    empty = make_take_file(takes / "empty.h5", 2, cameras=3, calibration=ring_calibration(3))
    for cam in ("cam00", "cam01", "cam02"):
        write_masks(empty, cam, np.zeros((2, 24, 32), bool))
    c = make_client(work="pipeline.process:process_take")
    cases = [("nocal", None, "a job processes a take recorded or imported with its calibration", "`stage calibrate`"),
             ("bad", None, "parameters.skip_damaged = true processes", "--skip-damaged"),
             ("empty", ["surface"], "check the masks: /ui/takes/empty shows each camera's, e.g. "
              "/takes/empty/frames/0/cam00/mask.png)", "`stage key --preview`")]
    for take, steps, job_words, cli_words in cases:
        jid = c.post("/jobs", json={"take": take, "steps": steps}, headers=AUTH).json()["id"]
        st = wait_job(c, jid, timeout=60)
        assert st["state"] == "failed" and job_words in st["error"], st
        assert "--" not in st["error"] and "stage " not in st["error"] and "\n" not in st["error"], st["error"]
        for url in re.findall(r"(?<!\w)/(?:ui/)?takes/[^\s,)]+", st["error"]):  # the error's links answer (no placeholder)
            assert c.get(url, headers=AUTH).status_code == 200, (url, st["error"])
        with pytest.raises(ProcessError) as exc:
            process_take(takes / f"{take}.h5", data_root / "cli" / take, steps=steps)
        assert cli_words in str(exc.value) and exc.value.job_message == st["error"].replace("DATA/", f"{data_root}/")


def test_every_process_error_that_names_a_command_says_it_in_a_jobs_words_too():
    """Every ``ProcessError(...)`` of pipeline/process whose message names a command line option or a ``stage``
    command gives ``job_message`` (what a job's error shows), and that one names neither: a new error of the
    processing cannot send an API user to the command line (the messages read from the source)."""
    import ast
    from pathlib import Path

    import pipeline.process

    def text(node) -> str:  # the literal parts of a message (f-strings' too; concatenations)
        return " ".join(n.value for n in ast.walk(node) if isinstance(n, ast.Constant) and isinstance(n.value, str))

    def cli(s: str) -> bool:
        return "--" in s or "`stage " in s or "stage calibrate" in s or "stage verify" in s

    seen, bad = 0, []
    for path in sorted(Path(pipeline.process.__file__).parent.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "ProcessError" and node.args:
                seen += 1
                job = [k.value for k in node.keywords if k.arg == "job_message"]
                if cli(text(node.args[0])) and (not job or cli(text(job[0]))):
                    bad.append(f"{path.name}:{node.lineno}")
                if job and cli(text(job[0])):
                    bad.append(f"{path.name}:{node.lineno} (job_message)")
    assert seen >= 8 and not bad, (seen, bad)


def test_a_job_whose_steps_need_surfaces_it_does_not_make_is_refused_when_submitted(make_client, data_root):
    """A job's results start in an empty folder: spine, track or rig without the surface step could only fail (a
    surface job's results are another job's). Refused at once (400), naming the steps to give; with the surface step
    the same job is queued. The track step run on a folder without surfaces still says which step makes them."""
    import pytest

    from pipeline.process import ProcessParams, check_job_steps
    from pipeline.process.steps import _step_track

    add_take(data_root, "t", frames=2)
    c = make_client(work="pipeline.process:process_take")
    for steps, need in ((["rig"], "rig works"), (["track", "rig"], "track, rig work"), (["spine"], "spine works"),
                        (["key", "track"], "track works")):
        r = c.post("/jobs", json={"take": "t", "steps": steps}, headers=AUTH)
        assert r.status_code == 400, r.json()
        assert r.json()["detail"].startswith(f"steps: {need} on the surfaces the job makes itself (a job's results "
                                             "start empty): add the surface step, e.g. steps ['key', 'surface', 'spine'")
    r = c.post("/jobs", json={"take": "t", "steps": ["refine", "rig"]}, headers=AUTH)  # the example keeps what was given
    assert r.status_code == 400 and r.json()["detail"].endswith("e.g. steps ['key', 'refine', 'surface', 'spine', 'rig']")
    assert c.get("/jobs").json() == []  # nothing of the refused ones was queued
    r = c.post("/jobs", json={"take": "t", "steps": ["surface", "track", "rig"]}, headers=AUTH)
    assert r.status_code == 202 and r.json()["steps"] == ["surface", "track", "rig"]
    for bad in ("rig", ["rig", 3], None):
        with pytest.raises(ValueError, match="steps must be a sequence of step names"):
            check_job_steps(bad)
    ctx = SimpleNamespace(out=data_root / "empty", params=ProcessParams(), steps=("track",))
    with pytest.raises(ValueError, match="track: the take has no surfaces to track yet .*: run the surface step first"):
        _step_track(ctx)
