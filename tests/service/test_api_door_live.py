"""Issue 20's bad requests (malformed uploads, server folders in messages, tus edge cases),
issue 32's nine findings and issue 42's hostile capture files replayed against a real `dgs
serve` (API and embedded worker, fresh data folder): each bad request gets a 4xx that says what
is wrong, naming files (and, in a capture's metadata, fields) as the client knows them; nothing
answers 500 and no answer, job error or artifact shows the server's data folder; a large body
never holds the API; Location never comes from Host; submits with one Idempotency-Key make one
job; a finished part names its worker; a run the capture cannot follow (issue 42: a split with no
camera left to train, a subject mesh without masks) is refused."""

from __future__ import annotations

import base64
import io
import sys
import threading
import time
import zipfile
from pathlib import Path

import httpx
import pytest
from service_harness import (
    TUS,
    ZIP,
    capture_files,
    capture_variant,
    make_zip,
    manifest_of,
    metadata,
    submit_together,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bad_inputs import HUGE, bad_variants, good_image, png_header  # noqa: E402
from hostile_sources import ATTACKS, attacked  # noqa: E402
from live_server import LiveServer, wait_for  # noqa: E402

from core.rundir import ARTIFACT_KINDS  # noqa: E402
from service.client import Client  # noqa: E402

pytestmark = pytest.mark.timeout(1200)


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    data = tmp_path_factory.mktemp("door-live") / "data"
    server = LiveServer(data, data.parent / "serve.log").start()
    with httpx.Client(base_url=server.url, timeout=60) as http:
        yield server, http
    server.stop()



def _refused(r: httpx.Response, server: LiveServer, status: int = 422) -> dict:
    assert r.status_code == status, r.text
    assert str(server.data_dir) not in r.text
    return r.json()["error"]


def test_malformed_uploads_answer_422_naming_the_client_file(live, synth_capture, tmp_path):
    server, http = live
    exr = good_image("exr", tmp_path, 64, 32)
    error = _refused(http.post("/v1/assets", params={"filename": "studio.exr"},
                               content=exr[:len(exr) // 2]), server)  # a truncated EXR
    assert error["code"] == "invalid_asset" and error["message"].startswith("studio.exr: ")
    hdr, words = bad_variants("hdr", good_image("hdr", tmp_path, 64, 32))["wrong magic"]
    assert words in _refused(http.post("/v1/assets", params={"filename": "sky.hdr"},
                                       content=hdr), server)["message"]
    files = capture_files(synth_capture)
    files["images/000000/cam01.png"] = png_header(*HUGE)  # 20000 x 20000 inside a zip
    error = _refused(http.post("/v1/captures/archive", content=make_zip(files), headers=ZIP),
                     server)
    assert error["details"][0]["path"] == "images/000000/cam01.png"
    assert "is 20000x20000 (400000000 pixels); the limit is" in error["message"]
    error = _refused(http.post("/v1/captures", content=b"\x89PNG\r\n\x1a\n",
                               headers={"Content-Type": "application/json"}), server)
    assert "not UTF-8" in error["message"]


def _tus_upload(http: httpx.Client, capture_id: str, path: str, data: bytes) -> str:
    r = http.post("/v1/uploads", headers={**TUS, "Upload-Length": str(len(data)),
                                          "Upload-Metadata": metadata(capture=capture_id,
                                                                      path=path)})
    assert r.status_code == 201, r.text
    url = r.headers["Location"]
    if data:
        r = http.patch(url, content=data, headers={
            **TUS, "Upload-Offset": "0", "Content-Type": "application/offset+octet-stream"})
        assert r.status_code == 204, r.text
    return url


def test_a_capture_by_tus_names_its_bad_file_and_tus_edges_are_refused(live, synth_capture):
    server, http = live
    files = capture_files(synth_capture)
    files["images/000000/cam03.png"] = b"not an image at all"
    capture = http.post("/v1/captures", json={"format": "canonical",
                                              "manifest": manifest_of(files)}).json()
    urls = {p: _tus_upload(http, capture["id"], p, d) for p, d in files.items()}
    error = _refused(http.post(f"/v1/captures/{capture['id']}/commit"), server)
    assert error["code"] == "invalid_capture"
    assert "images/000000/cam03.png: is not a PNG file (wrong magic bytes)" in error["message"]
    # Bytes after the last one of a complete upload: refused, not silently dropped.
    done = urls["capture.json"]
    r = http.patch(done, content=b"more", headers={
        **TUS, "Upload-Offset": str(len(files["capture.json"])),
        "Content-Type": "application/offset+octet-stream"})
    assert _refused(r, server, 413)["code"] == "payload_too_large"
    # A wrong checksum after 100 bytes names the bytes that were sent.
    big = {"images/000000/extra.png": bytes(300)}
    other = http.post("/v1/captures", json={"format": "auto",
                                            "manifest": manifest_of(big)}).json()
    r = http.post("/v1/uploads", headers={**TUS, "Upload-Length": "300", "Upload-Metadata":
                                          metadata(capture=other["id"],
                                                   path="images/000000/extra.png")})
    url = r.headers["Location"]
    patch = {**TUS, "Content-Type": "application/offset+octet-stream"}
    assert http.patch(url, content=bytes(100), headers={**patch, "Upload-Offset": "0"}) \
        .status_code == 204
    r = http.patch(url, content=bytes(50), headers={
        **patch, "Upload-Offset": "100",
        "Upload-Checksum": "sha1 " + base64.b64encode(bytes(20)).decode()})
    assert "the sha1 of the 50 bytes sent does not match" in _refused(r, server, 460)["message"]


@pytest.mark.parametrize("attack", ATTACKS, ids=lambda a: a.name)
def test_hostile_capture_files_answer_422_naming_file_and_field(live, synth_capture, attack):
    """Issue 42: each of the review's files, as a zip and through tus, answers 422 naming the
    metadata file and the field (it answered 500 retryable); committing the same files again
    answers the same 422, and the capture stays uploading with the error to read."""
    server, http = live
    files = attacked(synth_capture, attack)
    expected = f"{attack.file}: {attack.message}"
    error = _refused(http.post("/v1/captures/archive", params={"format": attack.fmt},
                               content=make_zip(files), headers=ZIP), server)
    assert error["code"] == "invalid_capture" and expected in error["message"], error
    assert not error["retryable"]
    capture = http.post("/v1/captures", json={"format": attack.fmt,
                                              "manifest": manifest_of(files)}).json()
    for path, data in files.items():
        _tus_upload(http, capture["id"], path, data)
    first = _refused(http.post(f"/v1/captures/{capture['id']}/commit"), server)
    assert first["code"] == "invalid_capture" and expected in first["message"], first
    assert any(d["path"] == attack.file for d in first["details"])
    assert _refused(http.post(f"/v1/captures/{capture['id']}/commit"), server) == first
    state = http.get(f"/v1/captures/{capture['id']}").json()
    assert state["state"] == "uploading" and state["error"] == first


def test_a_failed_job_names_the_capture_file_not_the_server_folder(live, synth_capture):
    server, http = live
    server.wait_worker()
    files = capture_files(synth_capture)
    r = http.post("/v1/captures/archive", content=make_zip(files), headers=ZIP)
    assert r.status_code == 201, r.text
    capture_id = r.json()["id"]
    stored = server.data_dir / "store" / "captures" / capture_id / "images/000000/cam02.png"
    stored.write_bytes(stored.read_bytes()[:64])  # damaged in the store after its commit
    job = http.post("/v1/jobs", json={"capture_id": capture_id,
                                      "params": {"preset": "test"}}).json()
    deadline = time.monotonic() + 300
    while (state := http.get(f"/v1/jobs/{job['id']}").json())["state"] in ("queued", "running"):
        assert time.monotonic() < deadline, state
        time.sleep(0.5)
    assert state["state"] == "failed" and state["error"]["code"] == "invalid_input", state
    assert "images/000000/cam02.png" in state["error"]["message"]
    logs = http.get(f"/v1/jobs/{job['id']}/logs").text
    for text in (str(state), logs):
        assert str(server.data_dir) not in text


@pytest.mark.parametrize("cameras, masks, config, field, words", [
    (1, True, {"split": "auto"}, "params.config.split", "every8 leaves no camera to train on"),
    (1, True, {"split": "every8"}, "params.config.split", "every8 leaves no camera to train on"),
    (None, False, {"mesh": {"subject": True}}, "params.config.mesh.subject",
     "the capture has no masks"),
])
def test_a_run_the_capture_cannot_follow_is_refused_at_the_door(live, synth_capture, cameras,
                                                               masks, config, field, words):
    """Issue 42, items 3 and 4: a split that leaves a one-camera capture nothing to train on
    (the worker failed it after a 202), a subject mesh of a capture without masks (it
    'succeeded' with no mesh): 422 naming the setting, by the rules the worker runs, and no
    job."""
    server, http = live
    files = capture_variant(synth_capture, cameras=cameras, masks=masks)
    r = http.post("/v1/captures/archive", content=make_zip(files), headers=ZIP)
    assert r.status_code == 201, r.text
    before = _jobs(http)
    r = http.post("/v1/jobs", json={"capture_id": r.json()["id"], "params": {
        "preset": "test", "config": config}})
    error = _refused(r, server)
    assert error["details"][0]["path"] == field and words in error["message"], error
    assert _jobs(http) == before


# -- issue 32: the door, second pass ------------------------------------------------------------
# 40 steps densified every 4 (not an epoch apart: densify_epoch off), so that the tiny job grows
# enough to mesh.
TINY = {"train": {"schedule": {"iterations": 40, "stage2_start": 12, "stage3_start": 28,
                               "densify_from": 2, "densify_until": 24, "densify_interval": 4,
                               "densify_epoch": False, "reset_interval": 16, "sh_interval": 4},
                  "init_points": 300},
        "sequence": {"enabled": False}}
JSON = {"Content-Type": "application/json"}


def _ended(http: httpx.Client, job_id: str) -> dict:
    def ended() -> dict | None:
        job = http.get(f"/v1/jobs/{job_id}").json()
        return job if job["state"] not in ("queued", "running") else None

    return wait_for(ended, 600, f"job {job_id} to end")


@pytest.fixture(scope="module")
def made(live, tmp_path_factory):
    """A two-frame capture reconstructed as two parts (sequence off: a part per frame, meshes
    on), then rendered on an orbit and exported in every format: every kind of artifact."""
    from core.synth import SynthConfig, synthesize

    server, http = live
    server.wait_worker()
    folder = tmp_path_factory.mktemp("door-two") / "capture"
    synthesize(folder, SynthConfig(frames=2, views=8, width=32, height=32, seed=5,
                                   ao_directions=8))
    r = http.post("/v1/captures/archive", content=make_zip(capture_files(folder)), headers=ZIP)
    assert r.status_code == 201, r.text
    capture = r.json()["id"]
    job = http.post("/v1/jobs", json={"capture_id": capture, "params": {
        "preset": "test", "config": TINY}}).json()
    assert len(job["parts"]) == 2
    done = _ended(http, job["id"])
    assert done["state"] == "succeeded", (done, server.log())
    render = http.post("/v1/renders", json={"job_id": job["id"], "envmap": "builtin:studio",
                                            "orbit": 3, "fps": 8}).json()
    export = http.post("/v1/exports", json={"job_id": job["id"],
                                            "formats": ["stream", "spz", "ply"]}).json()
    for each in (render, export):
        assert _ended(http, each["id"])["state"] == "succeeded", server.log()
    return {"capture": capture, "job": done, "render": render["id"], "export": export["id"]}


def test_every_artifact_names_the_capture_by_id_never_a_server_path(live, made):
    """Finding 2: config.json, eval.json, relight.json, export.json, every other artifact and
    each job's artifacts.zip are scanned for the data folder (which holds the scratch and the
    store)."""
    server, http = live
    folders = {str(server.data_dir), str(server.data_dir.resolve())}
    kinds: set[str] = set()
    for job_id in (made["job"]["id"], made["render"], made["export"]):
        items = Client(server.url).artifacts(job_id)
        for item in items:
            data = http.get(item["url"]).content
            assert len(data) == item["size"]
            assert not [f for f in folders if f.encode() in data], item["path"]
            kinds.add(item["kind"])
        archive = http.get(f"/v1/jobs/{job_id}/artifacts.zip").content
        assert not [f for f in folders if f.encode() in archive]
        with zipfile.ZipFile(io.BytesIO(archive)) as zf:
            assert len(zf.namelist()) == len(items)
            for name in zf.namelist():
                assert not [f for f in folders if f.encode() in zf.read(name)], name
    assert set(ARTIFACT_KINDS) <= kinds, set(ARTIFACT_KINDS) - kinds  # every kind there is
    job = made["job"]["id"]
    for name in ("config.json", "eval.json"):
        record = http.get(f"/v1/jobs/{job}/artifacts/{name}").json()
        assert record["capture"] == made["capture"], name


def test_finished_parts_keep_their_worker(live, made):
    """Finding 9: a part that has ended still names the worker that ran it, and its runs."""
    _, http = live
    parts = http.get(f"/v1/jobs/{made['job']['id']}").json()["parts"]
    assert [p["state"] for p in parts] == ["succeeded"] * 2
    for part in parts:
        assert part["worker"] and part["worker"].count("/") == 1, part
        assert [(r["worker"], r["outcome"]) for r in part["runs"]][-1] == (part["worker"],
                                                                           "succeeded")
    events = http.get(f"/v1/jobs/{made['job']['id']}/events",  # every event: it has ended
                      headers={"Last-Event-ID": "0"}).text
    assert all(f'"worker":"{p["worker"]}"' in events for p in parts)


def _jobs(http: httpx.Client) -> int:
    return len(http.get("/v1/jobs", params={"limit": 200}).json()["items"])


@pytest.mark.parametrize("path, body, field", [
    ("/v1/jobs", {"params": {"checkpoint_every": True}}, "params.checkpoint_every"),
    ("/v1/jobs", {"params": {"gop": "5"}}, "params.gop"),
    ("/v1/jobs", {"params": {"frames": "-99999999999999999999:"}}, "params.frames"),
    ("/v1/jobs", {"name": "a\x00b\x1b[2J\r\nc"}, "body.name"),
    ("/v1/renders", {"envmap": "builtin:studio", "rotation_deg": "90"}, "body.rotation_deg"),
    ("/v1/renders", {"envmap": "builtin:studio", "orbit": True}, "body.orbit"),
    ("/v1/renders", {"envmap": "builtin:studio", "orbit": "8"}, "body.orbit"),
    ("/v1/renders", {"envmap": "builtin:studio", "ao": "yes"}, "body.ao"),
    ("/v1/renders", {"lights": [{"kind": "point", "position": [0, 0, 1], "intensity": "2"}]},
     "body.lights.0.intensity"),
    ("/v1/renders", {"envmap": "builtin:studio", "frames": "-99999999999999999999:"},
     "body.frames"),
    ("/v1/renders", {"envmap": "builtin:studio", "name": "x\x00"}, "body.name"),
    ("/v1/exports", {"fps": "24"}, "body.fps"),
    ("/v1/exports", {"fps": True}, "body.fps"),
    ("/v1/exports", {"frames": "5:9"}, "frames"),
    ("/v1/exports", {"frames": "::0"}, "body.frames"),
    ("/v1/exports", {"frames": "-99999999999999999999:"}, "body.frames"),
    ("/v1/exports", {"name": "\r\n"}, "body.name"),
])
def test_loose_values_frames_and_names_are_refused_at_the_door(live, made, path, body, field):
    """Findings 3 to 5: coerced types, export frames checked only in the worker, unbounded
    slices and control characters in names: 422 naming the field, and no job."""
    server, http = live
    before = _jobs(http)
    target = ({"capture_id": made["capture"]} if path == "/v1/jobs"
              else {"job_id": made["job"]["id"]})
    r = http.post(path, json={**target, **body})
    assert _refused(r, server)["details"][0]["path"] == field
    assert _jobs(http) == before


@pytest.mark.parametrize("value", ["bytes=" + "0" * 4400 + "-1", "bytes=-" + "9" * 4400,
                                   "bytes=" + "9" * 4400 + "-"])
def test_range_numbers_of_thousands_of_digits(live, made, value, tmp_path):
    """Finding 1: on an artifact and on an asset's content, the plain and the suffix form."""
    server, http = live
    asset = http.post("/v1/assets", params={"filename": "sky.hdr"},
                      content=good_image("hdr", tmp_path, 16, 8)).json()
    for url in (f"/v1/jobs/{made['job']['id']}/artifacts/config.json",
                f"/v1/assets/{asset['id']}/content"):
        r = http.get(url, headers={"Range": value})
        assert r.status_code in (206, 416), r.text[:200]
        assert str(server.data_dir) not in r.text


def test_a_large_body_is_refused_without_holding_the_api(live, made):
    """Finding 6: a 50 MB body of a 25M-element array is refused by every JSON operation before
    it is parsed (413 past the limit, or a manifest's shape checked at memchr speed), and
    /healthz answers while such a body is still arriving (no clock: the body waits for it)."""
    server, http = live
    array = b"[" + b"0," * (25_000_000 - 1) + b"0]"
    for path in ("/v1/jobs", "/v1/renders", "/v1/exports"):
        error = _refused(http.post(path, content=array, headers=JSON), server, 413)
        assert "passes the limit of 1048576 bytes" in error["message"]
    assert "expected a JSON object" in _refused(
        http.post("/v1/captures", content=array, headers=JSON), server)["message"]
    files = b'{"format": "auto", "manifest": {"files": ' + array + b"}}"
    assert "JSON values" in _refused(http.post("/v1/captures", content=files, headers=JSON),
                                     server, 413)["message"]
    halfway, probed = threading.Event(), threading.Event()

    def slow_body():
        yield files[:len(files) // 2]
        halfway.set()
        probed.wait(120)
        yield files[len(files) // 2:]

    answers = []
    sender = threading.Thread(target=lambda: answers.append(http.post(
        "/v1/captures", content=slow_body(), headers=JSON)))
    sender.start()
    assert halfway.wait(120)
    with httpx.Client(base_url=server.url, timeout=60) as other:
        assert other.get("/healthz").status_code == 200
    probed.set()
    sender.join(120)
    assert answers and answers[0].status_code == 413


def test_location_never_comes_from_the_host_header(live, made):
    """Finding 7: without DGS_PUBLIC_URL, Location is a relative reference."""
    _, http = live
    evil = {"Host": "evil.example", "X-Forwarded-Host": "evil.example"}
    r = http.post("/v1/exports", json={"job_id": made["job"]["id"], "formats": ["ply"]},
                  headers=evil)
    assert r.status_code == 202 and r.headers["Location"] == f"/v1/jobs/{r.json()['id']}"
    http.post(f"/v1/jobs/{r.json()['id']}/cancel")


def test_concurrent_submits_with_one_key_make_one_job(live, made):
    """Finding 8: eight submits at once with one Idempotency-Key make one job."""
    server, http = live
    before = _jobs(http)
    answers = submit_together(server.url, "/v1/exports",
                              {"job_id": made["job"]["id"], "formats": ["spz"]}, "door-8")
    assert [a.status_code for a in answers] == [202] * 8, [a.text for a in answers]
    assert len({a.json()["id"] for a in answers}) == 1 and _jobs(http) == before + 1
    http.post(f"/v1/jobs/{answers[0].json()['id']}/cancel")


# -- issue 42: one tenant cannot starve the others -----------------------------------------------
def test_a_flood_of_changes_and_streams_is_refused_with_retry_after(live, made):
    """The review's flood replayed on the defaults: retry/cancel pairs on one job answer 429
    rate_limited with a Retry-After once the tenant's burst is spent (reads still answer), and
    event streams past the tenant's cap answer 429 too_many_streams until one is closed. A long
    reconstruction holds the worker meanwhile, so the flooded export is never claimed and every
    pair changes it."""
    server, http = live
    info = http.get("/v1/info").json()["limits"]
    burst, cap = info["job_changes_burst"], info["max_event_streams"]
    long = http.post("/v1/jobs", json={"capture_id": made["capture"], "params": {
        "preset": "test", "config": {"sequence": {"enabled": False},
                                     "train": {"schedule": {"iterations": 5000}}}}})
    export = http.post("/v1/exports", json={"job_id": made["job"]["id"], "formats": ["ply"]})
    assert long.status_code == export.status_code == 202, (long.text, export.text)
    long, export = long.json()["id"], export.json()["id"]
    answers = []
    for i in range(4 * burst):  # the bucket also refills meanwhile (a token a second)
        r = http.post(f"/v1/jobs/{export}/{('cancel', 'retry')[i % 2]}")
        answers.append(r.status_code)
        if r.status_code == 429:
            break
    error = _refused(r, server, 429)
    assert error["code"] == "rate_limited" and int(r.headers["Retry-After"]) >= 1, error
    assert set(answers) <= {202, 429} and answers.count(429) == 1, answers
    assert http.get(f"/v1/jobs/{export}").status_code == 200  # reads are not limited
    with httpx.Client(base_url=server.url, timeout=60,
                      limits=httpx.Limits(max_connections=cap + 2)) as streams:
        held = [streams.send(streams.build_request("GET", f"/v1/jobs/{long}/events"),
                             stream=True) for _ in range(cap)]
        assert [h.status_code for h in held] == [200] * cap
        over = streams.get(f"/v1/jobs/{long}/events")
        assert _refused(over, server, 429)["code"] == "too_many_streams"
        assert over.headers["Retry-After"].isdigit()
        held.pop().close()  # the client goes away: its slot comes back

        def reopened():
            r = streams.send(streams.build_request("GET", f"/v1/jobs/{long}/events"),
                             stream=True)
            if r.status_code == 200:
                return r
            r.close()
            return None

        held.append(wait_for(reopened, 60, "a stream after one was closed"))
        client = Client(server.url)  # waits out the rate limit
        for job in (export, long):  # the export first: while `long` runs, it cannot start
            if client.job(job)["state"] in ("queued", "running"):
                client.cancel(job)
        for h in held:
            h.close()
