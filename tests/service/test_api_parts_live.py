"""A sequence of three groups of pictures through a real `dgs serve --workers 2` (API and two
embedded workers on the SQLite job store and broker): the job runs as three parts, two of them
at the same time on the two workers; one worker is SIGKILLed mid-part and that part alone
resumes from its checkpoint while the other part goes on; the assembled sequence.json lists
every frame; the job's events carry its parts' progress."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pytest
from live_server import LiveServer, wait_for

from service.client import Client
from worker.lease import Owner

pytestmark = pytest.mark.timeout(600)

FRAMES = tuple(f"{i:06d}" for i in range(6))
ITERATIONS = 1500
CONFIG = {"train": {"schedule": {
    "iterations": ITERATIONS, "stage2_start": 450, "stage3_start": 1050, "densify_from": 75,
    "densify_until": 900, "densify_interval": 150, "reset_interval": 600, "sh_interval": 150},
    "init_points": 300}, "sequence": {"num_nodes": 32}, "mesh": {"enabled": False},
    "checkpoint_every": 50}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("parts-api") / "data"
    # A short lease, so the killed worker's part is handed on within seconds.
    live = LiveServer(data, data.parent / "serve.log", "--workers", "2",
                      DGS_LEASE_SECONDS="4", DGS_HEARTBEAT_SECONDS="0.5").start()
    live.wait_worker(timeout=300)
    live.wait_worker(timeout=300, name="worker-2.log")
    yield live
    live.stop()


def _checkpointed(server: LiveServer, part: dict) -> bool:
    """The part is in its key frame and has a checkpoint of it in the store."""
    state = server.data_dir / "store" / "jobs" / part["id"] / "state" / "checkpoints"
    return (part["state"] == "running" and part["frame"] == 1
            and 100 < part["iteration"] < ITERATIONS - 300
            and (state / f"{part['frames'][0]}.pt").is_file())


def test_parts_run_at_once_and_a_killed_workers_part_resumes_alone(server, tmp_path):
    from core.synth import SynthConfig, synthesize

    folder = tmp_path / "capture"
    synthesize(folder, SynthConfig(frames=6, views=8, width=32, height=32, seed=5,
                                   ao_directions=8))
    with Client(server.url) as client:
        cap = client.create_capture(folder)
        client.upload_capture(cap["id"], folder)
        assert client.commit(cap["id"], timeout=120)["state"] == "ready"
        job = client.submit(cap["id"], {"preset": "test", "gop": 2, "config": CONFIG})
        assert [p["frames"] for p in job["parts"]] == [list(FRAMES[i:i + 2]) for i in (0, 2, 4)]

        def two_running():
            parts = client.job(job["id"])["parts"]
            running = [p for p in parts if p["state"] == "running" and p["worker"]]
            return running if len({p["worker"] for p in running}) == 2 else None

        both = wait_for(two_running, 300, "two parts running at once on two workers")
        assert len({p["index"] for p in both}) == 2

        def victim():
            with_ids = _with_ids(server, job["id"], client.job(job["id"])["parts"])
            ready = [p for p in with_ids if _checkpointed(server, p)]
            return ready[0] if ready else None

        part = wait_for(victim, 300, "a part with a checkpoint of its key frame")
        others = [p for p in _with_ids(server, job["id"], client.job(job["id"])["parts"])
                  if p["state"] == "running" and p["index"] != part["index"]]
        worker_pid = Owner.parse(part["lease_owner"]).pid
        os.killpg(os.getpgid(worker_pid), signal.SIGKILL)  # the whole worker, as a lost machine

        done = client.wait(job["id"], timeout=540)
        logs = "\n".join(client.logs(job["id"]))
        assert done["state"] == "succeeded", (logs, done, server.log())
        parts = {p["index"]: p for p in done["parts"]}
        assert all(p["state"] == "succeeded" for p in parts.values())
        assert parts[part["index"]]["attempts"] == 2  # resumed, by whichever worker
        # It keeps who ran it: the killed worker's run lost, the last one succeeded.
        runs = parts[part["index"]]["runs"]
        assert [r["outcome"] for r in runs] == ["lost", "succeeded"], runs
        assert runs[0]["worker"] == part["worker"] and parts[part["index"]]["worker"] == \
            runs[1]["worker"]
        assert all(p["worker"] and p["runs"] for p in parts.values())
        for other in others:  # the other part went on, never interrupted
            assert parts[other["index"]]["attempts"] == 1
        client.download(job["id"], "sequence.json", tmp_path / "sequence.json")
        record = json.loads(Path(tmp_path / "sequence.json").read_text())
        assert [f["frame"] for f in record["frames"]] == list(FRAMES)
        assert all(f["done"] for f in record["frames"])
        client.download(job["id"], "metrics.json", tmp_path / "metrics.json")
        frames = json.loads(Path(tmp_path / "metrics.json").read_text())["frames"]
        key = part["frames"][0]
        assert frames[key]["resumed_at"] > 0  # from its checkpoint, not from the start
        assert all(frames[f]["resumed_at"] == 0 for o in others for f in o["frames"])
        listed = {a["path"] for a in client.artifacts(job["id"])}
        assert {f"frames/{f}/gaussians.ply" for f in FRAMES} | {"eval.json"} <= listed


def _with_ids(server: LiveServer, job_id: str, parts: list[dict]) -> list[dict]:
    """The parts with their job-store ids and lease owners (which the API does not show)."""
    from worker.store import JobStore

    store = JobStore(f"sqlite:///{server.data_dir / 'dgs.sqlite3'}")
    rows = {p.part_index: p for p in store.parts(job_id)}
    return [{**p, "id": rows[p["index"]].id, "lease_owner": rows[p["index"]].lease_owner}
            for p in parts]
