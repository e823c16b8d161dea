"""worker.quota and JobStore.active_jobs on SQLite and PostgreSQL (issue 42): the active-jobs
cap counts a job run as parts once and holds against concurrent submits; the token bucket
refuses past its burst, says how long to wait, refills with its clock and is shared by every
session (so by every API process) on one job store."""

from __future__ import annotations

import threading

import pytest

from worker.quota import CapReached, Rate, take
from worker.store import JobStore


def _active(store: JobStore, tenant: str) -> int:
    with store.session(write=False) as s:
        return JobStore.active_jobs(s, tenant)


def test_a_job_run_as_parts_counts_once_and_ended_jobs_not_at_all(store: JobStore):
    store.create_parted("a", "reconstruct", {}, [["000000"], ["000001"], ["000002"]],
                        capture_id=None)
    done = store.create("a", "reconstruct", {}, capture_id=None)
    store.request_cancel(done.id, "a")
    store.create("b", "reconstruct", {}, capture_id=None)
    assert _active(store, "a") == 1 and _active(store, "b") == 1
    with pytest.raises(CapReached) as refused:
        store.create("a", "reconstruct", {}, capture_id=None, cap=1)
    assert (refused.value.active, refused.value.cap) == (1, 1)
    assert _active(store, "a") == 1  # nothing was added
    with pytest.raises(CapReached):  # a retry would queue it again: past the cap too
        store.retry(done.id, "a", cap=1)
    assert store.get(done.id).state == "cancelled"
    assert store.retry(done.id, "a", cap=2).state == "queued"


def test_concurrent_submits_cannot_pass_the_cap_together(store: JobStore):
    """Twelve creates released together with a cap of 4: exactly 4 jobs (the count and the
    insert share a transaction under the tenant's lock)."""
    start, made, refused = threading.Barrier(12), [], []

    def submit() -> None:
        start.wait()
        try:
            made.append(store.create("a", "reconstruct", {}, capture_id=None, cap=4).id)
        except CapReached:
            refused.append(1)

    threads = [threading.Thread(target=submit) for _ in range(12)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert (len(made), len(refused)) == (4, 8) and _active(store, "a") == 4


def test_the_bucket_refuses_past_its_burst_and_refills_with_its_clock(store_url: str):
    rate = Rate(per_second=0.5, burst=3)
    assert [take(store_url, "changes:a", rate, 100.0) for _ in range(3)] == [0.0] * 3
    assert take(store_url, "changes:a", rate, 100.0) == pytest.approx(2.0)  # 1 token / 0.5/s
    assert take(store_url, "changes:b", rate, 100.0) == 0.0  # another bucket: untouched
    assert take(store_url, "changes:a", rate, 101.0) == pytest.approx(1.0)  # half a token
    assert take(store_url, "changes:a", rate, 102.0) == 0.0  # one token back, taken
    assert take(store_url, "changes:a", rate, 99.0) == pytest.approx(2.0)  # a clock behind
    assert [take(store_url, "changes:a", rate, 1e6) for _ in range(4)][-1] > 0  # burst caps


def test_the_bucket_is_shared_by_concurrent_takers(store_url: str):
    """Sixteen takers at once on a burst of 5 (each its own session, as API processes are):
    five pass."""
    rate, start, waits = Rate(per_second=0.001, burst=5), threading.Barrier(16), []

    def taker() -> None:
        start.wait()
        waits.append(take(store_url, "changes:a", rate, 50.0))

    threads = [threading.Thread(target=taker) for _ in range(16)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert sorted(w == 0.0 for w in waits) == [False] * 11 + [True] * 5


@pytest.mark.parametrize("per_second, burst", [(0.0, 1), (-1.0, 1), (1.0, 0)])
def test_a_rate_must_be_positive_with_a_burst_of_one_or_more(per_second, burst):
    with pytest.raises(ValueError, match="per_second|burst"):
        Rate(per_second, burst)
