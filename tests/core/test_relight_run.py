"""A tiny finished run relit and meshed end to end: `relight_run` (views, orbit MP4, camera path,
progress, stop), `dgs relight` and `dgs mesh` with their bad input, the meshes `reconstruct`
writes by default, and `dgs eval`'s relit scores, mesh scores and contact sheet."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from core.config import read_run
from core.data.images import read_image, write_exr
from core.relight import RelightStopped, load_envmap, relight_run
from core.relight.output import read_mp4_info
from core.relight.presets import PRESETS, builtin_radiance

pytestmark = pytest.mark.usefixtures("one_thread")


def _cli(capsys: pytest.CaptureFixture, *argv) -> tuple[int, str, str]:
    from core.cli import main

    rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


@pytest.fixture(scope="module")
def envmap(synth_capture: Path) -> Path:
    """The synthetic capture's second light (an EXR of gt/envmaps)."""
    return synth_capture / "gt" / "envmaps" / "relight.exr"


def test_builtin_maps_are_valid_and_normalised():
    for name in PRESETS:
        env = load_envmap(f"builtin:{name}", up=(0.0, -1.0, 0.0))
        assert env.radiance.shape == (64, 128, 3) and np.isfinite(env.radiance).all()
        rad = builtin_radiance(name)
        w = np.sin((np.arange(64) + 0.5) / 64 * math.pi)[:, None, None]
        # Mean radiance 1 over the sphere (averaged over the channels).
        assert float(((rad * w).sum((0, 1)) / (w.sum() * 128)).mean()) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="no built-in map 'nope'"):
        load_envmap("builtin:nope")


def test_relight_run_views_and_record(tiny_run: Path, synth_capture: Path, envmap: Path,
                                      tmp_path: Path):
    events = []
    out = tmp_path / "relit"
    record = relight_run(tiny_run, out, envmap=envmap, cameras="all", rotation_deg=30,
                         lights=[{"kind": "directional", "direction": [0, 0, 1],
                                  "intensity": 2.0}],
                         capture_light=synth_capture / "gt" / "lights.json",
                         on_progress=events.append)
    cams = json.loads((synth_capture / "capture.json").read_text())["cameras"]
    assert record["views"] == len(cams) and record["frames"] == ["000000"]
    png = read_image(out / "000000" / "cam01.png")
    exr = read_image(out / "000000" / "cam01.exr")
    assert png.shape == (48, 48, 3) and exr.shape == (48, 48, 4)  # linear premultiplied RGBA
    alpha = exr[..., 3]
    assert 0.02 < alpha.mean() < 0.9 and np.isfinite(exr).all() and (exr >= 0).all()
    assert png[alpha > 0.9].max() > 0.1  # the figure is lit
    assert [e.kind for e in events][0] == "start" and events[-1].kind == "done"
    done = [e.done for e in events]
    assert done == sorted(done) and done[-1] == events[0].total == len(cams)
    saved = json.loads((out / "relight.json").read_text())
    assert saved["params"]["rotation_deg"] == 30 and saved["params"]["lights"][0]["intensity"] == 2
    assert np.asarray(saved["envmap_sh9"]).shape == (9, 3)


def test_relight_orbit_writes_an_mp4_and_stops_when_asked(tiny_run: Path, tmp_path: Path):
    record = relight_run(tiny_run, tmp_path / "orbit", envmap="builtin:sunset", orbit=5, fps=10)
    assert record["videos"] == ["000000.mp4"]
    info = read_mp4_info(tmp_path / "orbit" / "000000.mp4")
    assert info["frames"] == 5 and (info["width"], info["height"]) == (48, 48)
    first, last = (read_image(tmp_path / "orbit" / "000000" / f"orbit00{i}.png") for i in (0, 4))
    assert np.abs(first - last).mean() > 0.005  # the views go round the figure
    calls = []

    def stop() -> bool:
        calls.append(1)
        return len(calls) > 2

    with pytest.raises(RelightStopped, match="after 2 of 5"):
        relight_run(tiny_run, tmp_path / "stopped", envmap="builtin:studio", orbit=5,
                    should_stop=stop)
    assert len(list((tmp_path / "stopped" / "000000").glob("*.png"))) == 2  # written stay


def test_relight_camera_path(tiny_run: Path, synth_capture: Path, tmp_path: Path):
    cam = json.loads((synth_capture / "capture.json").read_text())["cameras"][1]
    c2w = np.linalg.inv(np.asarray(cam["world_to_camera"])) @ np.diag([1.0, -1, -1, 1])
    path = tmp_path / "camera_path.json"
    path.write_text(json.dumps({"render_height": 40, "render_width": 60, "fps": 12,
                                "camera_path": [{"camera_to_world": c2w.ravel().tolist(),
                                                 "fov": 40, "aspect": 1.5}] * 3}))
    record = relight_run(tiny_run, tmp_path / "path", envmap="builtin:neon", camera_path=path)
    assert record["views"] == 3 and record["videos"] == ["000000.mp4"]
    assert read_image(tmp_path / "path" / "000000" / "path000.png").shape == (40, 60, 3)


def test_lights_alone_in_a_black_environment(tiny_run: Path, synth_capture: Path,
                                             tmp_path: Path):
    """No map: only the added light shines, on the side that faces it (cam01 looks from -x)."""
    cam = json.loads((synth_capture / "capture.json").read_text())["cameras"][1]
    assert np.linalg.inv(np.asarray(cam["world_to_camera"]))[0, 3] < -1  # on the -x side

    def relit(direction, name):
        record = relight_run(tiny_run, tmp_path / name, cameras="cam01", lights=[
            {"kind": "directional", "direction": direction, "intensity": 3}])
        assert record["params"]["envmap"] is None and not np.any(record["envmap_sh9"])
        image = read_image(tmp_path / name / "000000" / "cam01.exr")
        return image[..., :3].sum(-1)[image[..., 3] > 0.5]

    front, back = relit([-1, 0, 0], "front"), relit([1, 0, 0], "back")
    # Lambert's max(0, n . l): lit from behind the subject, the camera sees mostly shadow.
    assert back.mean() < 0.2 * front.mean() and (back < 0.05).mean() > 0.5


def test_no_ao_baseline_differs_only_by_visibility(tiny_run: Path, envmap: Path,
                                                   tmp_path: Path):
    a = relight_run(tiny_run, tmp_path / "ao", envmap=envmap, cameras="cam01")
    b = relight_run(tiny_run, tmp_path / "no_ao", envmap=envmap, cameras="cam01", ao=False)
    assert a["views"] == b["views"] == 1
    with_ao = read_image(tmp_path / "ao" / "000000" / "cam01.exr")
    without = read_image(tmp_path / "no_ao" / "000000" / "cam01.exr")
    # Visibility <= 1 only darkens the environment term.
    assert (with_ao[..., :3] <= without[..., :3] + 1e-5).all()
    assert without[..., :3].sum() > with_ao[..., :3].sum()


def _bad_map(tmp_path: Path, name: str, image: np.ndarray) -> Path:
    path = tmp_path / name
    write_exr(path, image.astype(np.float32))
    return path


@pytest.mark.parametrize("case, message", [
    ("unreadable", "truncated or corrupt OpenEXR header"),
    ("square", "twice as wide"),
    ("nan", "NaN or Inf"),
    ("zero light", "needs an intensity > 0"),
    ("empty frames", "selects no frame"),
    ("unknown camera", "no camera camXX"),
    ("not a run", "not a run directory"),
    ("no light at all", "give an environment map or at least one light"),
])
def test_cli_relight_bad_input(case: str, message: str, tiny_run: Path, envmap: Path,
                               tmp_path: Path, capsys: pytest.CaptureFixture):
    args = [tiny_run, "--envmap", envmap, "--out", tmp_path / "out"]
    if case == "unreadable":
        (tmp_path / "junk.exr").write_bytes(b"\x76\x2f\x31\x01" + b"x" * 64)
        args[2] = tmp_path / "junk.exr"
    elif case == "square":
        args[2] = _bad_map(tmp_path, "square.exr", np.ones((8, 8, 3)))
    elif case == "nan":
        img = np.ones((8, 16, 3))
        img[2, 3] = np.nan
        args[2] = _bad_map(tmp_path, "nan.exr", img)
    elif case == "zero light":
        args += ["--light", "directional:0,0,1:0"]
    elif case == "empty frames":
        args += ["--frames", "1:1"]
    elif case == "unknown camera":
        args += ["--cameras", "camXX"]
    elif case == "no light at all":
        args = [tiny_run, "--out", tmp_path / "out"]
    else:
        args[0] = tmp_path
    rc, _, err = _cli(capsys, "relight", *args)
    assert rc == 2 and message in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()  # nothing written for bad input


def test_cli_relight_orbit(tiny_run: Path, envmap: Path, tmp_path: Path,
                           capsys: pytest.CaptureFixture):
    rc, out, err = _cli(capsys, "relight", tiny_run, "--envmap", envmap, "--out", tmp_path / "o",
                        "--orbit", "3", "--light", "point:0,-2,1:4:1,0.8,0.6", "--exposure", "-1")
    assert rc == 0, err
    assert "relit 3 view(s) of 1 frame(s), 1 video(s)" in out
    assert read_mp4_info(tmp_path / "o" / "000000.mp4")["frames"] == 3


def test_reconstruct_writes_meshes(tiny_run: Path):
    metrics = json.loads((tiny_run / "metrics.json").read_text())
    info = metrics["frames"]["000000"]["mesh"]
    assert (tiny_run / "meshes" / "000000.ply").is_file()
    assert info["faces"] > 100 and info["files"] == ["000000.ply"]
    recorded = json.loads((tiny_run / "meshes" / "meshes.json").read_text())
    assert recorded["frames"]["000000"]["faces"] == info["faces"]
    assert read_run(tiny_run).config.mesh.resolution == 128


def test_cli_mesh_formats_and_baseline(tiny_run: Path, tmp_path: Path,
                                       capsys: pytest.CaptureFixture):
    import trimesh

    rc, out, err = _cli(capsys, "mesh", tiny_run, "--out", tmp_path / "m", "--formats",
                        "ply,obj,glb", "--resolution", "96")
    assert rc == 0, err
    assert "meshed 1 frame(s)" in out
    meshes = {fmt: trimesh.load(tmp_path / "m" / f"000000.{fmt}", force="mesh")
              for fmt in ("ply", "obj", "glb")}
    assert len({len(m.faces) for m in meshes.values()}) == 1
    assert meshes["ply"].visual.vertex_colors[:, :3].std() > 1  # coloured, not flat
    rc, _, err = _cli(capsys, "mesh", tiny_run, "--out", tmp_path / "a", "--depth",
                      "appearance", "--resolution", "96")
    assert rc == 0, err
    info = json.loads((tmp_path / "a" / "meshes.json").read_text())["frames"]["000000"]
    assert info["depth"] == "appearance" and info["faces"] > 0
    for bad, message in [(["--frames", "3:"], "selects no frame"),
                         (["--formats", "fbx"], "formats"), (["--resolution", "4"], "resolution")]:
        rc, _, err = _cli(capsys, "mesh", tiny_run, "--out", tmp_path / "bad", *bad)
        assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "bad").exists()


def test_eval_scores_relit_views_meshes_and_draws_the_sheet(tiny_run: Path, tmp_path: Path):
    from core.evaluation import evaluate_run

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    result = evaluate_run(run)
    relit = result["relight"]
    for key in ("psnr", "psnr_full", "ssim", "psnr_no_ao", "ssim_no_ao"):
        assert math.isfinite(relit[key]), key
    assert relit["envmap"].endswith("relight.exr") and relit["capture_light"].endswith(
        "lights.json")
    assert (run / "renders" / "000000" / "cam00_relit.png").is_file()
    mesh = result["mesh"]
    assert result["chamfer"] == mesh["chamfer"] > 0 and 0 < mesh["normal_consistency"] <= 1
    assert mesh["chamfer_relative"] < 0.2  # a 100-step run still lands near the figure
    frame = result["per_frame"][0]
    assert frame["relight"]["views"][0]["camera"] == "cam00" and frame["mesh"] is not None
    sheet = np.asarray(Image.open(run / result["contact_sheet"]))
    # capture, render, normal, AO, relit (gt light), gt relit, 3 built-in maps, gt normal.
    assert sheet.shape[1] == 10 * 96 and sheet.shape[0] == 16 + 96
    assert json.loads((run / "eval.json").read_text())["relight"]["psnr"] == relit["psnr"]


def test_meshes_are_written_in_the_source_coordinates(tiny_run: Path, synth_capture: Path,
                                                      tmp_path: Path):
    """A capture whose import record maps its world to the source's (here a shift and a turn)
    gets meshes in the source's coordinates: the same surface, moved by that transform."""
    import trimesh

    from core.config import MeshConfig
    from core.mesh import mesh_run

    capture = tmp_path / "capture"
    shutil.copytree(synth_capture, capture, ignore=shutil.ignore_patterns("gt"))
    doc = json.loads((capture / "capture.json").read_text())
    turn = np.array([[0.0, -1, 0, 0.5], [1, 0, 0, -2.0], [0, 0, 1, 3.0], [0, 0, 0, 1]])
    doc["import"] = {"format": "test", "to_source": {"source_from_world": turn.tolist()}}
    (capture / "capture.json").write_text(json.dumps(doc))
    config = MeshConfig(resolution=64, colors=False)
    plain = mesh_run(tiny_run, tmp_path / "plain", config=config)
    moved = mesh_run(tiny_run, tmp_path / "moved", config=config, capture_dir=capture)
    assert plain["to_source"] is None and np.allclose(moved["to_source"], turn)
    a = trimesh.load(tmp_path / "plain" / "000000.ply", force="mesh")
    b = trimesh.load(tmp_path / "moved" / "000000.ply", force="mesh")
    np.testing.assert_allclose(b.vertices, a.vertices @ turn[:3, :3].T + turn[:3, 3], atol=1e-5)
    assert b.volume == pytest.approx(a.volume)  # a rotation keeps the faces outward
