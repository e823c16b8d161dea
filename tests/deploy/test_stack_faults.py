"""Faults of the deployment, in its containers: a worker container killed mid-part (the part
resumes once, from its checkpoint, on the other worker, while the sequence's other part goes on);
the API container restarted (nothing lost, an upload under way resumes where it stopped);
PostgreSQL stopped (503, not 500, then service again); Redis restarted with a job in its queue
(the append-only file kept its message, and the job runs once)."""

from __future__ import annotations

import base64
import datetime as dt
import json
import threading
from pathlib import Path

import httpx
import pytest
from compose_stack import Stack, wait_for
from deploy_jobs import synth, tiny_config, worker_hosts

from service.client import Client, Event

pytestmark = pytest.mark.timeout(1800)

FRAMES = ("000000", "000001", "000002", "000003")
SEQUENCE = {"train": {"schedule": {
    "iterations": 600, "stage2_start": 180, "stage3_start": 420, "densify_from": 30,
    "densify_until": 360, "densify_interval": 60, "reset_interval": 240, "sh_interval": 60},
    "init_points": 300}, "sequence": {"num_nodes": 32}, "mesh": {"enabled": False},
    "checkpoint_every": 50}
"""Two groups of two frames (gop 2): a key frame long enough to be caught between two
checkpoints, a checkpoint every 50 steps."""


def _follow(url: str, key: str, job_id: str, events: list[Event], out: dict) -> None:
    """The job's server-sent events until it ends (a thread, with a client of its own)."""
    with Client(url, key, timeout=120) as c:
        out["job"] = c.wait(job_id, on_event=events.append, timeout=1500)


def _ready_capture(client: Client, folder: Path) -> str:
    cap = client.create_capture(folder)
    client.upload_capture(cap["id"], folder)
    return client.commit(cap["id"], timeout=600)["id"]


def _started(stack: Stack, container: str) -> str:
    return stack.docker("inspect", "-f", "{{.State.StartedAt}}", container).stdout.strip()


def _checkpointed(stack: Stack, client: Client, job_id: str, ids: dict[str, str]):
    """A part in its key frame, well before its end, with a checkpoint of it in the store."""
    for p in client.job(job_id)["parts"]:
        if p["state"] == "running" and p["frame"] == 1 and \
                100 < p["iteration"] < p["iterations"] - 300:
            prefix = f"jobs/{ids[str(p['index'])]}/state/"
            if f"{prefix}checkpoints/{p['frames'][0]}.pt" in stack.s3_keys(prefix):
                return p
    return None


def test_a_killed_worker_containers_part_resumes_once_on_the_other(
        stack: Stack, client: Client, tmp_path: Path):
    capture = _ready_capture(client, synth(tmp_path / "capture", frames=4, seed=5))
    job = client.submit(capture, {"preset": "test", "gop": 2, "config": SEQUENCE})
    assert [p["frames"] for p in job["parts"]] == [list(FRAMES[:2]), list(FRAMES[2:])]
    events: list[Event] = []
    result: dict = {}
    follower = threading.Thread(target=_follow, daemon=True,
                                args=(stack.url, stack.key, job["id"], events, result))
    follower.start()
    hosts = worker_hosts(stack)

    def both_running():
        parts = client.job(job["id"])["parts"]
        return {p["worker"].split("/")[0] for p in parts
                if p["state"] == "running" and p["worker"]} == set(hosts)

    wait_for(both_running, 900, "both parts running, one on each worker container")
    ids = dict(stack.sql(f"SELECT part_index, id FROM jobs WHERE parent_id = '{job['id']}'"))
    part = wait_for(lambda: _checkpointed(stack, client, job["id"], ids), 900,
                    "a part with a checkpoint of its key frame in the object store")
    lost = part["worker"].split("/")[0]
    stack.docker("kill", hosts[lost])  # the whole container, as a machine lost

    follower.join(timeout=1600)
    assert "job" in result, f"job {job['id']} did not end: {client.job(job['id'])}"
    done = result["job"]
    assert done["state"] == "succeeded", "\n".join(client.logs(job["id"]))
    parts = {p["index"]: p for p in done["parts"]}
    resumed, other = parts[part["index"]], parts[1 - part["index"]]
    (survivor,) = set(hosts) - {lost}
    assert resumed["attempts"] == 2
    assert [r["outcome"] for r in resumed["runs"]] == ["lost", "succeeded"]
    assert resumed["runs"][0]["worker"].split("/")[0] == lost
    assert resumed["runs"][1]["worker"].split("/")[0] == survivor
    assert other["attempts"] == 1 and [r["outcome"] for r in other["runs"]] == ["succeeded"]
    # Exactly once: the job ended once, and each frame was published once.
    ends = [e for e in events if e.kind == "state" and e.data["state"] in
            ("succeeded", "failed", "cancelled")]
    assert [e.data["state"] for e in ends] == ["succeeded"]
    assert {e.data["part"] for e in events if e.kind == "part"} == {0, 1}
    paths = [a["path"] for a in client.artifacts(job["id"])]
    assert len(paths) == len(set(paths))
    assert {f"frames/{f}/gaussians.ply" for f in FRAMES} <= set(paths)
    client.download(job["id"], "metrics.json", tmp_path / "metrics.json")
    frames = json.loads((tmp_path / "metrics.json").read_text())["frames"]
    assert frames[part["frames"][0]]["resumed_at"] > 0  # from its checkpoint
    assert all(frames[f]["resumed_at"] == 0 for f in other["frames"])

    # Back to two workers for what follows.
    since = dt.datetime.now(dt.timezone.utc).isoformat()
    stack.docker("start", hosts[lost])
    wait_for(lambda: stack.worker_ready(hosts[lost], since), 300, "the worker to come back")


def _half_upload(client: Client, capture_id: str, folder: Path) -> tuple[str, bytes, int]:
    """A tus upload of the capture's largest file, stopped half way: (its URL, bytes, sent)."""
    entry = max(client.missing_files(capture_id), key=lambda f: f["size"])
    data = (folder / entry["path"]).read_bytes()
    meta = ",".join(f"{k} {base64.b64encode(v.encode()).decode()}"
                    for k, v in (("capture", capture_id), ("path", entry["path"])))
    r = client.http.post("/v1/uploads", headers={
        "Tus-Resumable": "1.0.0", "Upload-Length": str(len(data)), "Upload-Metadata": meta})
    assert r.status_code == 201, r.text
    url, half = r.headers["Location"], len(data) // 2
    r = client.http.patch(url, content=data[:half], headers={
        "Tus-Resumable": "1.0.0", "Upload-Offset": "0",
        "Content-Type": "application/offset+octet-stream"})
    assert r.status_code == 204 and int(r.headers["Upload-Offset"]) == half, r.text
    return url, data, half


def test_the_api_container_restarts_with_everything_still_there(
        stack: Stack, client: Client, reconstruction: dict, tmp_path: Path):
    job_id = reconstruction["job"]["id"]
    jobs = {j["id"]: j["state"] for j in client._pages("/v1/jobs", {})}
    captures = {c["id"]: c["state"] for c in client._pages("/v1/captures", {})}
    artifacts = {a["path"]: a["sha256"] for a in client.artifacts(job_id)}
    folder = synth(tmp_path / "capture", frames=1, seed=7)
    capture = client.create_capture(folder)
    url, data, half = _half_upload(client, capture["id"], folder)
    (api,) = stack.containers("api")
    before = _started(stack, api["ID"])

    stack.compose("restart", "api")
    wait_for(lambda: _started(stack, api["ID"]) != before and stack.ready(), 300,
             "the API container to restart and answer /readyz")
    assert {j["id"]: j["state"] for j in client._pages("/v1/jobs", {})} == jobs
    assert {c["id"]: c["state"] for c in client._pages("/v1/captures", {})
            if c["id"] != capture["id"]} == captures
    assert {a["path"]: a["sha256"] for a in client.artifacts(job_id)} == artifacts
    client.download(job_id, "metrics.json", tmp_path / "metrics.json",
                    sha256=artifacts["metrics.json"])
    # The upload under way kept its bytes (the staging volume) and goes on where it stopped.
    head = client.http.head(url, headers={"Tus-Resumable": "1.0.0"})
    assert head.status_code == 200 and int(head.headers["Upload-Offset"]) == half
    r = client.http.patch(url, content=data[half:], headers={
        "Tus-Resumable": "1.0.0", "Upload-Offset": str(half),
        "Content-Type": "application/offset+octet-stream"})
    assert r.status_code == 204 and int(r.headers["Upload-Offset"]) == len(data), r.text
    client.upload_capture(capture["id"], folder)
    assert client.commit(capture["id"], timeout=600)["state"] == "ready"


def test_a_stopped_job_store_answers_503_and_the_service_recovers(stack: Stack,
                                                                  client: Client):
    running = {c["ID"]: _started(stack, c["ID"]) for s in ("api", "worker")
               for c in stack.containers(s)}
    stack.compose("stop", "postgres")
    try:
        for path in ("/v1/jobs", "/v1/captures", "/v1/info"):
            r = client.http.get(path)
            assert r.status_code == 503, (path, r.status_code, r.text)
            assert r.json()["error"]["code"] == "unavailable"
            assert r.json()["error"]["retryable"] is True and "Retry-After" in r.headers
        assert httpx.get(f"{stack.url}/readyz", timeout=30).status_code == 503
    finally:
        stack.compose("start", "postgres")
    wait_for(stack.ready, 300, "the API to be ready again")
    assert client.http.get("/v1/jobs").status_code == 200
    # Nothing crashed or was restarted meanwhile.
    assert {c["ID"]: _started(stack, c["ID"]) for s in ("api", "worker")
            for c in stack.containers(s)} == running


def _queued_messages(stack: Stack) -> str:
    """Every message in the broker's lists (Celery's queues), as redis-cli prints them."""
    script = ('for k in $(redis-cli --scan); do [ "$(redis-cli type "$k")" = list ] && '
              'redis-cli lrange "$k" 0 -1; done; true')
    return stack.exec("redis", "sh", "-c", script).stdout


def test_a_queued_job_outlives_a_redis_restart(stack: Stack, client: Client,
                                               reconstruction: dict):
    stack.compose("stop", "worker")  # nobody takes the job: it waits in Redis
    try:
        job = client.submit(reconstruction["capture"]["id"],
                            {"preset": "test", "config": tiny_config(40)})
        wait_for(lambda: job["id"] in _queued_messages(stack), 120,
                 "the job's message in Redis")
        (redis,) = stack.containers("redis")
        before = _started(stack, redis["ID"])
        stack.compose("restart", "redis")
        assert _started(stack, redis["ID"]) != before
        wait_for(lambda: stack.redis("PING") == "PONG", 120, "Redis to answer again")
        # The append-only file brought the message back: nothing had to send it again.
        assert job["id"] in _queued_messages(stack)
    finally:
        since = dt.datetime.now(dt.timezone.utc).isoformat()
        stack.compose("start", "worker")
    for c in stack.containers("worker"):
        wait_for(lambda c=c: stack.worker_ready(c["ID"], since), 300, "the workers to connect")
    done = client.wait(job["id"], timeout=900)
    logs = client.logs(job["id"])
    assert done["state"] == "succeeded", "\n".join(logs)
    assert done["attempts"] == 1
    # No sweeper had to send it again (each re-send is logged with its reason).
    out = stack.compose("logs", "--no-color", "api", "worker").stdout
    assert f"job {job['id']}: sent to the queue again" not in out
