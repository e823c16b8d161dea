"""/v1/renders: a render request becomes a `relight` job on a succeeded reconstruction (202 +
Location, the job representation of /v1/jobs), after checking what it names (404 across
tenants, 409 for a source that is not a succeeded reconstruction, 422 for bad lights, orbits
and fields); the reconstruction and the envmap cannot be deleted while a render needs them.
The render running on a real worker: tests/worker/test_relight_celery.py."""

from __future__ import annotations

import sqlite3

import pytest
from test_api_assets import exr_bytes

from worker.store import Owner


def finished(services, tenant: str = "local", state: str = "succeeded",
             pipeline: str = "reconstruct", capture_id: str | None = None) -> str:
    """A job of `tenant` that ended in `state` (no worker needed)."""
    store = services.store
    job = store.create(tenant, pipeline, {}, capture_id=capture_id)
    if state != "queued":
        owner = Owner.current()
        store.claim(job.id, owner, 5, 3)
        if state != "running":
            store.finish(job.id, owner, state)
    return job.id


@pytest.fixture
def envmap(client, tmp_path) -> str:
    r = client.post("/v1/assets?filename=sky.exr", content=exr_bytes(tmp_path))
    assert r.status_code == 201, r.text
    return r.json()["id"]


def render(client, job_id: str, envmap: str, headers: dict | None = None, **extra):
    return client.post("/v1/renders", json={"job_id": job_id, "envmap": envmap, **extra},
                       headers=headers or {})


def test_a_render_is_a_relight_job(client, services, envmap, ready_capture):
    capture = ready_capture()
    source = finished(services, capture_id=capture)
    r = render(client, source, envmap, orbit=4, rotation_deg=90, cameras="all", lights=[
        {"kind": "directional", "direction": [0, -1, 0], "intensity": 3},
        {"kind": "point", "position": [0.5, 0, 1], "intensity": 2, "color": [1, 0.5, 0.2]}])
    assert r.status_code == 202, r.text
    job = r.json()
    assert r.headers["Location"].endswith(f"/v1/jobs/{job['id']}")
    assert job["pipeline"] == "relight" and job["state"] == "queued"
    assert job["source_job_id"] == source and job["capture_id"] == capture
    p = job["params"]
    assert p["envmap"] == envmap and p["orbit"] == 4 and p["rotation_deg"] == 90
    assert p["fps"] == 24 and p["ao"] is True and p["frames"] is None  # defaults resolved
    assert p["lights"] == [
        {"kind": "directional", "direction": [0, -1, 0], "color": [1, 1, 1], "intensity": 3},
        {"kind": "point", "position": [0.5, 0, 1], "color": [1, 0.5, 0.2], "intensity": 2}]
    assert client.get(job["links"]["self"]).json()["pipeline"] == "relight"
    assert [j["id"] for j in client.get("/v1/jobs").json()["items"]][0] == job["id"]
    broker = services.settings.data_dir / "broker.sqlite3"
    with sqlite3.connect(broker) as db:
        payloads = [row[0] for row in db.execute("SELECT payload FROM kombu_message")]
    assert any(job["id"] in p for p in payloads)  # handed to the broker for a worker


def test_the_relight_pipeline_is_published(client):
    assert "relight" in client.get("/v1/info").json()["pipelines"]
    pipelines = {p["name"]: p for p in client.get("/v1/pipelines").json()}
    relight = pipelines["relight"]
    assert {"relit", "video", "relight"} <= set(relight["artifact_kinds"])
    props = relight["params_schema"]["properties"]
    assert {"envmap", "rotation_deg", "exposure", "lights", "cameras", "frames", "orbit", "fps",
            "ao", "capture_light"} <= set(props)
    assert "required" not in relight["params_schema"]  # a map or lights: checked together
    light = client.get("/openapi.json").json()["components"]["schemas"]["LightIn"]
    assert {"kind", "direction", "position", "intensity", "color"} <= set(light["properties"])


def test_relight_jobs_are_not_made_on_captures(client, ready_capture):
    r = client.post("/v1/jobs", json={"capture_id": ready_capture(), "pipeline": "relight",
                                      "params": {"envmap": "ast_x"}})
    assert r.status_code == 422 and "POST /v1/renders" in r.json()["error"]["message"], r.text


LIGHT = {"kind": "directional", "direction": [0, 1, 0], "intensity": 1}


@pytest.mark.parametrize("extra, words", [
    ({"lights": [{**LIGHT, "intensity": 0}]}, "intensity > 0"),
    ({"lights": [{**LIGHT, "intensity": -2}]}, "intensity > 0"),
    ({"lights": [{**LIGHT, "color": [0, 0, 0]}]}, "color must not be all zero"),
    ({"lights": [{**LIGHT, "direction": [0, 0, 0]}]}, "must not be zero"),
    ({"lights": [{"kind": "point", "direction": [0, 1, 0], "intensity": 1}]},
     "point light needs 'position'"),
    ({"lights": [{**LIGHT, "position": [0, 1, 0]}]}, "not 'position'"),
    ({"lights": [{**LIGHT, "kind": "spot"}]}, "lights.0.kind"),
    ({"orbit": 0}, "orbit"),
    ({"orbit": 721}, "orbit"),
    ({"fps": 0}, "fps"),
    ({"capture_light": 0}, "capture_light"),
    ({"frames": "a:b"}, "frames"),
    ({"envmap": None}, "give an environment map or at least one light"),
    ({"envmap": "builtin:moon"}, "no built-in map builtin:moon"),
    ({"unknown": 1}, "body.unknown"),
])
def test_render_requests_that_are_refused(client, services, envmap, extra, words):
    source = finished(services)
    r = client.post("/v1/renders", json={"job_id": source, "envmap": envmap, **extra})
    assert r.status_code == 422 and words in r.json()["error"]["message"], r.text
    assert [j["id"] for j in client.get("/v1/jobs").json()["items"]] == [source]


@pytest.mark.parametrize("envmap", ["builtin:sunset", None])
def test_a_built_in_map_or_lights_alone_need_no_asset(client, services, envmap):
    body = {"job_id": finished(services), "lights": [LIGHT]}
    if envmap is not None:
        body["envmap"] = envmap
    r = client.post("/v1/renders", json=body)
    assert r.status_code == 202, r.text
    assert r.json()["params"]["envmap"] == envmap


@pytest.mark.parametrize("state", ["queued", "running", "failed", "cancelled"])
def test_the_source_must_be_a_succeeded_reconstruction(client, services, envmap, state):
    source = finished(services, state=state)
    r = render(client, source, envmap)
    error = r.json()["error"]
    assert r.status_code == 409 and f"is {state}" in error["message"], r.text
    assert error["retryable"] is (state in ("queued", "running"))
    relit = finished(services, pipeline="relight")
    r = render(client, relit, envmap)
    assert r.status_code == 409 and "relight job" in r.json()["error"]["message"], r.text


def test_renders_see_only_the_callers_jobs_and_assets(client, services, tenants, tmp_path):
    a, b = tenants["a"], tenants["b"]
    job_a, job_b = finished(services, "a"), finished(services, "b")
    env_a = client.post("/v1/assets?filename=a.exr", content=exr_bytes(tmp_path),
                        headers=a).json()["id"]
    env_b = client.post("/v1/assets?filename=b.exr", content=exr_bytes(tmp_path),
                        headers=b).json()["id"]
    for job, env, words in ((job_a, env_b, "job"), (job_b, env_a, "asset"),
                            (job_a, env_a, "job")):
        r = render(client, job, env, headers=b)
        assert r.status_code == 404 and words in r.json()["error"]["message"], r.text
    assert render(client, job_b, env_b, headers=b).status_code == 202
    assert render(client, job_a, env_a, headers=a).status_code == 202


def test_a_source_and_an_envmap_in_use_are_not_deleted(client, services, envmap):
    source = finished(services)
    job = render(client, source, envmap).json()
    for url in (f"/v1/jobs/{source}", f"/v1/assets/{envmap}"):
        r = client.delete(url)
        assert r.status_code == 409 and job["id"] in r.json()["error"]["message"], r.text
    assert client.post(f"/v1/jobs/{job['id']}/cancel").json()["state"] == "cancelled"
    assert client.delete(f"/v1/jobs/{source}").status_code == 204
    after = client.get(f"/v1/jobs/{job['id']}").json()
    assert after["source_job_id"] is None  # the render stays, its source is gone
    r = client.post(f"/v1/jobs/{job['id']}/retry")
    assert r.status_code == 409 and "source reconstruction was deleted" in r.text, r.text
    assert client.delete(f"/v1/assets/{envmap}").status_code == 204
    r = render(client, source, "ast_gone")
    assert r.status_code == 404


def test_an_export_is_an_export_job_and_bad_requests_are_refused(client, services, ready_capture,
                                                                  envmap):
    """/v1/exports: the same shape as a render (an `export` job on a succeeded reconstruction);
    refused with the reason for a source that is not one, unknown formats and tolerances."""
    capture = ready_capture()
    source = finished(services, capture_id=capture)
    r = client.post("/v1/exports", json={"job_id": source, "formats": ["stream", "spz"],
                                         "fps": 30})
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["pipeline"] == "export" and job["source_job_id"] == source
    assert job["params"] == {"formats": ["stream", "spz"], "frames": None, "fps": 30.0,
                             "position_tolerance": None, "subject": False}
    for body, status, words in (
            ({"job_id": source, "formats": ["gif"]}, 422, "formats"),
            ({"job_id": source, "formats": []}, 422, "formats"),
            ({"job_id": source, "position_tolerance": 0.5}, 422, "position_tolerance"),
            ({"job_id": finished(services, state="failed", capture_id=capture)}, 409,
             "succeeded reconstruction"),
            ({"job_id": job["id"]}, 409, "from a reconstruct job"),
            ({"job_id": "job_nope"}, 404, "job_nope")):
        r = client.post("/v1/exports", json=body)
        assert r.status_code == status, (body, r.text)
        assert words in r.json()["error"]["message"], r.text
    assets = client.get(f"/v1/assets/{envmap}").json()
    assert len(assets["sh9"]) == 9 and assets["sh9"][0][0] > 0  # the page relights with it
    r = client.post("/v1/jobs", json={"capture_id": capture, "pipeline": "export"})
    assert r.status_code == 422 and "POST /v1/exports" in r.text
