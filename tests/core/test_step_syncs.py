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
