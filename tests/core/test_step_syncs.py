"""No training step waits for the device (`core.syncs`): apart from the steps that densify,
prune, reset, change stage or start a frame, a key frame's step and a tracked frame's deform
and refine steps read nothing back to the host. On the CPU such reads cost nothing; on a GPU
each waits for every queued kernel (benchmarks/step_profile.py: 11 a refine step before)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from core.syncs import SyncCounter

RUN = {"train": {"schedule": {"iterations": 40, "stage2_start": 12, "stage3_start": 28,
                              "densify_from": 2, "densify_until": 24, "densify_interval": 5,
                              "reset_interval": 15, "sh_interval": 5},
                 "init_points": 300, "masks": "subject"},
       "sequence": {"num_nodes": 32, "deform_fraction": 0.5, "refine_fraction": 0.5,
                    "deform_views": 2}}


def _syncs_per_step(fitter) -> list[dict]:
    steps = []
    while fitter.step < fitter.iterations:
        with SyncCounter() as counter:
            fitter.train_step()
        steps.append(dict(counter.by_line))
    return steps


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory):
    from core.config import load_config, select_views
    from core.data import load_capture
    from core.synth import SynthConfig, synthesize
    from core.training import Trainer, frame_views

    out = tmp_path_factory.mktemp("syncs") / "capture"
    synthesize(out, SynthConfig(frames=2, views=8, width=32, height=32, seed=4, priors=True,
                                ao_directions=8))
    capture = load_capture(out)
    cfg = load_config("test", overrides=RUN)
    train = replace(cfg.train, bake_ao=False)
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        key = Trainer(frame_views(capture, "000000", select_views(capture, masks="subject")), train)
        key_syncs = _syncs_per_step(key)
    finally:
        torch.set_num_threads(before)
    return capture, train, cfg.sequence, key, key_syncs


def test_a_key_frame_step_reads_nothing_back(fitted):
    key, syncs = fitted[3], fitted[4]
    quiet = [s for i, (s, p) in enumerate(zip(syncs, map(key.plan_at, range(len(syncs)))))
             if i > 0 and not (p.densify or p.reset_opacity or p.start_geometry or p.bake_ao)]
    assert len(quiet) > 20 and all(s == {} for s in quiet), [s for s in quiet if s]


def test_a_tracked_frame_step_reads_nothing_back(fitted, one_thread):
    from core.config import select_views
    from core.sequence import FrameTracker
    from core.training import frame_views

    capture, train, seq, key, _ = fitted
    model = key.model
    moving = torch.zeros(len(model), dtype=torch.bool)
    moving[::2] = True  # the scene mode: a subject moves, the rest is frozen
    views = frame_views(capture, "000001", select_views(capture, masks="subject"))
    tracker = FrameTracker(views, model, torch.arange(len(model)), len(model), train, seq,
                           moving=moving)
    syncs = _syncs_per_step(tracker)
    every = max(1, tracker.refine_steps // 4)
    busy = {0, tracker.deform_steps} | {tracker.deform_steps + k - 1 for k in
                                        range(every, tracker.refine_steps, every)}
    quiet = [s for i, s in enumerate(syncs) if i not in busy]
    assert len(quiet) >= tracker.deform_steps + tracker.refine_steps - 6
    assert all(s == {} for s in quiet), [s for s in quiet if s]


def test_the_step_profile_runs_and_a_deform_step_stays_near_a_key_frames_work(tmp_path):
    # benchmarks/step_profile.py is what a lent GPU runs to count launches (issue 38): it must
    # run as the tree is (it once called frame_views with arguments the function had stopped
    # taking). A deform step's operators (about one kernel launch each on a GPU) stay within
    # 1.8x a key frame step's: its rotations are a table each (the entries written out took
    # 1,209 operators a step against the key frame's 542).
    import json
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    out = tmp_path / "profile.json"
    subprocess.run([sys.executable, str(root / "benchmarks" / "step_profile.py"), "--steps", "1",
                    "--key-steps", "30", "--json", str(out)], check=True, cwd=root,
                   stdout=subprocess.DEVNULL)
    rows = json.loads(out.read_text())["rows"]
    key, deform, refine = (rows[k]["ops"] for k in ("key frame (stage 3)", "tracked: deform",
                                                    "tracked: refine"))
    assert key > 100 and refine > 100
    assert deform <= 1.8 * key, (deform, key)
    assert all(rows[k]["syncs"] == 0 for k in rows)
