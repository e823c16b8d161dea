"""A sequence run carried across processes (`core.pipeline.carry`): stopped after a frame,
packed into files of bounded size, laid out in a new folder and resumed there, it ends as the
uninterrupted run does, bit for bit on the CPU."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from core.pipeline import Stopped, reconstruct
from core.pipeline.carry import pack_resume, unpack_resume
from core.plyio import read_gaussian_ply

RUN = {"train": {"schedule": {"iterations": 30, "stage2_start": 10, "stage3_start": 20,
                              "densify_from": 2, "densify_until": 18, "densify_interval": 5,
                              "reset_interval": 15, "sh_interval": 5},
                 "init_points": 300},
       "sequence": {"num_nodes": 32, "deform_fraction": 0.25, "refine_fraction": 0.25,
                    "deform_views": 1},
       "checkpoint_every": 100, "gop": 3}
FRAMES = ("000000", "000001", "000002")


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from core.synth import SynthConfig, synthesize

    out = tmp_path_factory.mktemp("carry") / "capture"
    synthesize(out, SynthConfig(frames=3, views=8, width=32, height=32, seed=4, priors=True,
                                ao_directions=8))
    return out


@pytest.fixture(scope="module")
def straight(capture: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    run = tmp_path_factory.mktemp("straight") / "run"
    before = __import__("torch").get_num_threads()
    __import__("torch").set_num_threads(1)
    try:
        reconstruct(capture, run, preset="test", overrides=RUN, progress=False)
    finally:
        __import__("torch").set_num_threads(before)
    return run


def _stop_after(capture: Path, run: Path, frame: str, overrides: dict = RUN, **kwargs) -> None:
    """The run, stopped at the first step after `frame` is finished (as a time limit would);
    `kwargs` go to `reconstruct`."""
    done: list[str] = []
    with pytest.raises(Stopped):
        reconstruct(capture, run, preset="test", overrides=overrides, progress=False,
                    on_progress=lambda e: e.kind == "frame_done" and done.append(e.frame),
                    should_stop=lambda: frame in done, **kwargs)


def test_a_run_stopped_after_a_frame_resumes_elsewhere_to_the_same_result(
        capture, straight, tmp_path, one_thread):
    first = tmp_path / "first" / "run"
    _stop_after(capture, first, "000001")
    pack = tmp_path / "pack"
    record = pack_resume(first, pack, part_bytes=100_000)
    # Frame 2 deforms frame 1 (all its Gaussians) and continues frame 0's motion (positions).
    assert record["next"] == "000002" and record["carried"] == ["000000", "000001"]
    assert record["capture_from"] == "000001"  # its views: the subject hull of a scene
    assert {f: a["kind"] for f, a in record["arrays"].items()} == {"000001": "full",
                                                                   "000000": "tracks"}
    assert len(record["arrays"]["000001"]["files"]) > 1 and record["lossy"] == {}
    assert all((pack / n).stat().st_size <= 100_000 for n in record["files"][:-1])
    assert record["files"][-1] == "resume.json"

    second = tmp_path / "second" / "run"  # another machine: only the pack is there
    unpack_resume(pack, second)
    assert (second / "frames" / "000001" / "gaussians.ply").read_bytes() == \
        (straight / "frames" / "000001" / "gaussians.ply").read_bytes()
    metrics = reconstruct(capture, second, preset="test", overrides=RUN, progress=False,
                          resume=True)
    assert list(metrics["frames"]) == list(FRAMES)
    assert (second / "frames" / "000002" / "gaussians.ply").read_bytes() == \
        (straight / "frames" / "000002" / "gaussians.ply").read_bytes()
    assert not (second / "frames" / "000000" / "gaussians.ply").exists()  # not redone
    straight_metrics = json.loads((straight / "metrics.json").read_text())
    assert metrics["frames"]["000002"]["refine_steps"] == \
        straight_metrics["frames"]["000002"]["refine_steps"]

    from core.evaluation import evaluate_run

    ev = evaluate_run(second)  # scores what this run made; the carried frames stayed behind
    assert [f["frame"] for f in ev["per_frame"]] == ["000002"]


def test_at_a_group_boundary_nothing_but_the_records_is_carried(capture, tmp_path, one_thread):
    run = tmp_path / "run"
    reconstruct(capture, run, preset="test", overrides={**RUN, "gop": 1}, progress=False,
                frames="0:1")
    record = pack_resume(run, tmp_path / "pack")
    assert record["arrays"] == {} and record["files"] == ["resume.json"]
    assert record["next"] is None  # every chosen frame is finished


def test_a_later_key_frame_resumed_elsewhere_keeps_the_first_ones_static_seeds(
        tmp_path, one_thread):
    """A scene around a subject, every frame a key frame: stopped after frame 0 and carried to a
    machine whose capture holds frame 1 alone (the lend's next call), frame 1 keeps frame 0's
    static seeds and comes out as the run continued in place makes it."""
    import shutil

    from core.synth import SynthConfig, synthesize

    full = tmp_path / "capture"  # 64 pixels: enough for stereo to seed the static scene
    synthesize(full, SynthConfig(frames=2, views=10, width=64, height=64, seed=4,
                                 ao_directions=8))
    data = json.loads((full / "capture.json").read_text())
    data["masks"] = "subject"
    (full / "capture.json").write_text(json.dumps(data))
    later = tmp_path / "later"  # what the next call's capture holds: frame 1 on
    shutil.copytree(full, later, ignore=shutil.ignore_patterns("000000"))
    (later / "capture.json").write_text(json.dumps({**data, "frames": ["000001"]}))

    over = {**RUN, "gop": 1}
    here = tmp_path / "here"
    _stop_after(full, here, "000000", over, frames="0:2")
    record = pack_resume(here, tmp_path / "pack", part_bytes=100_000)
    assert record["next"] == "000001" and record["capture_from"] == "000001"
    assert record["arrays"] == {} and record["static"] == ["resume--static-0.npz"]
    there = tmp_path / "there"
    unpack_resume(tmp_path / "pack", there)
    reconstruct(later, there, preset="test", overrides=over, progress=False, resume=True)
    reconstruct(full, here, preset="test", overrides=over, progress=False, frames="0:2",
                resume=True)
    for path in ("seeds/static.ply", "frames/000001/gaussians.ply"):
        assert (there / path).read_bytes() == (here / path).read_bytes(), path


def test_over_budget_the_higher_sh_is_halved_and_said(straight, tmp_path):
    run = tmp_path / "run"
    import shutil

    shutil.copytree(straight, run)
    metrics = json.loads((run / "metrics.json").read_text())
    del metrics["frames"]["000002"]  # frame 2 is next
    (run / "metrics.json").write_text(json.dumps(metrics))
    lossless = pack_resume(run, tmp_path / "a")
    size = sum((tmp_path / "a" / n).stat().st_size for n in lossless["files"][:-1])
    record = pack_resume(run, tmp_path / "b", budget=int(size * 0.8))
    assert record["lossy"] == {"shN": "float16"}
    unpack_resume(tmp_path / "b", tmp_path / "c")
    got = read_gaussian_ply(tmp_path / "c" / "frames" / "000001" / "gaussians.ply")
    want = read_gaussian_ply(straight / "frames" / "000001" / "gaussians.ply")
    for name, value in want.items():
        expect = value.astype(np.float16).astype(np.float32) if name == "shN" else value
        np.testing.assert_array_equal(got[name], expect, err_msg=name)
    # Not even that fits: the unfinished group stays behind, to be made again.
    small = pack_resume(run, tmp_path / "d", budget=1000)
    assert small["dropped"] == ["000000", "000001"] and small["next"] == "000000"
    assert small["arrays"] == {} and small["carried"] == [] and small["files"] == ["resume.json"]


class _Done:
    kind = "frame_done"

    def __init__(self, index: int):
        self.frame_index = index


def test_a_frame_budget_stops_where_the_next_frame_would_not_fit():
    import time

    from core.pipeline.carry import FrameBudget

    # Groups of 10: after frame 9 comes a key frame, predicted at the key frames' mean.
    budget = FrameBudget(10, time.monotonic() + 1000, reserve=lambda b: 100.0)
    budget.seconds["key"] = [950.0]
    budget.on_progress(_Done(9))
    assert budget.should_stop()  # 950 + 100 s of reserve do not fit in what is left
    budget = FrameBudget(10, time.monotonic() + 1000, reserve=lambda b: 10.0)
    budget.seconds["key"] = [950.0]
    budget.on_progress(_Done(9))
    assert not budget.should_stop()
    after_key = FrameBudget(10, time.monotonic() + 1000, reserve=lambda b: 100.0)
    after_key.seconds["key"] = [5000.0]
    after_key.on_progress(_Done(10))  # a tracked frame next, none measured: no guess stops it
    assert after_key.predict("tracked") is None and not after_key.should_stop()
    budget.on_progress(_Done(3))  # measured now (the time between the two events)
    assert budget.predict("tracked") < 1.0 and not budget.should_stop()
    late = FrameBudget(10, time.monotonic() - 1.0)
    assert late.should_stop()  # inside a frame that overran its deadline
    assert not FrameBudget(10, None).should_stop()
