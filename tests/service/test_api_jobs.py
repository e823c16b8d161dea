"""/v1/jobs: creation rules, dispatch through the embedded broker (no worker runs here: the
job store is driven directly, as a worker would), cursor pagination, cancel / retry / delete
rules, logs by offset, and server-sent events that resume with Last-Event-ID."""

from __future__ import annotations

import json
import sqlite3
import threading
import time

import pytest
from sqlalchemy import update

from service_harness import capture_variant, upload_file

import service.events as service_events
from worker.models import Job
from worker.store import Owner

PARAMS = {"preset": "test"}


def parse_sse(text: str) -> list[dict]:
    events = []
    for block in text.split("\n\n"):
        fields = {}
        for line in block.splitlines():
            if line.startswith(":"):
                fields.setdefault("comment", line)
                continue
            key, _, value = line.partition(": ")
            fields[key] = value
        if "data" in fields:
            fields["data"] = json.loads(fields["data"])
            fields["id"] = int(fields["id"]) if "id" in fields else None
            events.append(fields)
        elif fields:
            events.append(fields)
    return events


def run_job(store, job_id: str, *, outcome: str = "succeeded", steps: int = 3) -> None:
    """What a worker does to the store: claim, report progress, finish."""
    owner = Owner.current()
    assert store.claim(job_id, owner, 30, 3).status == "claimed"
    for i in range(steps):
        store.heartbeat(job_id, owner, 30, {"fraction": (i + 1) / (steps + 1), "stage": "train",
                                            "iteration": i + 1, "iterations": steps})
    error = {"code": "internal", "message": "boom", "retryable": True} if outcome == "failed" \
        else None
    assert store.finish(job_id, owner, outcome, error)


@pytest.fixture
def capture_id(ready_capture) -> str:
    return ready_capture()


def test_create_job(client, services, capture_id):
    r = client.post("/v1/jobs", json={"capture_id": capture_id, "params": PARAMS,
                                      "name": "first"})
    assert r.status_code == 202, r.text
    job = r.json()
    assert r.headers["Location"].endswith(f"/v1/jobs/{job['id']}")
    assert job["state"] == "queued" and job["name"] == "first" and job["attempts"] == 0
    assert job["params"]["preset"] == "test" and job["params"]["gop"] is None  # config.gop
    assert job["progress"]["fraction"] == 0.0 and job["links"]["events"].endswith("/events")
    broker = services.settings.data_dir / "broker.sqlite3"
    with sqlite3.connect(broker) as db:
        payloads = [row[0] for row in db.execute("SELECT payload FROM kombu_message")]
    assert any(job["id"] in p for p in payloads)  # handed to the broker for a worker
    assert services.store.get(job["id"]).dispatched_at is not None


@pytest.mark.parametrize("body, status, words", [
    ({"capture_id": "cap_nope"}, 404, "no capture"),
    ({"params": {"preset": "huge"}}, 422, "params.preset"),
    ({"params": {"gop": 0}}, 422, "params.gop"),
    ({"params": {"unknown": 1}}, 422, "params.unknown"),
    ({"pipeline": "relight"}, 422, "pipeline"),
])
def test_job_requests_that_are_refused(client, capture_id, body, status, words):
    r = client.post("/v1/jobs", json={"capture_id": capture_id, **body})
    assert r.status_code == status and words in r.json()["error"]["message"], r.text
    assert client.get("/v1/jobs").json()["items"] == []


def test_a_capture_must_be_ready(client, new_capture):
    capture = new_capture({"a": b"1"}, fmt="auto")
    r = client.post("/v1/jobs", json={"capture_id": capture["id"]})
    assert r.status_code == 409 and "commit it first" in r.json()["error"]["message"]


def test_a_broker_that_is_away_leaves_the_job_to_the_sweeper(tmp_path, synth_capture):
    from fastapi.testclient import TestClient
    from service_harness import make_settings

    from service.app import create_app
    from worker.models import Capture

    settings = make_settings(tmp_path / "d", broker_url="redis://127.0.0.1:9/0")
    client = TestClient(create_app(settings))
    services = client.app.state.services
    store = services.store
    with store.session() as s:
        s.add(Capture(id="cap_x", tenant="local", format="canonical", state="ready"))
    # Its frozen capture.json, which the door resolves the job's run against.
    services.blobs.put_file("captures/cap_x/capture.json", synth_capture / "capture.json")
    r = client.post("/v1/jobs", json={"capture_id": "cap_x"})
    assert r.status_code == 202 and r.json()["state"] == "queued"
    job = store.get(r.json()["id"])
    assert job.dispatched_at is None  # so the sweeper sends it as soon as it can
    assert job.id in store.stranded(requeue_after=3600)


@pytest.mark.parametrize("database_url", ["sqlite", "postgres"], indirect=True)
def test_cursor_pages_with_a_state_filter(client, services, capture_id):
    store = services.store
    ids = []
    for i in range(7):
        ids.append(store.create("local", "reconstruct", PARAMS, capture_id=capture_id).id)
        if i % 2 == 0:
            run_job(store, ids[-1], outcome="failed", steps=1)
    failed = [j for i, j in enumerate(ids) if i % 2 == 0][::-1]  # newest first
    first = client.get("/v1/jobs", params={"state": "failed", "limit": 3}).json()
    assert [j["id"] for j in first["items"]] == failed[:3] and first["next_cursor"]
    newer = store.create("local", "reconstruct", PARAMS, capture_id=capture_id).id
    run_job(store, newer, outcome="failed", steps=1)  # an insert between two pages
    second = client.get("/v1/jobs", params={"state": "failed", "limit": 3,
                                            "cursor": first["next_cursor"]}).json()
    assert [j["id"] for j in second["items"]] == failed[3:] and second["next_cursor"] is None
    everything = client.get("/v1/jobs", params={"limit": 200}).json()["items"]
    assert [j["id"] for j in everything] == [newer, *ids[::-1]]
    assert client.get("/v1/jobs", params={"cursor": "bm9wZQ"}).status_code == 400
    assert client.get("/v1/jobs", params={"state": "sleeping"}).status_code == 422


def test_cancel_retry_delete_rules(client, services, capture_id):
    store = services.store
    job = client.post("/v1/jobs", json={"capture_id": capture_id, "params": PARAMS}).json()
    url = f"/v1/jobs/{job['id']}"
    assert client.delete(url).status_code == 409  # queued
    assert client.post(f"{url}/retry").status_code == 409  # not failed or cancelled
    r = client.post(f"{url}/cancel")
    assert r.status_code == 202 and r.json()["state"] == "cancelled"  # queued: at once
    assert client.post(f"{url}/cancel").status_code == 409
    r = client.post(f"{url}/retry")
    assert r.status_code == 202 and r.json()["state"] == "queued"
    owner = Owner.current()
    assert store.claim(job["id"], owner, 30, 3).status == "claimed"
    r = client.post(f"{url}/cancel")  # running: the worker is asked to stop
    assert r.status_code == 202 and r.json()["state"] == "running"
    assert r.json()["cancel_requested"] is True
    assert client.delete(url).status_code == 409
    store.finish(job["id"], owner, "cancelled")
    services.blobs.put_file(f"jobs/{job['id']}/artifacts/metrics.json",
                            services.settings.data_dir / "dgs.sqlite3")
    assert client.delete(url).status_code == 204
    assert client.get(url).status_code == 404
    assert services.blobs.list(f"jobs/{job['id']}") == []
    assert client.post(f"{url}/retry").status_code == 404


def test_retry_of_a_failed_job_dispatches_again(client, services, capture_id):
    job = client.post("/v1/jobs", json={"capture_id": capture_id, "params": PARAMS}).json()
    run_job(services.store, job["id"], outcome="failed")
    failed = client.get(f"/v1/jobs/{job['id']}").json()
    assert failed["state"] == "failed" and failed["error"]["code"] == "internal"
    assert failed["progress"]["fraction"] == 0.75  # kept for the resumed run
    r = client.post(f"/v1/jobs/{job['id']}/retry")
    assert r.status_code == 202 and r.json()["error"] is None
    assert services.store.get(job["id"]).dispatches == 2
    run_job(services.store, job["id"])
    assert client.post(f"/v1/jobs/{job['id']}/retry").status_code == 409  # succeeded


def test_logs_by_offset(client, services, capture_id):
    store = services.store
    job = store.create("local", "reconstruct", PARAMS, capture_id=capture_id)
    store.append_logs(job.id, [f"line {i}" for i in range(25)])
    url = f"/v1/jobs/{job.id}/logs"
    page = client.get(url, params={"limit": 10}).json()
    assert page["lines"] == [f"line {i}" for i in range(10)]
    assert page["next_offset"] == 10 and page["complete"] is False
    page = client.get(url, params={"offset": 20, "limit": 10}).json()
    assert page["lines"][-1] == "line 24" and page["next_offset"] == 25
    assert page["complete"] is False  # still queued: more may come
    run_job(store, job.id)
    page = client.get(url, params={"offset": 25}).json()
    assert page == {"lines": [], "offset": 25, "next_offset": 25, "complete": True}


def test_events_resume_after_last_event_id(client, services, capture_id):
    store = services.store
    job = store.create("local", "reconstruct", PARAMS, capture_id=capture_id)
    run_job(store, job.id, steps=3)
    url = f"/v1/jobs/{job.id}/events"
    everything = parse_sse(client.get(url, headers={"Last-Event-ID": "0"}).text)
    kinds = [e["event"] for e in everything]
    assert kinds == ["state", "state", "progress", "progress", "progress", "state"]
    assert [e["data"]["state"] for e in everything if e["event"] == "state"] == [
        "queued", "running", "succeeded"]
    ids = [e["id"] for e in everything]
    assert ids == sorted(ids) and len(set(ids)) == len(ids)
    rest = parse_sse(client.get(url, headers={"Last-Event-ID": str(ids[2])}).text)
    assert [e["id"] for e in rest] == ids[3:]  # nothing twice, nothing missed
    now = parse_sse(client.get(url).text)  # a new stream: the current state, then the end
    assert len(now) == 1 and now[0]["data"]["state"] == "succeeded" and now[0]["id"] == ids[-1]
    r = client.get(url, headers={"Last-Event-ID": "abc"})
    assert r.status_code == 400


def test_events_stream_live_until_the_job_ends(tmp_path, capture_id, client, services,
                                              monkeypatch):
    services.settings.sse_keepalive_seconds = 0.1
    store = services.store
    job = store.create("local", "reconstruct", PARAMS, capture_id=capture_id)
    # The worker starts only once the stream has sent the queued state and then polled long
    # enough for a keep-alive: no sleep that a loaded machine could outlast.
    opened: list[float] = []
    quiet = threading.Event()
    snapshot, events_after = service_events.snapshot, store.events_after

    def watched_snapshot(*args):
        result = snapshot(*args)
        opened.append(time.monotonic())
        return result

    def watched_events_after(*args):
        result = events_after(*args)
        if opened and time.monotonic() - opened[0] > 0.15:
            quiet.set()
        return result

    monkeypatch.setattr(service_events, "snapshot", watched_snapshot)
    monkeypatch.setattr(store, "events_after", watched_events_after)

    def worker():
        quiet.wait(60)  # on a timeout the assertions below say what was missed
        run_job(store, job.id, steps=2)

    thread = threading.Thread(target=worker)
    thread.start()
    r = client.get(f"/v1/jobs/{job.id}/events")
    thread.join()
    assert r.headers["content-type"].startswith("text/event-stream")
    events = parse_sse(r.text)
    assert events[0]["data"]["state"] == "queued"
    assert any("comment" in e for e in events)  # keep-alive while nothing happened
    data = [e for e in events if "data" in e]
    assert data[-1]["data"]["state"] == "succeeded"
    fractions = [e["data"]["fraction"] for e in data]
    assert fractions == sorted(fractions)


def test_fraction_never_goes_back_in_the_api(client, services, capture_id):
    store = services.store
    job = store.create("local", "reconstruct", PARAMS, capture_id=capture_id)
    owner = Owner.current()
    store.claim(job.id, owner, 30, 3)
    store.heartbeat(job.id, owner, 30, {"fraction": 0.5})
    with store.session() as s:  # the worker is lost; another one resumes from a checkpoint
        s.execute(update(Job).where(Job.id == job.id).values(lease_owner=None))
    other = Owner.current()
    store.claim(job.id, other, 30, 3)
    store.heartbeat(job.id, other, 30, {"fraction": 0.3})
    out = client.get(f"/v1/jobs/{job.id}").json()
    assert out["progress"]["fraction"] == 0.5 and out["attempts"] == 2


def test_readyz_reports_an_unreachable_broker(tmp_path):
    from fastapi.testclient import TestClient
    from service_harness import make_settings

    from service.app import create_app

    client = TestClient(create_app(make_settings(tmp_path / "d",
                                                 broker_url="redis://127.0.0.1:9/0")))
    assert client.get("/healthz").json() == {"status": "ok"}
    r = client.get("/readyz")
    assert r.status_code == 503 and r.json()["status"] == "unavailable"
    assert r.json()["checks"]["database"] == "ok"
    assert r.json()["checks"]["broker"].startswith("error")


def _committed(client, new_capture, files: dict[str, bytes]) -> str:
    capture = new_capture(files)
    for path, data in files.items():
        upload_file(client, capture["id"], path, data)
    r = client.post(f"/v1/captures/{capture['id']}/commit")
    assert r.status_code == 200, r.text
    return capture["id"]


def _jobs(client) -> int:
    return len(client.get("/v1/jobs", params={"limit": 200}).json()["items"])


@pytest.mark.parametrize("split", ["auto", "every8", "capture"])
def test_a_split_that_leaves_no_camera_to_train_on_is_refused(client, services, new_capture,
                                                              synth_capture, split):
    """Issue 42, item 3: on a one-camera capture every held-out rule but `none` leaves nothing
    to train on; the door refuses it with the split rule's own words (the worker failed it
    after a 202), and `none` gets through."""
    one = _committed(client, new_capture, capture_variant(synth_capture, cameras=1))
    before = _jobs(client)
    r = client.post("/v1/jobs", json={"capture_id": one, "params": {"config": {"split": split}}})
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["details"][0]["path"] == "params.config.split"
    words = ("declares no test_cameras" if split == "capture"
             else "every8 leaves no camera to train on")
    assert words in error["message"], error
    assert _jobs(client) == before  # no job
    r = client.post("/v1/jobs", json={"capture_id": one, "params": {"config": {"split": "none"}}})
    assert r.status_code == 202, r.text
    stored = services.store.get(r.json()["id"]).resolved_run  # the run its worker will run
    assert stored["views"]["split"] == {"rule": "none", "training": ["cam00"], "heldout": []}


def test_a_subject_mesh_or_export_of_a_capture_without_masks_is_refused(client, services,
                                                                      new_capture,
                                                                      synth_capture):
    """Issue 42, item 4: `mesh.subject` needs masks to say where the subject is, as a subject
    export does: both answer 422 before a job exists (the worker 'succeeded' with no mesh)."""
    bare = _committed(client, new_capture, capture_variant(synth_capture, masks=False))
    before = _jobs(client)
    r = client.post("/v1/jobs", json={"capture_id": bare, "params": {
        "config": {"mesh": {"subject": True}}}})
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["details"][0]["path"] == "params.config.mesh.subject"
    assert "the capture has no masks" in error["message"] and _jobs(client) == before
    with services.store.session() as s:
        s.add(Job(id="job_done", tenant="local", capture_id=bare, pipeline="reconstruct",
                  params={}, state="succeeded", stage="succeeded"))
    r = client.post("/v1/exports", json={"job_id": "job_done", "subject": True})
    assert r.status_code == 422, r.text
    assert r.json()["error"]["details"][0]["path"] == "subject"
    assert "the capture has no masks" in r.json()["error"]["message"]
    assert client.post("/v1/exports", json={"job_id": "job_done"}).status_code == 202
    r = client.post("/v1/jobs", json={"capture_id": bare, "params": {"preset": "test"}})
    assert r.status_code == 202, r.text
