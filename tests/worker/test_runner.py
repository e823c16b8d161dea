"""The runner and its heartbeat, without Celery: failures are recorded with the right code, a
job that does not reach a step boundary after a cancel has its process ended, a worker that
lost its lease writes nothing more, the sweeper deletes what expired."""

from __future__ import annotations

import datetime as dt
import json
import secrets
import signal
import subprocess
import sys
import textwrap
import threading
import time
import warnings
from pathlib import Path

import pytest
import torch
from billiard.exceptions import SoftTimeLimitExceeded
from sqlalchemy import update
from worker_harness import add_capture, tiny_config, wait_for

from core.config import read_run
from core.data import load_capture
from worker.blobs import LocalBlobStore
from worker.models import Asset, Capture, Job, utcnow
from worker.pipelines import MODEL_KIND, ReconstructParams
from worker.progress import JobLink
from worker.runner import Runner
from worker.settings import WorkerSettings
from worker.store import JobStore, Owner
from worker.sweeper import Sweeper


@pytest.fixture
def setup(tmp_path: Path, store_url: str):
    settings = WorkerSettings(data_dir=tmp_path / "data", database_url=store_url,
                              heartbeat_seconds=0.2, lease_seconds=5, cancel_grace_seconds=1)
    store = JobStore(store_url)
    blobs = LocalBlobStore(settings.data_dir / "store")
    return settings, store, blobs


def test_bad_parameters_and_missing_capture_fail_clearly(setup, tiny_capture: Path):
    settings, store, blobs = setup
    runner = Runner(settings, store, blobs)
    cap = add_capture(store, blobs, tiny_capture)
    bad = store.create("t1", "reconstruct", {"preset": "huge"}, capture_id=cap)
    assert runner.run(bad.id).status == "failed"
    err = store.get(bad.id).error
    assert err["code"] == "invalid_input" and not err["retryable"] and "preset" in err["message"]

    unknown = store.create("t1", "reconstruct", {"preset": "test", "config": {"nope": 1}},
                           capture_id=cap)
    assert runner.run(unknown.id).status == "failed"
    assert "config.nope: unknown setting" in store.get(unknown.id).error["message"]

    gone = store.create("t1", "reconstruct", {"preset": "test"}, capture_id=None)
    assert runner.run(gone.id).status == "failed"
    assert "capture" in store.get(gone.id).error["message"]
    assert runner.run(gone.id).status == "terminal"  # a second delivery changes nothing
    assert runner.run("job_missing").status == "missing"


def test_a_job_runs_the_run_it_stored_at_submit(setup, tiny_capture: Path):
    """The worker runs the run the API resolved at submit (Job.resolved_run) as it is: what
    its parameters would resolve to now (say, a preset changed since) does not change it."""
    settings, store, blobs = setup
    cap = add_capture(store, blobs, tiny_capture)
    config = {**tiny_config(3), "mesh": {"enabled": False}, "split": "none"}
    params = ReconstructParams(preset="test", config=config)
    resolved = params.resolve(load_capture(tiny_capture), capture_name=cap)
    drifted = {"preset": "test", "config": {**config, "split": "every8", "train": {
        **config["train"], "seed": 9}}}
    job = store.create("t1", "reconstruct", drifted, capture_id=cap,
                       resolved_run=resolved.to_json())
    assert Runner(settings, store, blobs).run(job.id).status == "succeeded", \
        store.get(job.id).error
    ran = read_run(settings.data_dir / "store" / "jobs" / job.id / "artifacts")
    assert ran.same_run(resolved) and ran.config.train.seed == 0 and ran.capture == cap
    assert ran.views.split.rule == "none" and ran.config.train.device == "cpu"


class _RemoteStore(LocalBlobStore):
    """A store whose blobs are not files on this machine (as S3's), counting the downloads."""

    def __init__(self, root: Path):
        super().__init__(root)
        self.downloads, self._lock = 0, threading.Lock()

    def local_path(self, key: str) -> None:
        return None

    def get_file(self, key: str, dest: Path) -> None:
        with self._lock:
            self.downloads += 1
        super().get_file(key, dest)


def test_two_jobs_on_one_capture_fetch_it_once(setup, tiny_capture: Path):
    """Two pool processes start jobs on one capture at once (threads stand in for them): one
    fetches it into the scratch folder while the other waits, and both read every file whole.
    Both used to download into the same temporaries, and one job failed."""
    settings, store, _ = setup
    blobs = _RemoteStore(settings.data_dir / "store")
    cap = add_capture(store, blobs, tiny_capture)
    jobs = [store.create("t1", "reconstruct", {"preset": "test"}, capture_id=cap)
            for _ in range(2)]
    runner, start, got = Runner(settings, store, blobs), threading.Barrier(2), {}

    def fetch(job) -> None:
        start.wait()
        got[job.id] = runner.capture(job, JobLink(store, job, Owner.current(), settings))

    threads = [threading.Thread(target=fetch, args=(job,)) for job in jobs]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    files = sorted(p for p in tiny_capture.rglob("*") if p.is_file())
    assert blobs.downloads == len(files)
    for folder in got.values():
        assert folder == settings.scratch / "captures" / cap
        for path in files:
            assert (folder / path.relative_to(tiny_capture)).read_bytes() == path.read_bytes()
    assert load_capture(folder).frames


class _CancelledWhileFetching(_RemoteStore):
    """A remote store whose job is cancelled during its first download: the download returns
    once the job's heartbeat has seen the cancel (its log line is in the store)."""

    def __init__(self, root: Path, store: JobStore):
        super().__init__(root)
        self.store, self.job_id = store, None

    def get_file(self, key: str, dest: Path) -> None:
        super().get_file(key, dest)
        if self.job_id is not None and self.downloads == 1:
            self.store.request_cancel(self.job_id, "t1")
            wait_for(lambda: any("cancel requested" in r.line
                                 for r in self.store.logs(self.job_id, 0, 100)),
                     300, "the heartbeat to see the cancel")


def test_a_job_cancelled_while_its_capture_downloads_stops_there(setup, tiny_capture: Path):
    """A cancel that comes while a job's capture downloads stops the download at the next file
    (not after the whole capture, then the run's setup): the job is cancelled, the half
    download is not marked complete, and the next job on the capture fetches all of it."""
    settings, store, _ = setup
    settings = settings.model_copy(update={"cancel_grace_seconds": 600})  # never killed here
    blobs = _CancelledWhileFetching(settings.data_dir / "store", store)
    cap = add_capture(store, blobs, tiny_capture)
    job = store.create("t1", "reconstruct", {"preset": "test"}, capture_id=cap)
    blobs.job_id = job.id
    assert Runner(settings, store, blobs).run(job.id).status == "cancelled"
    assert store.get(job.id).state == "cancelled" and blobs.downloads == 1
    lines = [r.line for r in store.logs(job.id, 0, 100)]
    assert any("fetching the capture (1 of " in line for line in lines), lines
    folder = settings.scratch / "captures" / cap
    assert not (folder / ".complete").exists()

    blobs.job_id = None
    again = store.create("t1", "reconstruct", {"preset": "test"}, capture_id=cap)
    link = JobLink(store, again, Owner.current(), settings)
    assert Runner(settings, store, blobs).capture(again, link) == folder
    files = sorted(p for p in tiny_capture.rglob("*") if p.is_file())
    assert blobs.downloads == 1 + len(files) and (folder / ".complete").is_file()


class _OutOfTime:
    """An execution whose task reaches its soft time limit (Celery raises it in the job)."""

    retry_note = "retry resumes from the last checkpoint"

    def run(self) -> None:
        raise SoftTimeLimitExceeded()


def test_a_handed_job_that_reaches_the_borrowed_time_limit_goes_back_to_the_queue(
        setup, tiny_capture: Path, monkeypatch: pytest.MonkeyPatch):
    """A job handed to a pool process after another gave way runs under that task's time limit:
    reaching it gives the job back to the queue (no attempt counted), where a job that ran
    under its own limit fails with time_limit, retryable."""
    settings, store, blobs = setup
    cap = add_capture(store, blobs, tiny_capture)
    monkeypatch.setattr(Runner, "_execution", lambda self, job, link: _OutOfTime())
    handed = store.create("t1", "reconstruct", {"preset": "test"}, capture_id=cap)
    outcome = Runner(settings, store, blobs).run(handed.id, handed=True)
    assert (outcome.status, outcome.gave_way) == ("released", False)
    back = store.get(handed.id)
    assert back.state == "queued" and back.lease_owner is None and back.redeliveries == 0
    assert back.message == ("back in the queue: its pool process reached its time limit (it "
                            "ran another job first)")
    lines = [r.line for r in store.logs(handed.id, 0, 100)]
    assert any(line.endswith("to resume from its last checkpoint; back in the queue")
               for line in lines), lines

    own = store.create("t1", "reconstruct", {"preset": "test"}, capture_id=cap)
    assert Runner(settings, store, blobs).run(own.id).status == "failed"
    error = store.get(own.id).error
    assert error["code"] == "time_limit" and error["retryable"]


def test_a_duplicate_message_of_a_running_job_is_dropped(setup):
    settings, store, blobs = setup
    job = store.create("t1", "reconstruct", {"preset": "test"}, capture_id=None)
    holder = Owner.current()
    store.claim(job.id, holder, 5, 3)
    outcome = Runner(settings, store, blobs).run(job.id)
    assert outcome.status == "leased" and str(holder) in outcome.note
    assert "duplicate message is dropped" in outcome.note
    assert store.get(job.id).lease_owner == str(holder) and store.get(job.id).attempts == 1


def test_a_worker_that_lost_its_lease_stops_without_writing(setup, tiny_capture: Path):
    settings, store, blobs = setup
    cap = add_capture(store, blobs, tiny_capture)
    job = store.create("t1", "reconstruct", {"preset": "test", "config": tiny_config(3000)},
                       capture_id=cap)
    runner = Runner(settings, store, blobs)
    thief = Owner.current()

    def steal() -> None:  # another worker took over (this one was presumed dead)
        # A bound for a broken run only (a loaded machine may take minutes to start it).
        wait_for(lambda: store.get(job.id).iteration > 3, 600, "the job to start")
        with store.session() as s:
            s.execute(update(Job).where(Job.id == job.id).values(lease_owner=str(thief)))

    import threading

    t = threading.Thread(target=steal)
    t.start()
    assert runner.run(job.id).status == "lost"
    t.join()
    after = store.get(job.id)
    assert after.state == "running" and after.lease_owner == str(thief)
    assert store.finish(job.id, thief, "succeeded")


WEDGED = textwrap.dedent("""
    import sys, time
    from worker.models import Job
    from worker.progress import JobLink
    from worker.settings import WorkerSettings
    from worker.store import JobStore, Owner
    settings = WorkerSettings(database_url=sys.argv[1], heartbeat_seconds=0.2,
                              cancel_grace_seconds=1.0, lease_seconds=30)
    store = JobStore(sys.argv[1])
    owner = Owner.current()
    claim = store.claim(sys.argv[2], owner, 30, 3)
    JobLink(store, claim.job, owner, settings).start()
    print("running", flush=True)
    time.sleep(120)  # a long native call that never reaches a step boundary
""")


def test_cancel_ends_a_wedged_process(setup, tmp_path: Path):
    settings, store, blobs = setup
    job = store.create("t1", "reconstruct", {}, capture_id=None)
    proc = subprocess.Popen([sys.executable, "-c", WEDGED, settings.database, job.id],
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "running"
    store.request_cancel(job.id, "t1")
    # The process never reaches a step boundary: its heartbeat sees the cancel, waits out the
    # grace and ends the process itself (SIGKILL, -9), recording the job as cancelled first.
    # The bound below only keeps a broken heartbeat from hanging the test; no duration is
    # asserted (the process would otherwise sleep 120 s and exit 0).
    proc.wait(timeout=110)
    assert proc.returncode == -signal.SIGKILL
    after = store.get(job.id)
    assert after.state == "cancelled" and "process ended" in after.message
    lines = [r.line for r in store.logs(job.id, 0, 100)]
    assert any("cancel requested: stopping after the current step" in line for line in lines)
    assert any("did not stop within 1 s of the cancel" in line for line in lines)


def test_joblink_progress_is_monotonic_with_an_eta(setup):
    settings, store, blobs = setup
    job = store.create("t1", "reconstruct", {}, capture_id=None)
    owner = Owner.current()
    claim = store.claim(job.id, owner, 5, 3)
    link = JobLink(store, claim.job, owner, settings)
    link._start = (time.monotonic() - 10.0, 0.0)  # ten seconds into the run
    link.update(fraction=0.25, stage="appearance", iteration=25, iterations=100)
    link.update(fraction=0.2, stage="appearance", iteration=20, iterations=100)  # a resume
    link.log("hello")
    link.close()
    now = store.get(job.id)
    assert now.fraction == 0.25 and now.iteration == 20
    assert now.eta_s == pytest.approx(30.0, rel=0.05)  # 10 s for a quarter: 30 s to go
    assert [r.line[9:] for r in store.logs(job.id, 0, 10)] == ["hello"]


def test_sweeper_deletes_what_expired_and_nothing_else(setup, tiny_capture: Path):
    settings, store, blobs = setup
    sweeper = Sweeper(settings, lambda job_id: None, store=store, blobs=blobs)
    past, future = utcnow() - dt.timedelta(days=1), utcnow() + dt.timedelta(days=1)
    old_cap = add_capture(store, blobs, tiny_capture, capture_id="cap_old")
    busy_cap = add_capture(store, blobs, tiny_capture, capture_id="cap_busy")
    old_job = store.create("t1", "reconstruct", {}, capture_id=old_cap, expires_at=past)
    owner = Owner.current()
    store.claim(old_job.id, owner, 5, 3)
    store.finish(old_job.id, owner, "succeeded")
    active = store.create("t1", "reconstruct", {}, capture_id=busy_cap, expires_at=past)
    kept = store.create("t1", "reconstruct", {}, capture_id=old_cap, expires_at=future)
    store.claim(kept.id, owner, 5, 3)
    store.finish(kept.id, owner, "failed")
    (tmp := settings.data_dir / "x.bin").write_bytes(b"x")
    blobs.put_file(f"jobs/{old_job.id}/artifacts/eval.json", tmp)
    blobs.put_file("assets/ast_old/env.exr", tmp)
    with store.session() as s:
        s.execute(update(Capture).values(expires_at=past))
        s.add(Asset(id="ast_old", tenant="t1", kind="envmap", filename="env.exr", size=1,
                    sha256="0" * 64, content_type="image/x-exr", expires_at=past))
    gone = sweeper.expire()
    assert gone == {"jobs": [old_job.id], "captures": [old_cap], "assets": ["ast_old"]}
    assert store.get(old_job.id) is None and blobs.list(f"jobs/{old_job.id}") == []
    assert blobs.list("captures/cap_old") == [] and blobs.list("assets") == []
    assert store.get(active.id).state == "queued" and blobs.list("captures/cap_busy")
    assert store.get(kept.id).capture_id is None  # its capture went; the job stays


def test_sweeper_keeps_what_an_active_job_needs(setup, tiny_capture: Path):
    """A render's source and envmap, a reconstruction's normal model (deleted before, as the
    sweeper looked at renders only)."""
    settings, store, blobs = setup
    sweeper = Sweeper(settings, lambda job_id: None, store=store, blobs=blobs)
    past = utcnow() - dt.timedelta(days=1)
    owner = Owner.current()
    sources = []
    for _ in range(2):
        job = store.create("t1", "reconstruct", {}, capture_id=None, expires_at=past)
        store.claim(job.id, owner, 5, 3)
        store.finish(job.id, owner, "succeeded")
        sources.append(job.id)
    with store.session() as s:
        for asset, kind in (("ast_used", "envmap"), ("ast_free", "envmap"),
                            ("ast_model", "normal_model")):
            s.add(Asset(id=asset, tenant="t1", kind=kind, filename="env.exr", size=1,
                        sha256="0" * 64, content_type="image/x-exr", expires_at=past))
    active = store.create_render("t1", sources[0], "relight", {"envmap": "ast_used"})
    store.create("t1", "reconstruct", {"config": {"normal_estimator": "ast_model"}},
                 capture_id=None)
    ended = store.create_render("t1", sources[1], "relight", {"envmap": "ast_free"})
    store.claim(ended.id, owner, 5, 3)
    store.finish(ended.id, owner, "failed")
    gone = sweeper.expire()
    assert gone == {"jobs": [sources[1]], "captures": [], "assets": ["ast_free"]}
    assert store.get(active.id).source_job_id == sources[0]
    assert store.get(ended.id).source_job_id is None  # its source went; the render stays


class _Facing(torch.nn.Module):
    """A normal estimator: every pixel faces the camera."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = torch.zeros_like(x)
        out[:, 2] = -1.0
        return out


def test_a_normal_estimator_is_a_model_asset_or_an_allowed_name_never_a_path(
        setup, tmp_path: Path):
    """A job's `normal_estimator` names the tenant's model asset (fetched from the store) or a
    model the operator allows; a path fails the job with the same message whether or not the
    file exists, and nothing is loaded from it."""
    from core.synth import SynthConfig, synthesize

    settings, store, blobs = setup
    capture = tmp_path / "capture"  # no normals/: the priors must come from the estimator
    synthesize(capture, SynthConfig(frames=1, views=8, width=24, height=24, seed=5,
                                    priors=False, ao_directions=4))
    cap = add_capture(store, blobs, capture)
    model = tmp_path / "facing.pt"
    with warnings.catch_warnings():  # TorchScript is deprecated in torch 2.x, still shipped
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.script(_Facing()).save(str(model))
    blobs.put_file("assets/ast_model/facing.pt", model)
    with store.session() as s:
        s.add(Asset(id="ast_model", tenant="t1", kind=MODEL_KIND, filename="facing.pt",
                    size=model.stat().st_size, sha256="0" * 64,
                    content_type="application/octet-stream", meta={}))
    settings = settings.model_copy(update={"normal_estimators": {"served": model}})
    runner = Runner(settings, store, blobs)

    def job(name: str) -> str:
        config = {**tiny_config(3), "normal_estimator": name, "mesh": {"enabled": False}}
        return store.create("t1", "reconstruct", {"preset": "test", "config": config},
                            capture_id=cap).id

    messages = []
    for path in (str(model), str(tmp_path / "missing.pt"), "ast_other"):
        failed = job(path)
        assert runner.run(failed).status == "failed"
        error = store.get(failed).error
        assert error["code"] == "invalid_input" and not error["retryable"]
        messages.append(error["message"].replace(path, "NAME"))
    assert messages[0] == messages[1] == messages[2] and "neither" in messages[0], messages
    for name in ("ast_model", "served"):
        done = job(name)
        assert runner.run(done).status == "succeeded", store.get(done).error
        metrics = json.loads((settings.data_dir / "store" / "jobs" / done / "artifacts" /
                              "metrics.json").read_text())
        assert metrics["frames"]["000000"]["normal_prior"] == "estimator"
        resolved = read_run(settings.data_dir / "store" / "jobs" / done / "artifacts")
        assert resolved.config.normal_estimator == name  # the name, not where it was put


def test_a_pool_process_gives_its_turn_up_when_another_tenant_came(setup):
    """A's job was picked while A was alone, and B came to wait while its pool process
    started: the runner claims nothing (no attempt), answers that the job gave way (the task
    then runs B's job in this process, worker.tasks) and A's job waits again."""
    settings, store, blobs = setup
    ta, tb = (f"{t}-{secrets.token_hex(3)}" for t in "ab")
    a1, a2 = (store.create(ta, "reconstruct", {"preset": "test"}, capture_id=None)
              for _ in range(2))
    b1 = store.create(tb, "reconstruct", {"preset": "test"}, capture_id=None)
    for job in (a1, a2):
        store.mark_dispatched(job.id)
    assert store.pick(a1.id, 300).status == "run"
    assert store.claim(a1.id, Owner.current(), 600, 3).status == "claimed"
    assert store.pick(a2.id, 300).status == "run"
    store.mark_dispatched(b1.id)
    try:
        outcome = Runner(settings, store, blobs).run(a2.id)
        assert (outcome.status, outcome.gave_way) == ("released", True)
        assert "fair share" in outcome.note
        assert "its turn goes to" in "".join(log.line for log in store.logs(a2.id, 0, 10))
        job = store.get(a2.id)
        assert (job.state, job.attempts, job.runs or [], job.dispatched_at) == (
            "queued", 0, [], None)
    finally:  # nothing left waiting in a shared PostgreSQL for other tests' picks
        for job, tenant in ((a1, ta), (a2, ta), (b1, tb)):
            store.request_cancel(job.id, tenant)


def test_a_pool_process_gives_a_jobs_memory_back_before_the_next(tmp_path: Path):
    """A pool process runs several jobs (worker.celery_app): after each, the job's freed heap
    goes back to the system (glibc keeps it resident otherwise), so an idle worker holds what
    torch needs, not its last job's peak. In a process of its own, to read its memory alone."""
    code = textwrap.dedent("""
        import gc, torch
        import worker.runner as runner
        def rss():
            return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20
        if runner._LIBC is None:
            print("no glibc"); raise SystemExit
        base = rss()
        held = [torch.randn(1000, 100) for _ in range(2500)]  # 1 GB in 400 KB pieces
        del held
        gc.collect()
        runner._release_memory()
        print(base, rss())
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[2], timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    if out.stdout.strip() == "no glibc":
        pytest.skip("no malloc_trim in this C library")
    base, after = map(float, out.stdout.split())
    assert after < base + 200, (base, after)  # 1,000 MiB were resident before the release
