"""The player in headless Chromium against a real `dgs serve`: a five-frame sequence
reconstructed through the service (groups of two: three groups, with tracked frames) is
exported by the page as a stream, fetched by ranges, played through, relit live, and one frame
of the relit view compared pixel by pixel with the server's relight of the same frame and
camera; a damaged stream is refused with the reason on the page and nothing else breaks.

Needs Debian's chromium and chromium-driver, like test_web.py."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from live_server import LiveServer, create_key

pytestmark = pytest.mark.timeout(600)

test_web = pytest.importorskip("test_web", reason="the browser tests need selenium + chromium")
from test_web import CANONICAL, TINY, browser, click, shot, text  # noqa: E402,F401
from test_web import wait_for as _wait_for  # noqa: E402


def wait_for(d, what: str, predicate, timeout: float = 60):
    """test_web.wait_for, also saying what the player's status line says."""
    try:
        return _wait_for(d, what, predicate, timeout)
    except AssertionError as exc:
        raise AssertionError(f"{exc}; player: {text(d, 'player-status')!r}") from None

# Tolerance of the page's relit frame against the server's (the stream's frame against the PLY, same
# camera): the stream's quantization, float16/32 blending on the GPU, the depth sort in 65536
# bins against the server's exact one (docs/stream.md, "The player").
RELIT_PSNR_DB = 38.0


@pytest.fixture(scope="module")
def sequence_job(tmp_path_factory):
    """(server, key, job id, capture folder): a succeeded 5-frame reconstruction, GoP 2."""
    from core.synth import SynthConfig, synthesize
    from service.client import Client

    base = tmp_path_factory.mktemp("player")
    synthesize(base / "synth", SynthConfig(frames=5, views=8, width=32, height=32, seed=3,
                                           ao_directions=8))
    folder = base / "capture"
    for path in (base / "synth").rglob("*"):
        rel = path.relative_to(base / "synth").as_posix()
        if path.is_file() and rel.startswith(CANONICAL):
            (folder / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(path, folder / rel)
    data = base / "data"
    key = create_key(data, "studio")
    live = LiveServer(data, base / "serve.log").start()
    try:
        with Client(live.url, key) as api:
            cap = api.create_capture(folder)
            api.upload_capture(cap["id"], folder)
            api.commit(cap["id"])
            job = api.submit(cap["id"], {"preset": "test", "gop": 2, "config": TINY})
            job = api.wait(job["id"], timeout=400)
            assert job["state"] == "succeeded", job.get("error")
        yield live, key, job["id"], data
    finally:
        live.stop()


def server_relit(live, key: str, job_id: str, body: dict) -> np.ndarray:
    """The server's relit PNG (H, W, 3) uint8 of one frame and camera."""
    import httpx
    from PIL import Image

    from service.client import Client

    with Client(live.url, key) as api:
        r = httpx.post(f"{live.url}/v1/renders", json={"job_id": job_id, **body},
                       headers={"Authorization": f"Bearer {key}"}, timeout=30)
        assert r.status_code == 202, r.text
        render = api.wait(r.json()["id"], timeout=200)
        assert render["state"] == "succeeded", render.get("error")
        png = [a for a in api.artifacts(render["id"], "relit") if a["path"].endswith(".png")]
        assert len(png) == 1, png
        raw = httpx.get(f"{live.url}/v1/jobs/{render['id']}/artifacts/{png[0]['path']}",
                        headers={"Authorization": f"Bearer {key}"}).content
    return np.asarray(Image.open(io.BytesIO(raw)).convert("RGB"))


def page_pixels(d) -> np.ndarray:
    info = d.execute_script("""
        const r = window.dgsPlayer.player.renderer;
        return [r.canvas.width, r.canvas.height, Array.from(r.pixels())];""")
    w, h, px = info
    return np.asarray(px, np.uint8).reshape(h, w, 4)[..., :3]


def sign_in(d, live, key) -> None:
    d.get(live.url + "/")
    wait_for(d, "the sign-in form", lambda d: d.find_element("id", "signin").is_displayed())
    d.find_element("id", "api-key").send_keys(key)
    click(d, "signin-button")
    wait_for(d, "the workspace", lambda d: d.find_element("id", "workspace").is_displayed())


def test_the_page_plays_a_relit_stream_matching_the_servers_relight(sequence_job, browser):
    from selenium.webdriver.support.ui import Select

    live, key, job_id, data = sequence_job
    d = browser
    sign_in(d, live, key)
    wait_for(d, "the job list", lambda d: job_id in d.find_element("id", "job-select")
             .get_attribute("innerHTML"))
    Select(d.find_element("id", "job-select")).select_by_value(job_id)
    click(d, "player-open")
    wait_for(d, "the stream", lambda d: "groups loaded" in text(d, "player-status")
             or d.find_element("id", "player-status").get_attribute("data-state") == "error", 240)
    wait_for(d, "every group", lambda d: "3 of 3 groups loaded" in text(d, "player-status"), 60)
    header = d.execute_script("return window.dgsPlayer.player.header;")
    assert [g["count"] for g in header["groups"]] == [2, 2, 1]
    assert header["fps"] > 0 and len(header["cameras"]) == 8

    # Play it through once (loop off): every frame shown, the last one last.
    click(d, "player-loop")
    click(d, "player-play")
    wait_for(d, "the end of the sequence", lambda d: text(d, "player-play") == "Play"
             and d.find_element("id", "player-canvas").get_attribute("data-frame") == "4", 120)
    shown = d.execute_script("return window.dgsPlayer.player.stats.shown;")
    assert shown >= 2
    d.execute_script("document.getElementById('player').scrollIntoView()")
    shot(d, "07-player-played")

    # Relight live: a built-in map, rotated, and a light; the held-out camera cam00, frame 3.
    Select(d.find_element("id", "envmap-select")).select_by_value("builtin:sunset")
    d.execute_script("const r = document.getElementById('envmap-rotation'); r.value = '90';"
                     "r.dispatchEvent(new Event('input'));")
    click(d, "light-add")
    Select(d.find_element("id", "player-camera")).select_by_value("cam00")
    Select(d.find_element("id", "player-view")).select_by_value("relit")
    d.execute_script("const s = document.getElementById('player-scrub'); s.value = '3';"
                     "s.dispatchEvent(new Event('input'));")
    wait_for(d, "frame 3", lambda d: d.find_element("id", "player-canvas")
             .get_attribute("data-frame") == "3", 30)
    d.execute_script("window.dgsPlayer.player.draw();")
    page = page_pixels(d)
    d.execute_script("document.getElementById('player').scrollIntoView()")
    shot(d, "08-player-relit")
    server = server_relit(live, key, job_id, {
        "envmap": "builtin:sunset", "rotation_deg": 90, "cameras": "cam00", "frames": "3",
        "lights": [{"kind": "directional", "direction": [1, 1, 1], "intensity": 3}]})
    assert page.shape == server.shape
    mse = float(np.mean((page.astype(np.float64) - server) ** 2))
    psnr = 10 * np.log10(255.0 ** 2 / max(mse, 1e-12))
    print(f"page vs server relight, frame 3, cam00: PSNR {psnr:.2f} dB, "
          f"max difference {int(np.abs(page.astype(int) - server).max())}/255")
    assert psnr >= RELIT_PSNR_DB, psnr
    # The other views draw something different from each other.
    views = {}
    for view in ("appearance", "normals", "ao"):
        Select(d.find_element("id", "player-view")).select_by_value(view)
        d.execute_script("window.dgsPlayer.player.draw();")
        views[view] = page_pixels(d)
    assert len({v.tobytes() for v in views.values()} | {page.tobytes()}) == 4
    severe = [e for e in d.get_log("browser") if e["level"] == "SEVERE"]
    assert not severe, severe



def test_the_page_refuses_a_damaged_stream_and_says_why(sequence_job, browser):
    """A corrupted group: the page says which and why, keeps the frames it had, and stops.
    (A fresh browser: the first test's would revalidate its cached ranges against the
    artifact's unchanged ETag.)"""
    from selenium.webdriver.support.ui import Select

    live, key, job_id, data = sequence_job
    d = browser
    stream = next(Path(data).rglob("stream.dgss"))
    raw = bytearray(stream.read_bytes())
    head_len = int.from_bytes(raw[8:12], "little")
    group = json.loads(raw[12:12 + head_len])["groups"][1]
    raw[12 + head_len + group["offset"] + 30] ^= 0xFF
    stream.write_bytes(bytes(raw))
    sign_in(d, live, key)
    wait_for(d, "the job list", lambda d: job_id in d.find_element("id", "job-select")
             .get_attribute("innerHTML"))
    Select(d.find_element("id", "job-select")).select_by_value(job_id)
    click(d, "player-open")
    wait_for(d, "the refusal", lambda d: d.find_element("id", "player-status")
             .get_attribute("data-state") == "error", 60)
    assert "group 1: corrupted (CRC-32 mismatch)" in text(d, "player-status")
    assert d.find_element("id", "player-canvas").get_attribute("data-frame") == "0"
    click(d, "player-play")  # playing on stays refused, without a crash
    assert "corrupted" in text(d, "player-status")
    d.execute_script("document.getElementById('player').scrollIntoView()")
    shot(d, "09-player-refused")
    severe = [e for e in d.get_log("browser") if e["level"] == "SEVERE"]
    assert not severe, severe
