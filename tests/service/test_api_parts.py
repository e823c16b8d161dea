"""/v1/jobs for a sequence run as parts (no worker runs here: the job store is driven as workers
would): the job is split at creation and its parts sent, not the job; it lists its parts and
progress over them; parts are reached only through their job; its events carry theirs; retry
sends only the failed part; delete takes the parts with the job."""

from __future__ import annotations

import json

import anyio
import pytest
from sqlalchemy import select, update
from test_api_jobs import parse_sse

from service.events import job_events
from worker.models import Capture, Job
from worker.store import Owner

FRAMES = [f"{i:06d}" for i in range(6)]
PARAMS = {"preset": "test", "gop": 2}


@pytest.fixture
def capture_id(ready_capture, services, tmp_path) -> str:
    """A ready capture whose frozen capture.json lists six frames (only the split reads it)."""
    cap = ready_capture()
    key = f"captures/{cap}/capture.json"
    data = json.loads(b"".join(services.blobs.read_range(key, 0, services.blobs.size(key))))
    data["frames"] = FRAMES
    (tmp_path / "capture.json").write_text(json.dumps(data))
    services.blobs.put_file(key, tmp_path / "capture.json")
    with services.store.session() as s:
        row = s.get(Capture, cap)
        s.execute(update(Capture).where(Capture.id == cap).values(
            summary={**row.summary, "frames": len(FRAMES)}))
    return cap


async def overall_event(store, job_id: str) -> dict:
    """The first overall progress event of the job's stream (from its first event)."""
    stream = job_events(store, job_id, 0, poll=0.05, keepalive=30)
    try:
        async for text in stream:
            (event,) = parse_sse(text)
            if event.get("event") == "progress" and event["data"].get("stage") == "parts":
                return event["data"]
    finally:
        await stream.aclose()
    raise AssertionError("the stream ended without the job's overall progress")


def finish(store, part_id: str, state: str = "succeeded") -> None:
    owner = Owner.current()
    assert store.claim(part_id, owner, 30, 3).status == "claimed"
    assert store.heartbeat(part_id, owner, 30, {"fraction": 0.5, "stage": "refine"})[0]
    error = {"code": "internal", "message": "boom", "retryable": True} \
        if state == "failed" else None
    assert store.finish(part_id, owner, state, error)


def test_a_sequence_job_runs_as_parts(client, services, capture_id):
    store = services.store
    r = client.post("/v1/jobs", json={"capture_id": capture_id, "params": PARAMS})
    assert r.status_code == 202, r.text
    job = r.json()
    assert [p["frames"] for p in job["parts"]] == [FRAMES[0:2], FRAMES[2:4], FRAMES[4:6]]
    assert [p["state"] for p in job["parts"]] == ["queued"] * 3
    parts = store.parts(job["id"])
    assert [p.dispatches for p in parts] == [1, 1, 1]  # the parts are sent, the job is not
    assert store.get(job["id"]).dispatches == 0
    # Parts are reached through their job only.
    assert [j["id"] for j in client.get("/v1/jobs").json()["items"]] == [job["id"]]
    assert client.get(f"/v1/jobs/{parts[0].id}").status_code == 404
    assert client.post(f"/v1/jobs/{parts[0].id}/cancel").status_code == 404

    finish(store, parts[0].id)
    owner = Owner.current()
    assert store.claim(parts[1].id, owner, 30, 3).status == "claimed"
    assert store.heartbeat(parts[1].id, owner, 30, {"fraction": 0.5, "frame": 1,
                                                     "frames": 2})[0]
    out = client.get(f"/v1/jobs/{job['id']}").json()
    assert out["state"] == "running"
    assert [p["state"] for p in out["parts"]] == ["succeeded", "running", "queued"]
    assert out["parts"][1]["worker"] == f"{owner.host}/{owner.pid}"
    # A finished part still names the worker that ran it (its lease is gone).
    done = out["parts"][0]
    assert done["state"] == "succeeded" and done["worker"] == f"{owner.host}/{owner.pid}"
    assert [(r["worker"], r["outcome"]) for r in done["runs"]] == [(done["worker"],
                                                                    "succeeded")]
    assert out["progress"]["fraction"] == pytest.approx((1 + 0.5) / 3 * 0.99)
    assert out["progress"]["frames"] == 6 and out["progress"]["frame"] == 2
    # While it runs, its stream follows the parts' events with the job's overall progress.
    overall = anyio.run(overall_event, store, job["id"])
    assert overall["fraction"] == pytest.approx(out["progress"]["fraction"])
    assert store.finish(parts[1].id, owner, "failed",
                        {"code": "internal", "message": "boom", "retryable": True})
    finish(store, parts[2].id)
    failed = client.get(f"/v1/jobs/{job['id']}").json()
    assert failed["state"] == "failed" and "part 1 (frames 000002..000003)" in \
        failed["error"]["message"]
    # The job has ended: its stream is every event up to its end, its parts' included.
    stream = parse_sse(client.get(f"/v1/jobs/{job['id']}/events",
                                  headers={"Last-Event-ID": "0"}).text)
    kinds = [e.get("event") for e in stream]
    assert "part" in kinds and kinds[-1] == "state"
    assert {e["data"]["part"] for e in stream if e.get("event") == "part"} == {0, 1, 2}

    r = client.post(f"/v1/jobs/{job['id']}/retry")
    assert r.status_code == 202 and r.json()["state"] == "queued"
    assert [p.dispatches for p in store.parts(job["id"])] == [1, 2, 1]  # the failed one only
    r = client.post(f"/v1/jobs/{job['id']}/cancel")
    assert r.status_code == 202 and r.json()["state"] == "cancelled"
    assert [p["state"] for p in r.json()["parts"]] == ["succeeded", "cancelled", "succeeded"]
    assert client.delete(f"/v1/jobs/{job['id']}").status_code == 204
    with store.session(write=False) as s:
        assert s.scalars(select(Job.id).where(Job.parent_id == job["id"])).all() == []
