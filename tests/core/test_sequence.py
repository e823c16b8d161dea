"""core.sequence: the deformation graph against hand-computed values, the losses with their
gradients, track ids through densification and pruning, GoP segmentation, and a 3-frame sequence
that is stopped twice (once in each stage) and resumed to the same result as a straight run."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from core.model import GaussianModel
from core.plyio import read_track_ids
from core.sequence import (
    DeformationGraph,
    TrackedState,
    anchors_of,
    anisotropy_loss,
    arap_loss,
    blend_weights,
    build_graph,
    farthest_point_sampling,
    prune_transparent,
    quat_norm_loss,
    relabel,
    temporal_loss,
)
from core.config import DensifyConfig, roles, segment
from core.strategy import DensifyStrategy

TOL = dict(rtol=1e-5, atol=1e-6)


def _graph(nodes, anchors, weights, edges=((0, 1), (1, 0))) -> DeformationGraph:
    return DeformationGraph(torch.tensor(nodes, dtype=torch.float32),
                            torch.tensor(anchors, dtype=torch.long),
                            torch.tensor(weights, dtype=torch.float32),
                            torch.tensor(edges, dtype=torch.long))


def _quat_z(angle: float) -> list[float]:
    return [math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)]


def test_blend_weights_by_hand():
    # d_max = 5: (1 - d/5)^2 = 0.64, 0.36, 0.16, 0.04, sum 1.2.
    w = blend_weights(torch.tensor([[1.0, 2.0, 3.0, 4.0, 5.0], [2.0, 2.0, 2.0, 2.0, 2.0]]))
    torch.testing.assert_close(w[0], torch.tensor([0.64, 0.36, 0.16, 0.04]) / 1.2, **TOL)
    torch.testing.assert_close(w[1], torch.full((4,), 0.25), **TOL)  # all at d_max: uniform


def test_farthest_point_sampling_and_graph_shapes():
    pts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [10, 0, 0]])
    assert farthest_point_sampling(pts, 3).tolist() == [0, 3, 2]
    # Coinciding points are still each chosen once (in index order once nothing is farther).
    twice = torch.tensor([[0.0, 0, 0], [0, 0, 0], [1, 0, 0], [1, 0, 0]])
    assert farthest_point_sampling(twice, 4).tolist() == [0, 2, 1, 3]
    with pytest.raises(ValueError, match="count"):
        farthest_point_sampling(pts, 5)
    g = build_graph(torch.randn(200, 3, generator=torch.Generator().manual_seed(0)), 20)
    assert g.nodes.shape == (20, 3) and g.anchors.shape == (200, 4) and g.weights.shape == (200, 4)
    torch.testing.assert_close(g.weights.sum(dim=1), torch.ones(200), **TOL)
    assert g.edges.shape == (20 * 8, 2) and bool((g.edges[:, 0] != g.edges[:, 1]).all())
    with pytest.raises(ValueError, match="at least 5 nodes"):
        build_graph(torch.randn(4, 3), 1024)


def test_deformation_blend_by_hand():
    # One point at (1, 0, 0) blended 0.75 / 0.25 from node 0 at the origin (turned 90 degrees
    # about z) and node 1 at (2, 0, 0) (moved by (0, 0, 1)).
    g = _graph([[0.0, 0, 0], [2.0, 0, 0]], [[0, 1]], [[0.75, 0.25]])
    rot = torch.tensor([_quat_z(math.pi / 2), [1.0, 0, 0, 0]])
    trans = torch.tensor([[0.0, 0, 0], [0.0, 0, 1]])
    means, quats, normals = g.deform(torch.tensor([[1.0, 0, 0]]), torch.tensor([[1.0, 0, 0, 0]]),
                                     torch.tensor([[2.0, 0, 0]]), rot, trans)
    # node 0 sends the point to (0, 1, 0), node 1 to (1, 0, 1): 0.75 (0,1,0) + 0.25 (1,0,1).
    torch.testing.assert_close(means, torch.tensor([[0.25, 0.75, 0.25]]), **TOL)
    # Blended quaternion 0.75 q_90 + 0.25 q_0, normalised: a turn about z by 2 atan2(z, w).
    w, z = 0.75 * math.cos(math.pi / 4) + 0.25, 0.75 * math.sin(math.pi / 4)
    angle = 2 * math.atan2(z, w)
    torch.testing.assert_close(quats, torch.tensor([[w, 0, 0, z]]) / math.hypot(w, z), **TOL)
    # The normal turns by the same angle and keeps its length 2.
    torch.testing.assert_close(normals, torch.tensor([[2 * math.cos(angle),
                                                       2 * math.sin(angle), 0.0]]), **TOL)


def _hamilton_written_out(a, b):
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], dim=-1)


def test_the_graphs_quaternion_maps_match_their_references_with_gradients():
    # The deform step's rotation and product are one table each (a few operators on a GPU):
    # the reference rotation (native.reference, the entries written out) and the product
    # written out give the same values and gradients, at any norm and broadcast.
    from core.sequence.graph import quat_multiply, quat_to_rotmat
    from native.reference import quat_to_rotmat as reference

    g = torch.Generator().manual_seed(5)
    q = (torch.randn(64, 4, generator=g, dtype=torch.float64) * 3).requires_grad_()
    p = torch.randn(64, 4, generator=g, dtype=torch.float64).requires_grad_()
    w = torch.randn(64, 3, 3, generator=g, dtype=torch.float64)
    ours, theirs = quat_to_rotmat(q), reference(q)
    torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-14)
    torch.testing.assert_close(torch.autograd.grad((ours * w).sum(), q)[0],
                               torch.autograd.grad((theirs * w).sum(), q)[0], rtol=0, atol=1e-13)
    for a, b in ((q, p), (q[:1], p), (q, p[:1])):
        ours, theirs = quat_multiply(a, b), _hamilton_written_out(a, b)
        torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-14)
        v = torch.randn(ours.shape, generator=g, dtype=torch.float64)
        for x, y in zip(torch.autograd.grad((ours * v).sum(), (a, b)),
                        torch.autograd.grad((theirs * v).sum(), (a, b))):
            torch.testing.assert_close(x, y, rtol=0, atol=1e-13)
    assert torch.autograd.gradcheck(quat_to_rotmat, (q[:4].detach().requires_grad_(),))
    assert torch.autograd.gradcheck(quat_multiply, (q[:4].detach().requires_grad_(),
                                                    p[:4].detach().requires_grad_()))
    # float32, as training runs: the reference's rounding
    torch.testing.assert_close(quat_to_rotmat(q.detach().float()), reference(q.detach().float()),
                               rtol=0, atol=1e-6)


def test_a_rigid_motion_is_reproduced_exactly_and_costs_no_arap():
    gen = torch.Generator().manual_seed(1)
    pts = torch.randn(300, 3, generator=gen)
    g = build_graph(pts, 32)
    angle = 0.7
    R = torch.tensor([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle),
                                                                math.cos(angle), 0], [0, 0, 1.0]])
    T = torch.tensor([0.3, -0.2, 0.5])
    rot = torch.tensor([_quat_z(angle)]).repeat(len(g), 1)
    trans = g.nodes @ R.T + T - g.nodes  # t_j = R g_j + T - g_j
    moved = g.deform_points(pts, rot, trans)
    torch.testing.assert_close(moved, pts @ R.T + T, rtol=1e-5, atol=1e-5)
    assert float(arap_loss(g, rot, trans)) < 1e-10
    q, t = g.identity()
    torch.testing.assert_close(g.deform_points(pts, q, t), pts, **TOL)


def test_arap_and_unit_norm_by_hand_with_gradients():
    g = _graph([[0.0, 0, 0], [1.0, 0, 0]], [[0, 1]], [[0.5, 0.5]])
    rot = torch.tensor([[1.0, 0, 0, 0], [1.0, 0, 0, 0]], requires_grad=True)
    trans = torch.tensor([[0.0, 0, 0], [0.0, 1, 0]], requires_grad=True)
    loss = arap_loss(g, rot, trans)  # R = I: residuals t_j - t_l, |.|^2 = 1 both ways
    loss.backward()
    assert float(loss.detach()) == pytest.approx(1.0)
    torch.testing.assert_close(trans.grad, torch.tensor([[0.0, -2, 0], [0.0, 2, 0]]), **TOL)
    p = torch.tensor([[2.0, 0, 0, 0], [0.0, 1, 0, 0]], requires_grad=True)
    loss = quat_norm_loss(p)  # mean((2 - 1)^2, 0) = 0.5
    loss.backward()
    assert float(loss.detach()) == pytest.approx(0.5)
    torch.testing.assert_close(p.grad, torch.tensor([[1.0, 0, 0, 0], [0.0, 0, 0, 0]]), **TOL)


def _model(n: int, seed: int = 0) -> GaussianModel:
    gen = torch.Generator().manual_seed(seed)
    m = GaussianModel.from_points(torch.randn(n, 3, generator=gen))
    m.params["quats"].data = torch.randn(n, 4, generator=gen)
    m.params["normals"].data = torch.randn(n, 3, generator=gen)
    return m


def test_temporal_l1_by_hand_with_gradients():
    m = _model(2)
    anchor = anchors_of(m)
    anchor["means"] = anchor["means"] + torch.tensor([[0.1, 0, 0], [0, -0.2, 0]])
    anchor["opacity_g"] = anchor["opacity_g"] + torch.tensor([0.05, 0.0])
    m.params["quats"].data = -m.params["quats"].data  # the same rotations: no cost
    terms = temporal_loss(m, anchor)
    values = {k: float(v.detach()) for k, v in terms.items()}
    assert values["temporal_means"] == pytest.approx(1.0 * 0.3 / 6)
    assert values["temporal_opacity_g"] == pytest.approx(0.01 * 0.05 / 2, rel=1e-4)
    assert values["temporal_quats"] < 1e-7 and values["temporal_normals"] < 1e-7
    terms["temporal_means"].backward()
    expected = torch.tensor([[-1.0, 0, 0], [0, 1.0, 0]]) / 6  # d mean|x - a| = sign(x - a) / 6
    torch.testing.assert_close(m.params["means"].grad, expected, **TOL)
    # A normal turned by 90 degrees: |(0,1,0) - (1,0,0)| summed over 3 components = 2, per
    # component 2/3, over 2 Gaussians (the other agrees) 1/3, times 0.5.
    m2 = _model(2)
    m2.params["normals"].data = torch.tensor([[0.0, 1, 0], [0, 0, 1]])
    a2 = anchors_of(m2)
    a2["normals"] = torch.tensor([[1.0, 0, 0], [0, 0, 1]])
    assert float(temporal_loss(m2, a2)["temporal_normals"].detach()) == pytest.approx(0.5 / 3)


def test_anisotropy_by_hand_with_gradients():
    s = torch.tensor([[1.0, 1, 1], [1, 1, 5], [1, 2, 8]], requires_grad=True)
    loss = anisotropy_loss(s)  # ratios 1, 5, 8 -> max(r - 3, 0) = 0, 2, 5; mean 7/3
    loss.backward()
    assert float(loss.detach()) == pytest.approx(0.01 * 7 / 3)
    # d(s_max / s_min): 1/s_min on s_max, -s_max/s_min^2 on s_min, each / 3 rows, times 0.01.
    expected = torch.tensor([[0.0, 0, 0], [-5.0, 0, 1], [-8.0, 0, 1]]) * 0.01 / 3
    torch.testing.assert_close(s.grad, expected, **TOL)


def test_track_ids_follow_densification_and_pruning():
    m = _model(6, seed=3)
    with torch.no_grad():  # Gaussian 1 small (clone), Gaussian 4 large (split), all opaque
        m.params["scales"].data[:] = math.log(0.001)
        m.params["scales"].data[4] = math.log(0.5)
        m.params["opacity_c"].data[:] = 2.0
        m.params["opacity_g"].data[:] = 2.0
    z = torch.zeros(6)
    state = TrackedState(z.clone(), z.clone(), torch.ones(6), z.clone(), z.clone(), rho=0.1,
                         ids=torch.arange(10, 16), anchor=anchors_of(m), next_id=100)
    state.grad_c[[1, 4]] = 1.0  # above the threshold in the appearance branch only
    before = anchors_of(m)
    strategy = DensifyStrategy(DensifyConfig(prune_scale=None), extent=1.0)
    strategy.densify(m, None, state, torch.Generator().manual_seed(0))
    assert relabel(state, m) == 2 and state.next_id == 102 and state.born == 2
    ids = state.ids.tolist()
    # Survivors keep ids and anchors; the clone's copy and the split's second sample are new.
    assert ids == [10, 11, 12, 13, 15, 100, 14, 101]
    keep = [0, 1, 2, 3, 5]
    torch.testing.assert_close(state.anchor["means"][:5], before["means"][keep])
    now = anchors_of(m)
    for row in (5, 7):  # new rows: anchors are their own values at birth
        torch.testing.assert_close(state.anchor["means"][row], now["means"][row])
    torch.testing.assert_close(state.anchor["means"][6], before["means"][4])  # first split sample
    with torch.no_grad():  # make 11 and 100 transparent in both branches
        for row in (1, 5):
            m.params["opacity_c"].data[row] = -10.0
            m.params["opacity_g"].data[row] = -10.0
    assert prune_transparent(m, None, state) == 2
    assert state.ids.tolist() == [10, 12, 13, 15, 14, 101] and len(m) == 6
    assert all(v.shape[0] == 6 for v in state.anchor.values())


def test_gop_segmentation():
    frames = [f"{i:06d}" for i in range(7)]
    gops = segment(frames, 3)
    assert [g.frames for g in gops] == [tuple(frames[0:3]), tuple(frames[3:6]), (frames[6],)]
    assert [g.key for g in gops] == [frames[0], frames[3], frames[6]]
    r = roles(frames, 3)
    assert [x.key for x in r] == [True, False, False, True, False, False, True]
    assert r[2].previous == frames[1] and r[3].previous is None and r[5].gop == 1
    assert all(x.key for x in roles(frames, 1))
    with pytest.raises(ValueError, match="gop"):
        segment(frames, 0)
    with pytest.raises(ValueError, match="distinct"):
        segment(["a", "a"], 2)


def test_the_plan_gives_each_tracked_frame_its_inputs_from_the_records():
    """GopPlan: a tracked frame starts from its predecessor (with the two before it in its group
    for the motion), takes the group's next track id and the previous frame's deform loss, or
    the run's median where a key frame precedes it, and the credit the records leave it."""
    from core.config import SequenceConfig
    from core.sequence import GopPlan

    frames = ["a", "b", "c", "d", "e"]
    plan = GopPlan(frames, 4, SequenceConfig(refine_borrow=1), 100)
    assert [r.key for r in plan.roles] == [True, False, False, False, True]
    assert plan.nominal == 28 and plan.inputs(0, {}) is None
    done = {"gaussians": 100, "seconds": 1.0}
    records = {"a": {**done, "next_track_id": 100, "previous": None},
               "b": {**done, "next_track_id": 104, "previous": "a", "deform_loss": 0.2,
                     "refine_steps": 26, "refine_nominal": 28,
                     "start": {"from": "rest", "scores": {}, "views": {}}}}
    second = plan.inputs(1, {"a": records["a"]})
    assert (second.previous, second.earlier, second.earliest, second.next_id) == \
        ("a", None, None, 100)
    assert second.reference_loss is None and second.refine_reference is None
    assert second.refine_credit == 1 * (28 - 24)  # borrow against one frame at its floor
    third = plan.inputs(2, records)
    assert (third.previous, third.earlier, third.next_id) == ("b", "a", 104)
    assert third.reference_loss == 0.2 and third.refine_reference is None
    assert third.refine_credit == 2 + 4  # b saved 2; d can pay back 4
    seq = plan.record(records)
    assert [f["done"] for f in seq["frames"]] == [True, True, False, False, False]
    assert [f["start"] for f in seq["frames"]][:2] == [None, "rest"]
    assert [g["frames"] for g in seq["gops"]] == [frames[:4], frames[4:]]
    independent = GopPlan(frames, 4, SequenceConfig(enabled=False), 100)
    assert all(r.key for r in independent.roles) and independent.record({})["gop"] == 1


def _track(capture, ply, train, seq, **kw):
    """A tracker of frame 000001 from the frame PLY `ply`."""
    from core.sequence import FrameTracker, load_frame
    from core.training import frame_views

    model, ids = load_frame(ply)
    return FrameTracker(frame_views(capture, "000001"), model, ids, 10 ** 6, train, seq, **kw)


# -- end to end ----------------------------------------------------------------------------------
TINY_RUN = {"train": {"schedule": {"iterations": 40, "stage2_start": 12, "stage3_start": 28,
                                   "densify_from": 2, "densify_until": 24, "densify_interval": 5,
                                   "reset_interval": 15, "sh_interval": 5},
                      "init_points": 300},
            "sequence": {"num_nodes": 64, "deform_fraction": 0.25, "refine_fraction": 0.25,
                         "deform_views": 2},
            "checkpoint_every": 4, "gop": 3}


@pytest.fixture(scope="module")
def capture3(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from core.synth import SynthConfig, synthesize

    out = tmp_path_factory.mktemp("seq") / "capture"
    synthesize(out, SynthConfig(frames=3, views=8, width=32, height=32, seed=4, priors=True,
                                ao_directions=8))
    return out


def _reconstruct(capture: Path, run: Path, **kwargs) -> dict:
    from core.pipeline import reconstruct

    return reconstruct(capture, run, preset="test", overrides=TINY_RUN, progress=False, **kwargs)


def test_three_frames_stop_twice_and_resume_to_the_straight_result(capture3, tmp_path,
                                                                   one_thread):
    from core.evaluation import evaluate_run
    from core.pipeline import Stopped

    straight = tmp_path / "straight"
    events = []
    straight_metrics = _reconstruct(capture3, straight, on_progress=events.append)
    # Cost in rendered images: D steps of 2 views (the default) and R steps of one.
    assert straight_metrics["frames"]["000001"]["renders"] == 10 * 2 + 11
    # The group's key frame trains sequence.key_steps (2) times the schedule's 40 steps.
    assert straight_metrics["frames"]["000000"]["renders"] == 2 * 40
    # The third frame chooses its start among rest and the first two frames' motion continued
    # at the candidate dampings (the second frame has no motion to go on).
    starts = [straight_metrics["frames"][f]["start"] for f in ("000001", "000002")]
    assert starts[0] == {"from": "rest", "scores": {}, "views": {}}
    assert set(starts[1]["scores"]) == {"rest", "damped 1"}
    # The race's winner was scored on the most views, and has the lowest mean among the
    # starts scored on as many (core.sequence.starts).
    won, views = starts[1]["from"], starts[1]["views"]
    assert set(views) == {"rest", "damped 1"} and views[won] == max(views.values()) >= 4
    assert starts[1]["scores"][won] == min(v for n, v in starts[1]["scores"].items()
                                           if views[n] == views[won])
    seq = json.loads((straight / "sequence.json").read_text())
    assert [f["role"] for f in seq["frames"]] == ["key", "deformed", "deformed"]
    kept = straight_metrics["frames"]["000002"]["start"]["from"]
    assert seq["frames"][2]["start"] == kept and seq["frames"][2]["start_views"] == views[won]
    assert [g["frames"] for g in seq["gops"]] == [["000000", "000001", "000002"]]
    assert seq["timings"]["seconds_per_deformed_frame"] > 0 and seq["gaussians"]["mean"] > 0
    assert {e.phase for e in events if e.frame_index > 0} == {"deform", "refine"}
    assert [e.frame for e in events if e.kind == "frame_done"] == ["000000", "000001", "000002"]
    # D = R = 10 steps for a 40-step key frame, and the refine stages sized by refine_adapt:
    # the second frame asks 2x (refine_second) but may borrow only what the third can pay back
    # at its floor (ceil(0.85 x 10) = 9): 11 steps; the third then runs 9, whatever its ratio.
    # Together they refine the nominal 2 x 10.
    second = [e.iterations for e in events if e.frame_index == 1]
    assert set(second) == {20, 21} and second[-1] == 21  # 20 until its refine stage starts
    assert [e.iterations for e in events if e.frame_index == 2][-1] == 19
    assert [(straight_metrics["frames"][f]["refine_steps"],
             straight_metrics["frames"][f]["refine_nominal"])
            for f in ("000001", "000002")] == [(11, 10), (9, 10)]
    assert [f["refine_steps"] for f in seq["frames"]] == [None, 11, 9]
    ids = [read_track_ids(straight / "frames" / f / "gaussians.ply") for f in
           ("000000", "000001", "000002")]
    assert ids[0].tolist() == list(range(len(ids[0])))  # key frame: 0..N-1
    for a, b in zip(ids, ids[1:]):
        assert len(set(b.tolist())) == len(b)  # unique within a frame
        assert len(np.intersect1d(a, b)) >= 0.8 * len(a)  # most Gaussians carry over
    for frame in ("000001", "000002"):
        assert (straight / "renders" / frame / "cam00_rgb.png").is_file()

    # Stop in frame 1's deform stage (step 3), resume, stop in frame 2's refine stage (step 15).
    resumed = tmp_path / "resumed"
    for frame, step in (("000001", 3), ("000002", 15)):
        with pytest.raises(Stopped) as stop:
            _reconstruct(capture3, resumed, resume=resumed.exists(),
                         should_stop=lambda f=frame, s=step: last[0] == (f, s),
                         on_progress=lambda e: last.__setitem__(0, (e.frame, e.step)))
        assert (stop.value.frame, stop.value.step) == (frame, step)
        assert (resumed / "checkpoints" / f"{frame}.pt").is_file()
    metrics = _reconstruct(capture3, resumed, resume=True)
    assert metrics["frames"]["000002"]["resumed_at"] == 15
    for frame in ("000001", "000002"):
        a = (straight / "frames" / frame / "gaussians.ply").read_bytes()
        assert a == (resumed / "frames" / frame / "gaussians.ply").read_bytes(), frame
    ev = evaluate_run(straight)
    assert ev["flicker"] is not None and ev["flicker"] >= 0
    assert len(ev["temporal"]["psnr_per_frame"]) == 3 and len(ev["temporal"]["pairs"]) == 2


last: list = [None]


def test_independent_mode_makes_every_frame_a_key_frame(capture3, tmp_path, one_thread):
    run = tmp_path / "run"
    cfg = {**TINY_RUN, "sequence": {"enabled": False},
           "train": {**TINY_RUN["train"], "schedule": {**TINY_RUN["train"]["schedule"],
                                                       "iterations": 20, "stage2_start": 6,
                                                       "stage3_start": 14}}}
    from core.pipeline import reconstruct

    reconstruct(capture3, run, preset="test", overrides=cfg, progress=False, frames="0:2")
    seq = json.loads((run / "sequence.json").read_text())
    assert [f["role"] for f in seq["frames"]] == ["key", "key"] and seq["gop"] == 1


def test_a_deform_step_averages_its_views_and_scores_the_silhouette(capture3, tmp_path,
                                                                    one_thread, monkeypatch):
    """deform_views renders per step, each view's terms averaged; the silhouette term is
    deform_mask x mean |blur(alpha_c) - blur(mask)| at the step's coarse-to-fine blur."""
    import core.training.loop as loop_mod
    from core.data import load_capture
    from core.config import apply_overrides, preset_config as resolve_config
    from core.pipeline import reconstruct
    from core.config import SequenceConfig
    from core.sequence.deform import blur, blur_sigma

    run = tmp_path / "key"
    reconstruct(capture3, run, preset="test", overrides=TINY_RUN, progress=False, frames="0:1")
    cfg = apply_overrides(resolve_config("test"), TINY_RUN, where="test")
    seq = SequenceConfig(num_nodes=64, deform_fraction=0.25, refine_fraction=0.25,
                         deform_views=3, deform_mask=2.0, coarse_sigma=1.5)
    tracker = _track(load_capture(capture3), run / "frames" / "000000" / "gaussians.ply",
                     cfg.train, seq)
    assert tracker.renders == 10 * 3 + 10 and tracker.iterations == 20
    drawn = []
    real = loop_mod.render

    def counting(model, camera, **kw):
        out = real(model, camera, **kw)
        drawn.append((next(k for k, c in enumerate(tracker.cameras) if c is camera),
                      out.alpha_c.detach()))
        return out

    monkeypatch.setattr(loop_mod, "render", counting)
    info = tracker.train_step()
    assert len(drawn) == 3 and len({i for i, _ in drawn}) == 3  # three different views
    sigma = blur_sigma(0, tracker.deform_steps, 1.5)
    want = sum(2.0 * float((blur(a, sigma) - blur(tracker.views[i].mask, sigma)).abs().mean())
               for i, a in drawn) / 3
    assert info.losses["silhouette"] == pytest.approx(want, rel=1e-5)
    assert {"photometric", "normal", "consistency", "arap", "quat_norm"} <= set(info.losses)
    with pytest.raises(ValueError, match="deform_views"):
        SequenceConfig(deform_views=0)


def test_the_deform_stage_starts_from_the_previous_motion_and_resumes_exactly(
        capture3, tmp_path, one_thread):
    """The deform stage's end loss is the mean image loss of its last sixth of steps; a
    checkpoint inside it resumes to the same model; with the previous frames' motion known
    the candidate starts continue it (first and second order), and the race's leader is the
    start the nodes begin from."""
    from core.data import load_capture
    from core.config import apply_overrides, preset_config as resolve_config
    from core.pipeline import reconstruct
    from core.config import SequenceConfig
    from core.sequence import FrameTracker
    from core.sequence.motion import align_tracks
    from core.sequence.tracks import load_frame

    run = tmp_path / "key"
    reconstruct(capture3, run, preset="test", overrides=TINY_RUN, progress=False, frames="0:1")
    cfg = apply_overrides(resolve_config("test"), TINY_RUN, where="test")
    seq = SequenceConfig(num_nodes=64, deform_fraction=0.25, refine_fraction=0.25,
                         deform_views=2, refine_adapt=0)
    capture = load_capture(capture3)
    ply = run / "frames" / "000000" / "gaussians.ply"

    straight = _track(capture, ply, cfg.train, seq)
    while straight.step < straight.iterations:
        straight.train_step()
        if straight.step == 6:
            straight.save_checkpoint(tmp_path / "mid.pt")
    assert straight.deform_steps == 10 and straight.step == 20 and straight.start == "rest"
    assert straight.renders == 10 * 2 + 10 and len(straight.deform_losses) == 10
    assert straight.deform_loss == pytest.approx(straight.deform_losses[-1])  # 10 // 6 = 1
    resumed = _track(capture, ply, cfg.train, seq)
    resumed.load_checkpoint(tmp_path / "mid.pt")
    assert resumed.step == 6 and resumed.deform_losses == straight.deform_losses[:6]
    resumed.train()
    for k, v in straight.model.params.items():
        assert torch.equal(v, resumed.model.params[k]), k
    assert resumed.deform_loss == straight.deform_loss

    # With the previous motion known (here: every Gaussian 2 cm lower one frame before, 5 cm
    # two frames before), the damped and the second-order predictions join rest.
    model, ids = load_frame(ply)
    earlier = align_tracks(ids, ids, model.means.detach() - torch.tensor([0.0, 0.0, 0.02]))
    earliest = align_tracks(ids, ids, model.means.detach() - torch.tensor([0.0, 0.0, 0.05]))
    second = FrameTracker(straight.views, model, ids, 10 ** 6, cfg.train, seq,
                          earlier=earlier, earliest=earliest)
    assert list(second.starts) == ["rest", "damped 1", "second-order 0.5"]
    assert set(second.race.scores) == set(second.starts)
    # The Gaussians rose 3 cm, then 2: 2c 2 - 3 = -1 cm at c = 0.5, the turn of a swing.
    _, t = second.starts["second-order 0.5"]
    # (A node that carries fewer than 4 Gaussians stays at rest.)
    moved = t.abs().sum(dim=1) > 0
    assert int(moved.sum()) >= 0.9 * len(t)
    assert torch.allclose(t[moved], torch.tensor([0.0, 0.0, -0.01]).expand_as(t[moved]),
                          atol=1e-4)
    switch = FrameTracker(straight.views, model, ids, 10 ** 6, cfg.train,
                          replace(seq, motion_candidates=(0.5, 1.0)), earlier=earlier)
    assert list(switch.starts) == ["rest", "damped 0.5", "damped 1"]
    assert switch.start == switch.race.order[0] and len(switch.race.order) == 3
    q, t = switch.starts[switch.start]
    assert torch.equal(switch.node_q.detach(), q) and torch.equal(switch.node_t.detach(), t)


def test_refine_steps_follow_how_the_frame_tracked_within_the_credit(capture3, tmp_path,
                                                                      one_thread):
    """refine_adapt: a frame whose deform stage ended above the previous frame's loss refines
    longer (at most refine_max x the nominal and never beyond its credit), one that ended below
    refines shorter (refine_min x at least), a frame without a reference compares with the
    run's median tracked frame or, before the first, asks refine_second x,
    a frame in debt pays back down to its floor; a checkpoint in the refine stage resumes to the
    same steps and model; the pipeline's credit is what the finished tracked frames left unused
    plus what the remaining ones can pay back."""
    from core.data import load_capture
    from core.config import apply_overrides, preset_config as resolve_config
    from core.pipeline import reconstruct
    from core.config import SequenceConfig
    from core.sequence.budget import median_deform_loss, refine_credit

    run = tmp_path / "key"
    reconstruct(capture3, run, preset="test", overrides=TINY_RUN, progress=False, frames="0:1")
    cfg = apply_overrides(resolve_config("test"), TINY_RUN, where="test")
    capture = load_capture(capture3)
    ply = run / "frames" / "000000" / "gaussians.ply"

    def tracker(reference, credit=0, second=None, **kw):
        kw = {"refine_adapt": 3.0, **kw}
        seq = SequenceConfig(num_nodes=64, deform_fraction=0.25, refine_fraction=0.25,
                             refine_min=0.5, refine_max=2.0, **kw)
        return _track(capture, ply, cfg.train, seq, reference_loss=reference,
                      refine_credit=credit, refine_reference=second)

    cases = {"no reference": (None, 100, 20), "no reference, no credit": (None, 0, 10),
             "far behind, no credit": (1e-9, 0, 10), "far behind, credit 3": (1e-9, 3, 13),
             "far behind, credit 100": (1e-9, 100, 20), "far ahead": (1e9, 100, 5),
             "far behind, 3 in debt": (1e-9, -3, 7), "far behind, deep in debt": (1e-9, -100, 5)}
    for name, (reference, credit, steps) in cases.items():
        t = tracker(reference, credit)
        t.train()
        assert (t.nominal_refine, t.refine_steps, t.step) == (10, steps, 10 + steps), name
        assert t.renders == 10 + steps and t.iterations == 10 + steps, name
    # The exponent applies to the ratio: r = 1.1 with refine_adapt 3 asks 1.33 x, 13 steps.
    t = tracker(None, 100)
    t.train()
    t = tracker(t.deform_loss / 1.1, 100)  # the same deform stage (deterministic) ends at 1.1 x
    t.train()
    assert t.refine_steps == 13
    # A group's second frame (no reference_loss) compares with the run's typical tracked
    # frame when it has one (refine_reference), else asks refine_second (2 x above).
    end = t.deform_loss
    for second, steps in ((end / 1.1, 13), (end * 10, 5), (None, 20)):
        t = tracker(None, 100, second=second)
        t.train()
        assert t.refine_steps == steps, second
    # A start race that scores more than start_views views pays the renders it took beyond
    # them out of the refine stage: a frame far behind with no credit refines that much less.
    from core.sequence import FrameTracker

    base = tracker(None, 0)
    shifted = (base.previous.means.detach() + 0.01, torch.ones(len(base.previous), dtype=bool))
    for race, extra in ((1e9, True), (0.0, False)):
        seq = SequenceConfig(num_nodes=64, deform_fraction=0.25, refine_fraction=0.25,
                             refine_min=0.5, refine_adapt=3.0, start_race=race)
        t = FrameTracker(base.views, base.previous, base.prev_ids, 10 ** 6, cfg.train, seq,
                         reference_loss=1e-9, earlier=shifted)
        views = len(t.views)
        assert t.race.views == ({"rest": views, "damped 1": views} if extra
                                else {"rest": 4, "damped 1": 4})
        assert t.scoring_extra == (views - 4 if extra else 0)  # 2 starts x (views - 4) / 2
        t.train()
        assert t.refine_steps == 10 - t.scoring_extra
        assert t.renders == 10 + t.refine_steps + (t.race.renders + 1) // 2
    fixed = tracker(1e-9, 100, refine_adapt=0.0)
    fixed.train()
    assert fixed.refine_steps == 10
    # Resume inside the adapted refine stage.
    straight = tracker(1e-9, 4)
    while straight.step < straight.iterations:
        straight.train_step()
        if straight.step == 12:
            straight.save_checkpoint(tmp_path / "mid.pt")
    resumed = tracker(1e-9, 4)
    resumed.load_checkpoint(tmp_path / "mid.pt")
    assert (resumed.step, resumed.refine_steps, resumed.iterations) == (12, 14, 24)
    resumed.train()
    for k, v in straight.model.params.items():
        assert torch.equal(v, resumed.model.params[k]), k
    frames = {"000000": {"refine_steps": None, "refine_nominal": None},
              "000001": {"refine_steps": 8, "refine_nominal": 10},
              "000002": {"refine_steps": 11, "refine_nominal": 10},
              "000003": {"refine_steps": None}}
    assert refine_credit(frames, 0, 10, 9) == 1  # saved 2, borrowed 1
    assert refine_credit(frames, 3, 10, 9) == 1 + 3  # and 3 frames can pay back 1 each
    assert refine_credit({"1": {"refine_steps": 14, "refine_nominal": 10}}, 3, 10, 9) == -1
    # A frame's start race beyond start_views counts as refine steps spent.
    frames["000002"]["scoring_extra"] = 2
    assert refine_credit(frames, 0, 10, 9) == 1 - 2
    # The second frame's reference: the median deform loss of the run's refined tracked frames.
    frames = {"000000": {"deform_loss": None, "refine_steps": None},
              "000001": {"deform_loss": 0.3, "refine_steps": 8},
              "000002": {"deform_loss": 0.1, "refine_steps": 9},
              "000003": {"deform_loss": 0.9, "refine_steps": None},
              "000004": {"deform_loss": 0.2, "refine_steps": 12}}
    assert median_deform_loss(frames) == pytest.approx(0.2)
    assert median_deform_loss({"000000": frames["000000"]}) is None
    assert SequenceConfig(refine_min=0.85).refine_floor(10) == 9
    assert SequenceConfig(refine_min=0.5).refine_floor(10) == 5
    with pytest.raises(ValueError, match="refine_min"):
        SequenceConfig(refine_min=1.5)
