"""Real `dgs worker` processes running real jobs, on the embedded stack (SQLite job store and
broker, local artifact store) and the distributed one (PostgreSQL, Redis, S3 over HTTP):
a job from queue to published artifacts; a task process killed mid-job resumes from its
checkpoint and completes once; a whole worker killed is replaced by another on a fresh machine
that resumes the job; a cancel stops a job at a step boundary and frees the worker."""

from __future__ import annotations

import json
import os
import re
import secrets
import signal
from pathlib import Path

import pytest

from worker_harness import add_capture, tiny_config, wait_for
from worker.blobs import open_store
from worker.celery_app import dispatch, make_celery
from worker.db import migrate
from worker.settings import WorkerSettings
from worker.store import JobStore, Owner

pytestmark = pytest.mark.timeout(600)


@pytest.fixture(scope="module")
def s3_server():
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0)
    server.start()
    host, port = server.get_host_and_port()
    yield f"http://{host}:{port}"
    server.stop()


@pytest.fixture(params=["embedded", "distributed"])
def stack(request, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """(environment for worker processes, settings for this process)."""
    # The fair share is off: the session's PostgreSQL keeps other tests' queued jobs (each
    # test has a queue of its own, so they never run), and one of another tenant would make a
    # test's own jobs give their workers up (test_gate turns it on).
    env = {"DGS_DATA_DIR": str(tmp_path / "data"), "DGS_LEASE_SECONDS": "4",
           "DGS_HEARTBEAT_SECONDS": "0.5", "DGS_CANCEL_GRACE_SECONDS": "3",
           "DGS_SHARE_AFTER_SECONDS": "0",
           "DGS_QUEUE": f"q-{secrets.token_hex(4)}", "OMP_NUM_THREADS": "1"}
    if request.param == "distributed":
        redis_url, prefix = request.getfixturevalue("redis_broker")
        endpoint = request.getfixturevalue("s3_server")
        bucket = f"dgs-{secrets.token_hex(4)}"
        env.update({"DGS_DATABASE_URL": request.getfixturevalue("pg_empty"),
                    "DGS_BROKER_URL": redis_url, "DGS_REDIS_KEY_PREFIX": prefix,
                    "DGS_STORAGE_URL": f"s3://{bucket}/dgs", "DGS_S3_ENDPOINT_URL": endpoint,
                    "DGS_S3_REGION": "us-east-1", "AWS_ACCESS_KEY_ID": "test",
                    "AWS_SECRET_ACCESS_KEY": "test"})
        import boto3

        boto3.client("s3", endpoint_url=endpoint, region_name="us-east-1",
                     aws_access_key_id="test", aws_secret_access_key="test",
                     ).create_bucket(Bucket=bucket)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    settings = WorkerSettings()
    migrate(settings.database)
    return {**os.environ, **env}, settings


class Harness:
    def __init__(self, settings: WorkerSettings, capture: Path):
        self.settings = settings
        self.store = JobStore(settings.database)
        self.blobs = open_store(settings.storage, endpoint_url=settings.s3_endpoint_url,
                                region=settings.s3_region)
        self.celery = make_celery(settings)
        self.capture_id = add_capture(self.store, self.blobs, capture,
                                      capture_id=f"cap_{secrets.token_hex(4)}")

    def submit(self, iterations: int, checkpoint_every: int = 20) -> str:
        job = self.store.create("t1", "reconstruct", {
            "preset": "test", "config": tiny_config(iterations),
            "checkpoint_every": checkpoint_every}, capture_id=self.capture_id)
        self.store.mark_dispatched(job.id)
        dispatch(self.celery, self.settings, job.id, "reconstruct")
        return job.id

    def state(self, job_id: str) -> str:
        return self.store.get(job_id).state

    def wait_state(self, job_id: str, states: tuple[str, ...], timeout: float = 180):
        return wait_for(lambda: self.store.get(job_id) if self.state(job_id) in states else None,
                        timeout, f"job {job_id} to reach {states}")

    def artifact_json(self, job_id: str, path: str) -> dict:
        data = b"".join(self.blobs.read_range(f"jobs/{job_id}/artifacts/{path}", 0, 1 << 30))
        return json.loads(data)

    def log(self, job_id: str) -> str:
        return "\n".join(r.line for r in self.store.logs(job_id, 0, 10_000))


def _pid(job) -> int:
    """The pool process that ran `job` (its worker: host/pid)."""
    return int(job.worker.rsplit("/", 1)[1])


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie is dead for our purposes
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_job_runs_to_published_artifacts(stack, tiny_capture: Path, worker_factory):
    env, settings = stack
    h = Harness(settings, tiny_capture)
    worker_factory(env).start()
    job_id = h.submit(iterations=100)
    job = h.wait_state(job_id, ("succeeded", "failed"))
    assert job.state == "succeeded", h.log(job_id)
    assert job.attempts == 1 and job.fraction == 1.0 and job.lease_owner is None
    keys = {b.key.split("/artifacts/", 1)[1] for b in h.blobs.list(f"jobs/{job_id}/artifacts")}
    assert {"frames/000000/gaussians.ply", "renders/000000/cam00_rgb.png", "metrics.json",
            "eval.json", "config.json", "plots/loss.png"} <= keys
    assert not any(k.startswith("checkpoints/") for k in keys)
    fractions = [e.data["fraction"] for e in h.store.events_after(job_id, 0)
                 if e.kind == "progress"]
    assert len(fractions) >= 3 and fractions == sorted(fractions)
    # An ETA is published (a rate needs 2 s of progress, so a fast job's may be only the 0 of
    # its end: no test may depend on the machine's speed).
    etas = [e.data.get("eta_s") for e in h.store.events_after(job_id, 0) if e.kind == "progress"]
    assert etas[-1] == 0.0 and all(x is None or x >= 0 for x in etas)
    assert h.artifact_json(job_id, "eval.json")["psnr"] > 10
    assert "published" in h.log(job_id)


def test_killed_task_process_resumes_from_its_checkpoint(stack, tiny_capture: Path,
                                                         worker_factory):
    env, settings = stack
    h = Harness(settings, tiny_capture)
    worker_factory(env).start()
    job_id = h.submit(iterations=300)
    job = wait_for(lambda: (j := h.store.get(job_id)).iteration >= 50 and j, 180,
                   "the job to pass step 50")
    child = Owner.parse(job.lease_owner).pid
    os.kill(child, signal.SIGKILL)  # the process running the task dies mid-frame
    done = h.wait_state(job_id, ("succeeded", "failed"))
    assert done.state == "succeeded", h.log(job_id)
    assert done.attempts == 2
    frame = h.artifact_json(job_id, "metrics.json")["frames"]["000000"]
    assert frame["resumed_at"] >= 40 and frame["resumed_at"] % 20 == 0
    # Exactly once to completion: every step recorded once, none repeated by the resume.
    assert [r["step"] for r in frame["history"]] == list(range(300))
    assert h.log(job_id).count("attempt ") == 2, h.log(job_id) + str([(e.id, e.kind, e.data) for e in h.store.events_after(job_id, 0) if e.kind == "state"])
    states = [e.data["state"] for e in h.store.events_after(job_id, 0) if e.kind == "state"
              and "state" in e.data and not e.data.get("cancel_requested")]
    assert states == ["queued", "running", "running", "succeeded"]


def test_lost_worker_is_replaced_and_the_job_resumes(stack, tiny_capture: Path, worker_factory,
                                                     tmp_path: Path):
    env, settings = stack
    h = Harness(settings, tiny_capture)
    first = worker_factory(env).start()
    job_id = h.submit(iterations=300)
    wait_for(lambda: h.store.get(job_id).iteration >= 50, 180, "the job to pass step 50")
    first.kill_all()  # the whole worker is gone, its broker message with it
    # A replacement on another machine: nothing of the first one's scratch folder.
    second_env = {**env, "DGS_SCRATCH_DIR": str(tmp_path / "other-machine")}
    worker_factory(second_env).start()
    done = h.wait_state(job_id, ("succeeded", "failed"), timeout=240)
    assert done.state == "succeeded", h.log(job_id)
    assert done.attempts == 2 and done.dispatches >= 2  # sent again by a sweeper
    frame = h.artifact_json(job_id, "metrics.json")["frames"]["000000"]
    assert frame["resumed_at"] >= 40
    assert [r["step"] for r in frame["history"]] == list(range(300))


def test_cancel_stops_the_job_at_a_step_boundary_and_frees_the_worker(
        stack, tiny_capture: Path, worker_factory):
    """A cancel stops the running job between two steps, with its checkpoint written (a retry
    resumes from it), and frees its task process: the worker's next job runs in that same
    process (kept between tasks: no interpreter to start). Nothing waits on the clock: the
    grace before a wedged job's process is ended is far longer than a step here, so only the
    step boundary can stop it (the wedged case: tests/worker/test_runner.py)."""
    env, settings = stack
    h = Harness(settings, tiny_capture)
    worker_factory({**env, "DGS_CANCEL_GRACE_SECONDS": "3600"}).start()
    job_id = h.submit(iterations=5000)
    job = wait_for(lambda: (j := h.store.get(job_id)).iteration >= 5 and j, 180,
                   "the job to start")
    child = Owner.parse(job.lease_owner).pid
    h.store.request_cancel(job_id, "t1")
    stopped = h.wait_state(job_id, ("cancelled", "failed", "succeeded"))
    log = h.log(job_id)
    assert stopped.state == "cancelled", log
    assert stopped.message == "cancelled; retry resumes from the last checkpoint"
    assert "cancel requested: stopping after the current step" in log
    where = re.search(r"cancelled: stopped at step (\d+) of frame 000000 \(checkpoint written\)",
                      log)
    assert where and 5 <= int(where.group(1)) < 5000, log
    assert "did not stop within" not in log
    assert h.blobs.size(f"jobs/{job_id}/state/checkpoints/000000.pt")  # what a retry resumes
    nxt = h.submit(iterations=100)  # the worker takes the next job
    done = h.wait_state(nxt, ("succeeded", "failed"))
    assert done.state == "succeeded", h.log(nxt)
    assert _pid(done) == child and _alive(child), done.runs
    assert h.store.retry(job_id, "t1").state == "queued"


@pytest.mark.parametrize("stack", ["embedded"], indirect=True)
def test_a_pool_process_that_grew_past_the_memory_cap_is_replaced(stack, tiny_capture: Path,
                                                                  worker_factory):
    """A pool process whose peak memory passed `DGS_POOL_PROCESS_MAX_MIB` (here any: 64 MiB is
    less than torch alone) ends after its task and the next job runs in a fresh one; with
    one task a process (`DGS_POOL_TASKS_PER_PROCESS` 1) likewise."""
    env, settings = stack
    h = Harness(settings, tiny_capture)
    for extra in ({"DGS_POOL_PROCESS_MAX_MIB": "64"}, {"DGS_POOL_TASKS_PER_PROCESS": "1"}):
        worker = worker_factory({**env, **extra}).start()
        pids = []
        for _ in range(2):
            job = h.wait_state(h.submit(iterations=10), ("succeeded", "failed"))
            assert job.state == "succeeded", h.log(job.id)
            pids.append(_pid(job))
        assert pids[0] != pids[1] and not _alive(pids[0]), (extra, pids)
        worker.stop()


def test_stopping_a_worker_hands_its_job_to_the_next(stack, tiny_capture: Path, worker_factory):
    """SIGTERM to a worker (docker compose stop): its job stops at the next step with a
    checkpoint, goes back to the queue, and the worker exits in seconds, not at the job's end;
    the next worker resumes the job from that step."""
    env, settings = stack
    h = Harness(settings, tiny_capture)
    first = worker_factory(env).start()
    job_id = h.submit(iterations=300, checkpoint_every=1000)  # only the stop writes one
    wait_for(lambda: h.store.get(job_id).iteration >= 50, 180, "the job to pass step 50")
    os.kill(first.proc.pid, signal.SIGTERM)
    first.proc.wait(timeout=60)
    back = h.store.get(job_id)
    assert back.state == "queued" and "shut down at step" in back.message
    stopped_at = int(back.message.rsplit(" ", 1)[1])
    assert stopped_at >= 50 and back.redeliveries == 0 and back.lease_owner is None
    worker_factory(env).start()
    done = h.wait_state(job_id, ("succeeded", "failed"))
    assert done.state == "succeeded", h.log(job_id)
    frame = h.artifact_json(job_id, "metrics.json")["frames"]["000000"]
    assert frame["resumed_at"] == stopped_at
    assert [r["step"] for r in frame["history"]] == list(range(300))
    assert "back in the queue" in h.log(job_id)


def test_soft_time_limit_fails_cleanly_and_keeps_the_checkpoint(stack, tiny_capture: Path,
                                                                worker_factory):
    env, settings = stack
    # The first checkpoint (step 10) comes well within the limit on a loaded machine too (a
    # fresh pool process imports torch first); 20,000 steps take minutes.
    env = {**env, "DGS_RECONSTRUCT_SOFT_LIMIT_SECONDS": "30"}
    settings = settings.model_copy(update={"reconstruct_soft_limit_seconds": 30.0})
    h = Harness(settings, tiny_capture)
    worker_factory(env).start()
    job_id = h.submit(iterations=20_000, checkpoint_every=10)
    done = h.wait_state(job_id, ("failed", "succeeded"), timeout=120)
    assert done.state == "failed" and done.error["code"] == "time_limit"
    assert done.error["retryable"] is True and "checkpoint" in done.error["message"]
    assert h.blobs.list(f"jobs/{job_id}/state/checkpoints")  # a retry resumes from here
