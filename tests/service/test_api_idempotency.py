"""Idempotency-Key on POST /v1/jobs, /v1/renders and /v1/exports (issue 32): a stored key answers
the job its first submit made, a key reused for another request is refused, keys are per tenant,
expire and go with their job, and submits racing with one key make one job, on SQLite and on
PostgreSQL (the database's unique constraint decides, not a check before the insert)."""

from __future__ import annotations

import json

import pytest
from sqlalchemy import func, select, update
from service_harness import submit_together
from test_api_renders import finished

from worker.idempotency import Idempotency, forget_expired
from worker.models import IdempotencyKey, Job, utcnow
from worker.store import NotCreated

BOTH = pytest.mark.parametrize("database_url", ["sqlite", "postgres"], indirect=True)
TEST = {"preset": "test"}


def _count(services) -> int:
    with services.store.session(write=False) as s:
        return s.scalar(select(func.count()).select_from(Job).where(Job.parent_id.is_(None)))


def _post(client, path: str, body: dict, key: str | None, headers: dict | None = None):
    return client.post(path, json=body, headers={**(headers or {}),
                                                  **({"Idempotency-Key": key} if key else {})})


@BOTH
def test_a_stored_key_answers_the_first_job(client, services, ready_capture):
    capture = ready_capture()
    body = {"capture_id": capture, "params": TEST, "name": "take 1"}
    first = _post(client, "/v1/jobs", body, "k-1")
    assert first.status_code == 202 and "Idempotent-Replayed" not in first.headers
    # The same request again (as a client sends it after a timeout), written another way.
    again = client.post("/v1/jobs", content=json.dumps({
        "name": "take 1", "params": {"preset": "test"}, "capture_id": capture,
        "pipeline": "reconstruct"}), headers={"Idempotency-Key": "k-1",
                                              "Content-Type": "application/json"})
    assert again.status_code == 202 and again.headers["Idempotent-Replayed"] == "true"
    assert again.json()["id"] == first.json()["id"]
    assert again.headers["Location"] == first.headers["Location"]
    assert _count(services) == 1
    # Whatever became of it: a cancelled job is still the answer.
    client.post(f"/v1/jobs/{first.json()['id']}/cancel")
    replay = _post(client, "/v1/jobs", body, "k-1")
    assert replay.json()["id"] == first.json()["id"] and replay.json()["state"] == "cancelled"
    # Without a key, every submit is a job.
    assert _post(client, "/v1/jobs", body, None).json()["id"] != first.json()["id"]
    assert _count(services) == 2


def test_a_key_reused_for_another_request_is_refused(client, services, ready_capture):
    capture = ready_capture()
    source = finished(services, capture_id=capture)
    job = _post(client, "/v1/jobs", {"capture_id": capture, "params": TEST}, "k-2").json()
    for path, body in (("/v1/jobs", {"capture_id": capture, "params": {"preset": "fast"}}),
                       ("/v1/renders", {"job_id": source, "envmap": "builtin:studio"}),
                       ("/v1/exports", {"job_id": source})):
        r = _post(client, path, body, "k-2")
        assert r.status_code == 422, r.text
        error = r.json()["error"]
        assert error["code"] == "idempotency_key_reused"
        assert error["details"][0]["path"] == "header.Idempotency-Key"
    assert _count(services) == 2  # the source and the job
    assert client.get(f"/v1/jobs/{job['id']}").json()["params"]["preset"] == "test"


@pytest.mark.parametrize("key", ["", "a b", "x" * 256, "naïve"])
def test_a_malformed_key_is_refused(client, services, ready_capture, key):
    r = client.post("/v1/jobs", json={"capture_id": ready_capture(), "params": TEST},
                    headers={"Idempotency-Key": key.encode()})
    assert r.status_code == 422, r.text
    assert r.json()["error"]["details"][0]["path"] == "header.Idempotency-Key"
    assert _count(services) == 0


def test_keys_are_per_tenant_expire_and_go_with_their_job(client, services, tenants,
                                                          ready_capture):
    a, b = tenants["a"], tenants["b"]
    cap_a, cap_b = ready_capture(a), ready_capture(b)
    job_a = _post(client, "/v1/jobs", {"capture_id": cap_a, "params": TEST}, "same", a).json()
    job_b = _post(client, "/v1/jobs", {"capture_id": cap_b, "params": TEST}, "same", b).json()
    assert job_a["id"] != job_b["id"]  # one key, two tenants: two jobs
    with services.store.session() as s:  # tenant a's key has expired
        s.execute(update(IdempotencyKey).where(IdempotencyKey.tenant == "a").values(
            expires_at=utcnow()))
    again = _post(client, "/v1/jobs", {"capture_id": cap_a, "params": TEST}, "same", a)
    assert again.status_code == 202 and again.json()["id"] != job_a["id"]
    assert "Idempotent-Replayed" not in again.headers
    # A deleted job takes its key with it: the key makes a new job.
    client.post(f"/v1/jobs/{job_b['id']}/cancel", headers=b)
    assert client.delete(f"/v1/jobs/{job_b['id']}", headers=b).status_code == 204
    fresh = _post(client, "/v1/jobs", {"capture_id": cap_b, "params": TEST}, "same", b).json()
    assert fresh["id"] != job_b["id"]
    # The sweeper forgets expired keys (rows only).
    with services.store.session() as s:
        s.execute(update(IdempotencyKey).values(expires_at=utcnow()))
        assert forget_expired(s) == 2
        assert s.scalar(select(func.count()).select_from(IdempotencyKey)) == 0


def test_renders_and_exports_take_a_key(client, services, ready_capture):
    source = finished(services, capture_id=ready_capture())
    for path, body in (("/v1/renders", {"job_id": source, "envmap": "builtin:studio"}),
                       ("/v1/exports", {"job_id": source, "formats": ["spz"]})):
        first = _post(client, path, body, f"{path}-key")
        again = _post(client, path, body, f"{path}-key")
        assert first.status_code == again.status_code == 202, again.text
        assert again.json()["id"] == first.json()["id"]
        assert again.headers["Idempotent-Replayed"] == "true"
    assert _count(services) == 3


@BOTH
def test_the_constraint_makes_one_job_of_two_inserts(services):
    """The loser of a race: its key's insert fails in the transaction of its job, so neither is
    kept (what `Submit.first` then reads is the winner's)."""
    key = Idempotency("t", "race", "0" * 64, utcnow().replace(year=utcnow().year + 1))
    first = services.store.create("t", "reconstruct", {}, capture_id=None, idempotency=key)
    with pytest.raises(NotCreated):
        services.store.create("t", "reconstruct", {}, capture_id=None, idempotency=key)
    assert _count(services) == 1
    with services.store.session(write=False) as s:
        assert s.scalar(select(IdempotencyKey.job_id)) == first.id


@BOTH
def test_concurrent_submits_with_one_key_make_one_job(services, live_api, ready_capture):
    url, _ = live_api
    capture = ready_capture()
    body = {"capture_id": capture, "params": TEST}
    answers = submit_together(url, "/v1/jobs", body, "k")
    assert [r.status_code for r in answers] == [202] * 8, [r.text for r in answers]
    assert len({r.json()["id"] for r in answers}) == 1
    assert sum("Idempotent-Replayed" not in r.headers for r in answers) == 1
    assert _count(services) == 1
