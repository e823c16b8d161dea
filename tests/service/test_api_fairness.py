"""One tenant cannot starve the others (issue 42): job state changes past the tenant's rate, jobs
past its active-jobs cap and event streams past its stream cap or its rate of openings answer
429 with Retry-After and a message saying what the limit is; another tenant is unaffected; an
idempotent replay and a request refused for another reason are never counted; a stream's slot
comes back when it ends and when its client goes away. The rate limits' clock is driven by the
tests (no sleeps)."""

from __future__ import annotations

import anyio
import httpx
import pytest
from live_server import wait_for
from service_harness import make_settings

from service.limits import HeldStream, Limits
from worker.store import JobStore

BOTH = pytest.mark.parametrize("database_url", ["sqlite", "postgres"], indirect=True)
TEST = {"preset": "test"}


@pytest.fixture
def settings(tmp_path, database_url):
    """Small limits: 3 changes at once then 6 a minute, 2 active jobs, 2 streams open and 2
    opened at once then 6 a minute; streams never write a keep-alive, so only the disconnect
    itself can free a slot."""
    return make_settings(tmp_path / "data", database_url=database_url, job_changes_burst=3,
                         job_changes_per_minute=6, max_active_jobs=2, max_event_streams=2,
                         event_streams_per_minute=6, sse_keepalive_seconds=3600)


@pytest.fixture
def clock(services) -> list[float]:
    """The rate limit's clock, in seconds; a test moves it by changing clock[0]."""
    now = [1_000_000.0]
    services.limits.clock = lambda: now[0]
    return now


def _queued(services, tenant: str) -> str:
    return services.store.create(tenant, "reconstruct", {}, capture_id=None).id


def _refused(r: httpx.Response, code: str, retry_after: str) -> str:
    assert r.status_code == 429, r.text
    assert r.headers["Retry-After"] == retry_after
    error = r.json()["error"]
    assert error["code"] == code and error["retryable"] is True
    return error["message"]


@BOTH
def test_a_burst_over_the_rate_is_refused_until_the_window_passes(client, services, tenants,
                                                                  clock):
    a, b = tenants["a"], tenants["b"]
    jobs = [_queued(services, "a") for _ in range(5)]
    for job in jobs[:3]:
        assert client.post(f"/v1/jobs/{job}/cancel", headers=a).status_code == 202
    message = _refused(client.post(f"/v1/jobs/{jobs[3]}/cancel", headers=a), "rate_limited",
                       "10")  # one token a 10 s
    assert "3 at once, then 6 a minute" in message and "try again in 10 s" in message
    assert services.store.get(jobs[3]).state == "queued"  # refused: nothing was done
    # Refused for another reason, or another tenant's: not counted, not limited.
    assert client.post(f"/v1/jobs/{jobs[0]}/cancel", headers=a).status_code == 409
    assert client.delete("/v1/jobs/job_nope", headers=a).status_code == 404
    other = _queued(services, "b")
    assert client.post(f"/v1/jobs/{other}/cancel", headers=b).status_code == 202
    clock[0] += 9.0
    assert _refused(client.post(f"/v1/jobs/{jobs[3]}/cancel", headers=a), "rate_limited", "1")
    clock[0] += 1.0
    assert client.post(f"/v1/jobs/{jobs[3]}/cancel", headers=a).status_code == 202
    _refused(client.delete(f"/v1/jobs/{jobs[0]}", headers=a), "rate_limited", "10")
    clock[0] += 10.0
    assert client.delete(f"/v1/jobs/{jobs[0]}", headers=a).status_code == 204


def test_submits_share_the_bucket_and_a_replay_is_never_refused(client, services, tenants,
                                                                ready_capture, clock):
    a = tenants["a"]
    capture = ready_capture(a)
    body = {"capture_id": capture, "params": TEST}
    first = client.post("/v1/jobs", json=body, headers={**a, "Idempotency-Key": "k-1"})
    assert first.status_code == 202
    bad = client.post("/v1/jobs", json={**body, "params": {"preset": "nope"}}, headers=a)
    assert bad.status_code == 422  # refused at the door: no token taken
    job = first.json()["id"]
    assert client.post(f"/v1/jobs/{job}/cancel", headers=a).status_code == 202
    assert client.post(f"/v1/jobs/{job}/retry", headers=a).status_code == 202
    _refused(client.post("/v1/jobs", json=body, headers=a), "rate_limited", "10")
    _refused(client.post(f"/v1/jobs/{job}/cancel", headers=a), "rate_limited", "10")
    again = client.post("/v1/jobs", json=body, headers={**a, "Idempotency-Key": "k-1"})
    assert again.status_code == 202 and again.headers["Idempotent-Replayed"] == "true"
    assert again.json()["id"] == job


@BOTH
def test_a_submit_past_the_active_jobs_cap_says_the_cap(client, services, tenants,
                                                        ready_capture, clock, monkeypatch):
    a, b = tenants["a"], tenants["b"]
    body = {"capture_id": ready_capture(a), "params": TEST}
    made = []
    for key in ("k-1", "k-2"):
        clock[0] += 60.0  # the rate is not what this test is about
        r = client.post("/v1/jobs", json=body, headers={**a, "Idempotency-Key": key})
        assert r.status_code == 202, r.text
        made.append(r.json()["id"])
    clock[0] += 60.0
    message = _refused(client.post("/v1/jobs", json=body, headers=a), "too_many_jobs", "30")
    assert "2 of yours are queued or running and the cap is 2" in message
    assert len(client.get("/v1/jobs", headers=a).json()["items"]) == 2
    replay = client.post("/v1/jobs", json=body, headers={**a, "Idempotency-Key": "k-1"})
    assert replay.status_code == 202 and replay.json()["id"] == made[0]
    r = client.post("/v1/jobs", json={"capture_id": ready_capture(b), "params": TEST},
                    headers=b)
    assert r.status_code == 202  # another tenant's cap is its own
    clock[0] += 60.0
    assert client.post(f"/v1/jobs/{made[0]}/cancel", headers=a).status_code == 202
    clock[0] += 60.0
    third = client.post("/v1/jobs", json=body, headers=a)
    assert third.status_code == 202
    clock[0] += 60.0  # a retry would queue the cancelled job again: a third active one
    message = _refused(client.post(f"/v1/jobs/{made[0]}/retry", headers=a), "too_many_jobs",
                       "30")
    assert "2 of yours" in message and services.store.get(made[0]).state == "cancelled"
    # Past the early check (a submit racing others), the job store refuses it when adding it.
    monkeypatch.setattr(services.limits, "admit", lambda tenant: None)
    clock[0] += 60.0
    message = _refused(client.post("/v1/jobs", json=body, headers=a), "too_many_jobs", "30")
    assert "2 of yours are queued or running and the cap is 2" in message
    with services.store.session(write=False) as s:
        assert JobStore.active_jobs(s, "a") == 2


def _first_event(lines) -> str:
    """The first `event:` line of a stream's lines (an iterator, left after it)."""
    for line in lines:
        if line.startswith("event:"):
            return line
    raise AssertionError("the stream ended before its first event")


def _open(http: httpx.Client, path: str, headers: dict):
    """A stream left open: its response and its lines."""
    response = http.send(http.build_request("GET", path, headers=headers), stream=True)
    return response, response.iter_lines()


def test_streams_past_the_cap_are_refused_and_slots_come_back(live_api, tenants, clock):
    url, services = live_api
    a, b = tenants["a"], tenants["b"]
    job, other = _queued(services, "a"), _queued(services, "b")
    with httpx.Client(base_url=url, timeout=60) as http:
        (first, lines1), (second, lines2) = (_open(http, f"/v1/jobs/{job}/events", a)
                                             for _ in range(2))
        assert [_first_event(x) for x in (lines1, lines2)] == ["event: state"] * 2
        message = _refused(http.get(f"/v1/jobs/{job}/events", headers=a), "too_many_streams",
                           "10")
        assert "2 of yours are open and the cap is 2" in message
        with http.stream("GET", f"/v1/jobs/{other}/events", headers=b) as theirs:  # its own cap
            assert _first_event(theirs.iter_lines()) == "event: state"
        # The client goes away: its slot comes back although the stream never writes again.
        first.close()
        wait_for(lambda: services.limits.streams.get("a") == 1, 60, "the closed stream's slot")
        clock[0] += 60.0  # the rate of openings is not what this test is about
        with http.stream("GET", f"/v1/jobs/{job}/events", headers=a) as third:
            lines3 = third.iter_lines()
            assert _first_event(lines3) == "event: state"
            # A stream that ends (its job was cancelled) frees its slot too.
            assert http.post(f"/v1/jobs/{job}/cancel", headers=a).status_code == 202
            assert '"state":"cancelled"' in "".join(lines3)
        assert '"state":"cancelled"' in "".join(lines2)
        second.close()
        wait_for(lambda: "a" not in services.limits.streams, 60, "every slot of tenant a")


@BOTH
def test_streams_opened_and_dropped_past_the_rate_are_refused(client, services, tenants, clock):
    """A stream of an ended job ends at once and frees its slot: the cap on open streams
    never stops a client that opens them in a loop; the rate of openings does."""
    a, b = tenants["a"], tenants["b"]
    job, other = _queued(services, "a"), _queued(services, "b")
    assert client.post(f"/v1/jobs/{job}/cancel", headers=a).status_code == 202
    for _ in range(2):  # the burst: as many as may be open at once
        r = client.get(f"/v1/jobs/{job}/events", headers=a)
        assert r.status_code == 200 and '"state":"cancelled"' in r.text
    assert "a" not in services.limits.streams  # both ended: no slot is held
    message = _refused(client.get(f"/v1/jobs/{job}/events", headers=a), "too_many_streams",
                       "10")  # one opening a 10 s
    assert "2 at once, then 6 a minute" in message and "try again in 10 s" in message
    assert "a" not in services.limits.streams  # refused: nothing held
    assert client.get(f"/v1/jobs/{job}", headers=a).status_code == 200  # polling still works
    with client.stream("GET", f"/v1/jobs/{other}/events", headers=b) as theirs:  # its own
        assert _first_event(theirs.iter_lines()) == "event: state"
    clock[0] += 9.0
    _refused(client.get(f"/v1/jobs/{job}/events", headers=a), "too_many_streams", "1")
    clock[0] += 1.0
    assert client.get(f"/v1/jobs/{job}/events", headers=a).status_code == 200
    _refused(client.get(f"/v1/jobs/{job}/events", headers=a), "too_many_streams", "10")


def test_a_slot_comes_back_when_the_client_goes_away_under_asgi_2_4(tmp_path):
    """Under an ASGI 2.4 server Starlette stops listening for the disconnect (it waits for a
    write to fail); HeldStream still listens, so an idle stream ends at once."""
    limits = Limits(make_settings(tmp_path / "data"), JobStore("sqlite://"))
    written, sent = anyio.Event(), []

    async def idle_stream():
        yield "event: state\ndata: {}\n\n"
        await anyio.sleep_forever()  # a job that never changes, no keep-alive due

    async def send(message) -> None:
        sent.append(message["type"])
        if message.get("body"):
            written.set()

    async def receive() -> dict:
        await written.wait()
        return {"type": "http.disconnect"}

    async def serve() -> None:
        response = HeldStream(idle_stream(), limits.open_stream("a"),
                              media_type="text/event-stream")
        assert limits.streams == {"a": 1}
        with anyio.fail_after(60):
            await response({"type": "http", "asgi": {"spec_version": "2.4"}}, receive, send)

    anyio.run(serve)
    assert sent[:2] == ["http.response.start", "http.response.body"] and limits.streams == {}
