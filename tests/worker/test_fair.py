"""The fair pick (worker.fair, issue 42) on SQLite and PostgreSQL: whose job a free worker runs
when several tenants wait. The tenant with the fewest jobs on a worker goes first, then the one
served longest ago, then the oldest waiting job; a picked job holds its worker until claimed;
only waiting jobs take part; racing picks are serialized."""

from __future__ import annotations

import datetime as dt
import threading

from sqlalchemy import update

from worker.models import Job, utcnow
from worker.store import JobStore, Owner

STARTING = 300.0


def _queued(store: JobStore, tenant: str, *, sent: bool = True) -> str:
    job = store.create(tenant, "reconstruct", {}, capture_id=None)
    if sent:
        store.mark_dispatched(job.id)
    return job.id


def test_a_tenant_served_last_waits_for_one_never_served(store: JobStore):
    """A queues 3 jobs, then B 1: with one worker B's job runs second, not fourth."""
    a1, a2, a3 = (_queued(store, "a") for _ in range(3))
    b1 = _queued(store, "b")
    assert store.pick(a1, STARTING).status == "run"  # both unserved: A's job is older
    assert store.claim(a1, Owner.current(), 60, 3).status == "claimed"
    deferred = store.pick(a2, STARTING)  # A holds the worker: B's turn
    assert deferred.status == "defer" and (deferred.first.tenant, deferred.first.job) == ("b", b1)
    store.finish(a1, Owner.parse(store.get(a1).lease_owner), "succeeded")
    # Nothing on a worker either side now: B has not been served, A has.
    assert store.pick(a3, STARTING).status == "defer"
    assert store.pick(b1, STARTING).status == "run"
    assert store.get(b1).picked_at is not None and store.get(a2).picked_at is None
    # B's job is starting (picked, not yet claimed): it holds the worker, so A goes next.
    assert store.pick(a2, STARTING).status == "run"


def test_fewest_on_a_worker_goes_first(store: JobStore):
    b0 = _queued(store, "b")
    store.claim(b0, Owner.current(), 60, 3)  # B runs one (never picked: a claim without a pick)
    b1, a1 = _queued(store, "b"), _queued(store, "a")
    deferred = store.pick(b1, STARTING)
    assert deferred.status == "defer" and deferred.first.tenant == "a"
    assert deferred.first.on_worker == 0
    assert store.pick(a1, STARTING).status == "run"
    # A's picked job counts as on a worker: one each now, and B (never picked) was served
    # longest ago.
    a2 = _queued(store, "a")
    assert store.pick(a2, STARTING).status == "defer"
    assert store.pick(b1, STARTING).status == "run"


def test_only_waiting_jobs_take_part(store: JobStore):
    """A tenant whose only jobs cannot run now (never sent, cancelled, a job waiting for its
    parts, a cancel asked for) has no turn; a part is a waiting job."""
    _queued(store, "c", sent=False)
    store.request_cancel(_queued(store, "c"), "c")
    parent, parts = store.create_parted("d", "reconstruct", {}, [["000000"], ["000001"]],
                                        capture_id=None)
    store.mark_dispatched(parent.id)
    a1 = _queued(store, "a")
    assert store.pick(a1, STARTING).status == "run"
    a2 = _queued(store, "a")
    store.mark_dispatched(parts[0].id)  # a part sent to the broker waits like any job
    deferred = store.pick(a2, STARTING)
    assert deferred.status == "defer" and deferred.first.job == parts[0].id


def test_a_forced_pick_runs_and_a_stale_pick_frees_its_worker(store: JobStore):
    a1, b1 = _queued(store, "a"), _queued(store, "b")
    assert store.pick(a1, STARTING).status == "run"
    a2 = _queued(store, "a")
    assert store.pick(a2, STARTING).status == "defer"
    assert store.pick(a2, STARTING, force=True).status == "run"
    # Picked longer ago than the starting window, never claimed (its process died): A's two
    # jobs wait again, and B, never served, goes first.
    assert store.pick(a1, 0.0).first.tenant == "b"
    assert store.pick(b1, 0.0).status == "run"


def test_racing_picks_give_the_tenant_one_worker(store: JobStore):
    """Eight free workers pick A's jobs at once while B waits: exactly one of A's runs (each
    pick sees the picks before it)."""
    a_jobs = [_queued(store, "a") for _ in range(8)]
    _queued(store, "b")
    start, outcomes = threading.Barrier(8), []

    def pick(job_id: str) -> None:
        start.wait()
        outcomes.append(store.pick(job_id, STARTING).status)

    threads = [threading.Thread(target=pick, args=(j,)) for j in a_jobs]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert sorted(outcomes) == ["defer"] * 7 + ["run"]


def _running(store: JobStore, tenant: str, held: float) -> str:
    """A job of `tenant` claimed `held` seconds ago (its run's start moved back)."""
    job_id = _queued(store, tenant)
    assert store.claim(job_id, Owner.current(), 600, 3).status == "claimed"
    with store.session() as s:
        s.execute(update(Job).where(Job.id == job_id).values(
            run_started_at=utcnow() - dt.timedelta(seconds=held)))
    return job_id


def _ask(store: JobStore, job_id: str, share_after: float = 10.0,
         time_slice: float = 0.0) -> bool:
    return store.ask_to_yield(job_id, store.get(job_id).lease_owner, share_after=share_after,
                              time_slice=time_slice, starting_seconds=STARTING)


def test_a_tenant_two_workers_ahead_gives_one_up(store: JobStore):
    """A holds both workers, B waits: A's job claimed last gives its worker up once it has
    held it `share_after` seconds; one ask at a time; the shares then even, nobody is asked."""
    a_old, a_new = _running(store, "a", 60), _running(store, "a", 30)
    b1 = _queued(store, "b")
    assert not _ask(store, a_new, share_after=45)  # not held long enough yet
    assert not _ask(store, a_old)  # held long enough, but A's other job was claimed last
    assert _ask(store, a_new)
    assert store.get(a_new).yield_asked_at is not None
    assert not _ask(store, a_old)  # the ask before has not left its worker yet
    owner = Owner.parse(store.get(a_new).lease_owner)
    assert store.release(a_new, owner, "back in the queue: it gave its worker to another "
                         "tenant's job (fair share) at step 7")
    released = store.get(a_new)
    assert (released.state, released.attempts, released.redeliveries) == ("queued", 1, 0)
    assert released.runs[-1]["outcome"] == "released"
    store.mark_dispatched(a_new)
    assert store.pick(a_new, STARTING).status == "defer"  # B has the turn: 0 on a worker
    assert store.pick(b1, STARTING).status == "run"
    store.claim(b1, Owner.current(), 600, 3)
    assert not _ask(store, a_old)  # one each: even
    # A's released job resumes later with a new attempt number; its ask is gone.
    store.finish(b1, Owner.parse(store.get(b1).lease_owner), "succeeded")
    assert store.pick(a_new, STARTING).status == "run"
    store.claim(a_new, Owner.current(), 600, 3)
    resumed = store.get(a_new)
    assert resumed.attempts == 2 and resumed.yield_asked_at is None


def test_a_running_job_looks_for_a_cancel_and_a_waiting_tenant(store: JobStore):
    """`watch`, a running job's read between heartbeats: its cancel, and whether a job of
    another tenant waits (its own tenant's, a cancelled one, or a lease it lost: nothing)."""
    a1 = _running(store, "a", 60)
    owner = store.get(a1).lease_owner

    def watch(job_id: str = a1, holder: str = owner) -> tuple[bool, bool]:
        return store.watch(job_id, holder, starting_seconds=STARTING)

    _queued(store, "a")
    assert watch() == (False, False)  # only A waits
    b1 = _queued(store, "b")
    assert watch() == (False, True)
    assert watch(holder="someone-else") == (False, False)
    store.request_cancel(b1, "b")
    assert watch() == (False, False)
    store.request_cancel(a1, "a")
    assert watch() == (True, False)


def test_one_worker_less_keeps_it_unless_time_sliced(store: JobStore):
    """With one worker each tenant cannot have its share: A's job keeps the worker (B's turn
    comes when it ends) unless time slicing is on, then after a slice."""
    a1 = _running(store, "a", 30)
    _queued(store, "b")
    assert not _ask(store, a1)
    assert not _ask(store, a1, time_slice=60)
    assert _ask(store, a1, time_slice=20)


def test_nobody_is_asked_for_its_own_tenant_or_a_cancelled_job(store: JobStore):
    a1, a2 = _running(store, "a", 60), _running(store, "a", 60)
    _queued(store, "a")
    assert not _ask(store, a1) and not _ask(store, a2)  # only A waits
    b1 = _queued(store, "b")
    store.request_cancel(b1, "b")  # B's one job is cancelled: B does not wait
    assert not _ask(store, a1) and not _ask(store, a2)
    _queued(store, "c")
    store.request_cancel(a2, "a")  # a job asked to stop already is not asked again
    assert not _ask(store, a2)
    assert _ask(store, a1)


def test_a_job_given_back_is_not_starting(store: JobStore):
    """A job released after its pick and claim holds no worker and waits again once sent: the
    tenant's other job is not asked too (one each would be two asks for one waiting job)."""
    a1, a2 = _queued(store, "a"), _queued(store, "a")
    for job_id in (a1, a2):
        assert store.pick(job_id, STARTING, force=True).status == "run"
        store.claim(job_id, Owner.current(), 600, 3)
    with store.session() as s:
        s.execute(update(Job).where(Job.id.in_([a1, a2])).values(
            picked_at=utcnow() - dt.timedelta(seconds=61),
            run_started_at=utcnow() - dt.timedelta(seconds=60)))
    b1 = _queued(store, "b")
    asked = [j for j in (a1, a2) if _ask(store, j)]
    assert len(asked) == 1
    store.release(asked[0], Owner.parse(store.get(asked[0]).lease_owner), "back in the queue")
    assert not any(_ask(store, j) for j in (a1, a2))  # A 1 on a worker, B 0: even enough
    store.mark_dispatched(asked[0])
    deferred = store.pick(asked[0], STARTING)  # waiting again, behind B
    assert deferred.status == "defer" and deferred.first.job == b1


def test_the_process_that_gave_way_is_handed_the_waiting_job(store: JobStore):
    """A's job gives its worker up to B: its pool process is handed B's oldest waiting job
    (marked picked, so no other worker's pick gives B a second one), never one of A's own;
    nothing is handed when nobody else waits or when the job's time limit does not fit."""
    a_old, a_new = _running(store, "a", 60), _running(store, "a", 30)
    b1, b2 = _queued(store, "b"), _queued(store, "b")
    everything = ("reconstruct", "relight", "export")
    assert _ask(store, a_new)
    store.release(a_new, Owner.parse(store.get(a_new).lease_owner), "back in the queue")
    store.mark_dispatched(a_new)  # a sweeper sent it again: A waits too, with one on a worker
    assert store.hand_over("a", STARTING, pipelines=("relight",)) is None  # does not fit
    assert store.get(b1).picked_at is None
    assert store.hand_over("a", STARTING, pipelines=everything) == b1
    assert store.get(b1).picked_at is not None
    store.claim(b1, Owner.current(), 600, 3)
    # One each on a worker now; B was served (the hand-over's pick), A never (its jobs were
    # claimed without one): A has the turn, so A's process is handed nothing (never its own
    # tenant's job), and a process of B's that gave way would be handed A's.
    assert store.hand_over("a", STARTING, pipelines=everything) is None
    assert store.get(b2).picked_at is None
    assert store.hand_over("b", STARTING, pipelines=everything) == a_new
    for job_id in (a_old, b1):
        store.finish(job_id, Owner.parse(store.get(job_id).lease_owner), "succeeded")
    with store.session() as s:
        s.execute(update(Job).where(Job.tenant.in_(["a", "b"]), Job.state == "queued")
                  .values(state="cancelled"))
    assert store.hand_over("a", STARTING, pipelines=everything) is None  # nobody waits


def test_a_job_picked_before_another_tenant_came_gives_its_turn_up_at_start(store: JobStore):
    """A's second job was picked while A was alone; B comes to wait before A's pool process
    claims it: the process gives A's turn to B (A's job back to waiting, no attempt, a new
    message from a sweeper) rather than claim it and stop a few seconds later. Not with the
    fair share off, not with the shares even, not for a job that was never picked."""
    a_old = _running(store, "a", 60)
    a_new = _queued(store, "a")
    assert store.pick(a_new, STARTING).status == "run"  # A alone: its turn
    assert not store.gives_way_at_start(a_new, share_after=1, starting_seconds=STARTING)
    b1 = _queued(store, "b")
    assert not store.gives_way_at_start(a_new, share_after=0, starting_seconds=STARTING)
    assert store.gives_way_at_start(a_new, share_after=1, starting_seconds=STARTING)
    back = store.get(a_new)
    assert (back.state, back.attempts, back.picked_at, back.dispatched_at) == (
        "queued", 0, None, None)
    assert store.hand_over("a", STARTING, pipelines=("reconstruct",)) == b1
    store.claim(b1, Owner.current(), 600, 3)
    store.mark_dispatched(a_new)  # the sweeper's new message: one each on a worker now
    assert store.pick(a_new, STARTING, force=True).status == "run"
    _queued(store, "b")  # B waits again, one job behind A (2 on a worker to 1): even enough
    assert not store.gives_way_at_start(a_new, share_after=1, starting_seconds=STARTING)
    assert not store.gives_way_at_start(_queued(store, "a"), share_after=1,
                                        starting_seconds=STARTING)  # never picked
    assert store.get(a_old).state == "running"
