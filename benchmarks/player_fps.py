"""The page's player on a large frame in headless Chromium (docs/benchmarks.md, "Delivery"):
a two-frame stream of N Gaussians (default 300k: a key frame and a tracked frame that turned)
is opened by the player's own classes (service/web/js/player.js), then timed: decoding the
tracked frame (and uploading it to the GPU), and drawing it relit from an orbit that moves
every draw (so every draw sorts again), in each view.

    python benchmarks/player_fps.py [--gaussians 300000] [--size 640 480] [--draws 5]

Chromium runs headless; without a GPU that is SwiftShader, software GL on the CPU, so the
numbers say what a machine without a graphics card gets (re-measure on a GPU machine).
Needs Debian's chromium and chromium-driver and the dev extra (selenium).
"""

from __future__ import annotations

import argparse
import functools
import http.server
import json
import math
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PAGE = """<!doctype html><html><body><canvas id="c"></canvas><p id="s"></p>
<script type="module">
import { Player } from '/web/js/player.js';
window.bench = async (draws) => {
  const p = new Player(document.getElementById('c'), document.getElementById('s'));
  let t = performance.now();
  await p.open('/stream.dgss');
  const open = performance.now() - t;
  p.look = { env: p.header.envmaps['builtin:studio'], rotation: 30,
             lights: [{ kind: 'directional', vector: [1, 1, 1], color: [1, 1, 1], intensity: 2 }] };
  const gl = p.renderer.gl, px = new Uint8Array(4), out = { open_ms: open };
  t = performance.now();
  p.decodeFrame(1);
  gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
  out.decode_upload_ms = performance.now() - t;
  out.decode_ms = p.stats.decodeMs[p.stats.decodeMs.length - 1];
  for (const mode of ['relit', 'appearance', 'normals', 'ao']) {
    p.mode = mode;
    p.draw();
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
    t = performance.now();
    for (let i = 0; i < draws; i++) {
      p.orbit.yaw += 0.05;
      p.draw();
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
    }
    out[`${mode}_ms`] = (performance.now() - t) / draws;
  }
  out.float32_blend = p.renderer.float32;
  out.renderer = gl.getParameter(gl.RENDERER);
  return out;
};
window.ready = true;
</script></body></html>"""


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:
        pass


def make_stream(path: Path, n: int, width: int, height: int) -> None:
    """A shell of n Gaussians (a figure-sized blob) and the same turned by 0.1 rad."""
    from core.export.run import _builtin_sh9
    from core.export.splats import Splats
    from core.export.stream import write_stream

    rng = np.random.default_rng(0)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    means = d * np.float32([0.4, 0.4, 0.9]) + np.float32([0, 0, 1])
    key = Splats(means=means, scales=np.full((n, 3), math.log(0.006), np.float32),
                 quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                 opacity_c=np.full(n, 0.8, np.float32), opacity_g=np.full(n, 0.8, np.float32),
                 sh0=rng.uniform(-1, 1, (n, 3)).astype(np.float32),
                 shN=rng.uniform(-0.1, 0.1, (n, 15, 3)).astype(np.float32), normals=d,
                 visibility=np.full(n, 0.8, np.float32), ids=np.arange(n)).canonical()
    a = 0.1
    R = np.float32([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    moved = key.take(np.arange(n))
    moved.means = (key.means - np.float32([0, 0, 1])) @ R.T + np.float32([0, 0, 1])
    moved.normals = key.normals @ R.T
    f = 0.9 * width
    eye = np.array([3.0, 0.0, 1.0])
    fwd = np.array([-1.0, 0, 0])
    right = np.cross(fwd, [0, 0, 1.0])
    down = np.cross(fwd, right)
    Rw = np.stack([right, down, fwd])
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = Rw, -Rw @ eye
    cam = {"id": "bench", "width": width, "height": height, "heldout": True,
           "K": [[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], "world_to_camera": w2c.tolist()}
    header = {"frames": ["000000", "000001"], "fps": 24.0, "up": [0, 0, 1], "cameras": [cam],
              "render": {"sh_degree": 3, "beta": 0.7, "eps2d": 0.1, "antialiased": True,
                         "background": [1, 1, 1], "linear": False},
              "capture_light": {"uniform": math.pi}, "envmaps": _builtin_sh9()}
    write_stream(path, [[key, moved]], header)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--gaussians", type=int, default=300_000)
    ap.add_argument("--size", type=int, nargs=2, default=(640, 480))
    ap.add_argument("--draws", type=int, default=5)
    args = ap.parse_args(argv)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    site = Path(tempfile.mkdtemp(prefix="dgs-player-fps-"))
    try:
        shutil.copytree(ROOT / "service" / "web", site / "web")
        (site / "bench.html").write_text(PAGE)
        t = time.perf_counter()
        make_stream(site / "stream.dgss", args.gaussians, *args.size)
        encode_s = time.perf_counter() - t
        handler = functools.partial(_Quiet, directory=str(site))
        server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        opts = webdriver.ChromeOptions()
        opts.binary_location = shutil.which("chromium") or "/usr/bin/chromium"
        for arg in ("--headless", "--no-sandbox", "--disable-gpu", "--window-size=800,700"):
            opts.add_argument(arg)
        driver = webdriver.Chrome(service=Service(shutil.which("chromedriver")
                                                  or "/usr/bin/chromedriver"), options=opts)
        # A draw of a large frame in software GL can hold the page's thread for minutes.
        driver.command_executor.client_config.timeout = 3600
        try:
            driver.set_script_timeout(1800)
            driver.get(f"http://127.0.0.1:{server.server_port}/bench.html")
            for _ in range(100):
                if driver.execute_script("return window.ready === true"):
                    break
                time.sleep(0.1)
            # Started, then polled: one long script call would outlast the driver's timeout.
            driver.execute_script("window.bench(arguments[0]).then((r) => { window.result = r; },"
                                  " (e) => { window.result = {error: String(e)}; });",
                                  args.draws)
            out = None
            while out is None:
                time.sleep(2)
                out = driver.execute_script("return window.result || null;")
        finally:
            driver.quit()
            server.shutdown()
        out.update(gaussians=args.gaussians, size=list(args.size),
                   stream_bytes=(site / "stream.dgss").stat().st_size, encode_s=encode_s)
        print(json.dumps(out, indent=1))
        if "error" in out:
            return 1
        print("| Gaussians | view | ms / draw | frames / s | decode / decode + upload (ms) |")
        print("| --- | --- | --- | --- | --- |")
        for mode in ("relit", "appearance", "normals", "ao"):
            ms = out[f"{mode}_ms"]
            print(f"| {args.gaussians} | {mode} | {ms:.0f} | {1000 / ms:.2f} | "
                  f"{out['decode_ms']:.0f} / {out['decode_upload_ms']:.0f} |")
    finally:
        shutil.rmtree(site, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
