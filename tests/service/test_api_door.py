"""Bad requests are refused at the door: replayed against a real `dgs serve`, every job and
render request that used to be queued and fail later (unknown settings, out-of-range numbers,
NaN, a frame slice or camera the capture does not have, a device the deployment does not
offer, a host path as a model) answers 422 naming the parameter, and no job is made."""

from __future__ import annotations

import json

import httpx
import pytest
from live_server import LiveServer, create_key

from service.client import Client

TINY = {"train": {"schedule": {"iterations": 20, "stage2_start": 6, "stage3_start": 14,
                               "densify_from": 2, "densify_until": 12, "densify_interval": 4,
                               "reset_interval": 8, "sh_interval": 4}, "init_points": 300},
        "mesh": {"enabled": False}}


@pytest.fixture(scope="module")
def door(tmp_path_factory):
    """A live server with a committed one-frame capture and one succeeded reconstruction."""
    from core.synth import SynthConfig, synthesize

    root = tmp_path_factory.mktemp("door")
    folder = root / "capture"
    synthesize(folder, SynthConfig(frames=1, views=8, width=24, height=24, seed=3,
                                   ao_directions=4))
    live = LiveServer(root / "data", root / "serve.log").start()
    live.wait_worker()
    key = create_key(root / "data", "door")
    with Client(live.url, key) as client:
        cap = client.create_capture(folder)
        client.upload_capture(cap["id"], folder)
        assert client.commit(cap["id"], timeout=120)["state"] == "ready"
        job = client.submit(cap["id"], {"preset": "test", "config": TINY})
        done = client.wait(job["id"], timeout=600)
        assert done["state"] == "succeeded", "\n".join(client.logs(job["id"]))
    yield live, key, cap["id"], job["id"]
    live.stop()


def _post(door, path: str, body: dict | str) -> httpx.Response:
    live, key = door[0], door[1]
    headers = {"Authorization": f"Bearer {key}", "Content-Type": "application/json"}
    content = body if isinstance(body, str) else json.dumps(body)
    return httpx.post(f"{live.url}{path}", content=content, headers=headers, timeout=30)


def _jobs(door) -> int:
    live, key = door[0], door[1]
    r = httpx.get(f"{live.url}/v1/jobs", headers={"Authorization": f"Bearer {key}"},
                  params={"limit": 200}, timeout=30)
    return len(r.json()["items"])


def _schedule(**values) -> dict:
    return {"config": {"train": {"schedule": values}}}


@pytest.mark.parametrize("params, path, words", [
    ({"config": {"train": {"nope": 1}}}, "params.config.train.nope", "unknown setting"),
    (_schedule(iterations=0), "params.config.train.schedule.iterations", ">= 3"),
    (_schedule(iterations=-5), "params.config.train.schedule.iterations", ">= 3"),
    (_schedule(iterations=10**12), "params.config.train.schedule.iterations", "<= 300000"),
    ({"frames": "5:9"}, "params.frames", "selects no frame of the 1 in the capture"),
    ({"config": {"train": {"device": "cuda:7"}}}, "params.config.train.device",
     "not offered by this deployment (offered: auto, cpu)"),
    ({"config": {"mesh": {"device": "cuda"}}}, "params.config.mesh.device", "not offered"),
    ({"config": {"normal_estimator": "/etc/passwd"}}, "params.config.normal_estimator",
     "neither a normal_model asset of yours nor a model this server offers"),
    ({"config": {"normal_estimator": "/root/.ssh/id_rsa"}}, "params.config.normal_estimator",
     "neither a normal_model asset of yours nor a model this server offers"),
    ({"gop": 0}, "params.gop", ">= 1"),
])
def test_a_bad_job_is_refused_naming_the_parameter(door, params, path, words):
    before = _jobs(door)
    r = _post(door, "/v1/jobs", {"capture_id": door[2], "params": params})
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    message = error["message"].replace("greater than or equal to ", ">= ") \
        .replace("less than or equal to ", "<= ")
    assert error["details"][0]["path"] == path and words in message, error
    assert _jobs(door) == before  # no job row


@pytest.mark.parametrize("literal, path", [
    ('{"train": {"schedule": {"iterations": NaN}}}', "params.config.train.schedule.iterations"),
    ('{"train": {"init_points": 1e400}}', "params.config.train.init_points"),
    ('{"train": {"eps2d": -Infinity}}', "params.config.train.eps2d"),
])
def test_nan_and_infinity_are_refused_not_stored_as_null(door, literal, path):
    before = _jobs(door)
    r = _post(door, "/v1/jobs", f'{{"capture_id": "{door[2]}", "params": {{"config": '
                                f'{literal}}}}}')
    assert r.status_code == 422, r.text
    assert r.json()["error"]["details"][0]["path"] == path
    assert _jobs(door) == before


def test_a_host_path_tells_nothing_about_the_host(door):
    """Whether the file exists or not, the answer is the same: the path is never opened."""
    bodies = [_post(door, "/v1/jobs", {"capture_id": door[2], "params": {
        "config": {"normal_estimator": name}}}).json()["error"]["message"].replace(name, "X")
        for name in ("/etc/passwd", "/no/such/file.pt")]
    assert bodies[0] == bodies[1]


@pytest.mark.parametrize("params, path, words", [
    ({"cameras": "cam99"}, "cameras", "no camera 'cam99' in the capture"),
    ({"cameras": "../x"}, "cameras", "no camera '../x' in the capture"),
    ({"cameras": "cam00,cam99"}, "cameras", "no camera 'cam99'"),
    ({"frames": "5:9"}, "frames", "selects no frame of the 1 in the reconstruction"),
])
def test_a_bad_render_is_refused_naming_the_parameter(door, params, path, words):
    before = _jobs(door)
    r = _post(door, "/v1/renders", {"job_id": door[3], "envmap": "builtin:studio", **params})
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["details"][0]["path"] == path and words in error["message"], error
    assert _jobs(door) == before


def test_good_requests_still_get_through(door):
    r = _post(door, "/v1/renders", {"job_id": door[3], "envmap": "builtin:studio",
                                    "cameras": "cam00,cam03", "frames": "0"})
    assert r.status_code == 202, r.text
    r = _post(door, "/v1/jobs", {"capture_id": door[2], "params": {
        "preset": "test", "frames": "0:1", "config": {**TINY, "train": {
            **TINY["train"], "device": "cpu"}}}})
    assert r.status_code == 202, r.text
    live, key = door[0], door[1]
    with Client(live.url, key) as client:
        client.cancel(r.json()["id"])
