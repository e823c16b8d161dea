"""Motion prediction for the deform stage (core.sequence.motion): per-node rigid fits of the
motion between the two frames before, continued and damped, and the second-order prediction
from three."""

from __future__ import annotations

import math

import pytest
import torch

from core.sequence.graph import build_graph, quat_multiply
from core.sequence.motion import align_tracks, predict_node_motion, predict_node_motion_second_order
from native.reference import quat_to_rotmat


def _rotation(axis, angle: float) -> torch.Tensor:
    axis = torch.tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    q = torch.cat([torch.tensor([math.cos(angle / 2)], dtype=torch.float64),
                   axis * math.sin(angle / 2)])
    return quat_to_rotmat(q[None])[0]


def _cloud(n: int = 600, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=g) * torch.tensor([0.4, 0.3, 1.2])


def test_align_tracks_looks_up_earlier_positions_by_id() -> None:
    earlier_ids = torch.tensor([7, 2, 9])
    earlier = torch.tensor([[7.0, 0, 0], [2.0, 0, 0], [9.0, 0, 0]])
    pos, known = align_tracks(torch.tensor([2, 9, 11, 7]), earlier_ids, earlier)
    assert known.tolist() == [True, True, False, True]
    assert pos[:, 0].tolist() == [2.0, 9.0, 0.0, 7.0]
    pos, known = align_tracks(torch.tensor([0, 1]), torch.zeros(0, dtype=torch.long),
                              torch.zeros(0, 3))
    assert not known.any()


def test_a_rigid_motion_is_continued_exactly() -> None:
    # Every Gaussian turns 0.3 rad about a pivot and shifts between t-2 and t-1: with damping 1
    # the graph, applied to t-1, must give the same motion once more (to float precision).
    R = _rotation([0.3, 1.0, 0.2], 0.3)
    pivot = torch.tensor([0.1, -0.2, 0.5], dtype=torch.float64)
    shift = torch.tensor([0.05, 0.0, -0.02], dtype=torch.float64)
    move = lambda x: (x.double() - pivot) @ R.T + pivot + shift  # noqa: E731
    before = _cloud()
    current = move(before).float()
    graph = build_graph(current, num_nodes=24)
    q, t = predict_node_motion(graph, current, before, torch.ones(len(before), dtype=torch.bool),
                               damping=1.0)
    predicted = graph.deform_points(current, q, t)
    assert torch.allclose(predicted.double(), move(current), atol=2e-5)
    # Every node turns by the same rotation (its quaternion is unit, the same up to sign).
    assert torch.allclose(quat_to_rotmat(q).double(), R.expand(len(graph), 3, 3), atol=1e-5)


def test_damping_scales_angle_and_displacement() -> None:
    before = _cloud(seed=1)
    shift = torch.tensor([0.1, -0.04, 0.02])
    current = before + shift
    graph = build_graph(current, num_nodes=16)
    known = torch.ones(len(before), dtype=torch.bool)
    q, t = predict_node_motion(graph, current, before, known, damping=0.5)
    assert torch.allclose(t, (0.5 * shift).expand_as(t), atol=1e-5)
    assert torch.allclose(q, torch.tensor([1.0, 0, 0, 0]).expand_as(q), atol=1e-5)
    # A pure rotation about the origin: half the angle, and the nodes move half way along it.
    R = _rotation([0, 0, 1], 0.4)
    current = (before.double() @ R.T).float()
    graph = build_graph(current, num_nodes=16)
    q, t = predict_node_motion(graph, current, before, known, damping=0.5)
    half = quat_to_rotmat(q).double()
    assert torch.allclose(half, _rotation([0, 0, 1], 0.2).expand_as(half), atol=1e-5)
    full = quat_to_rotmat(quat_multiply(q, q)).double()
    assert torch.allclose(full, R.expand_as(full), atol=1e-5)
    moved = graph.nodes.double() @ R.T
    assert torch.allclose(t.double(), 0.5 * (moved - graph.nodes.double()), atol=1e-5)


def test_nodes_without_known_gaussians_stay_at_rest() -> None:
    before = _cloud(seed=2)
    current = before + torch.tensor([0.0, 0.0, 0.1])
    graph = build_graph(current, num_nodes=12)
    # Only the Gaussians of the lower half have a track in the earlier frame.
    known = current[:, 2] < 0.5
    q, t = predict_node_motion(graph, current, before, known, damping=1.0)
    carried = torch.zeros(len(graph))
    carried.index_add_(0, graph.anchors[known].reshape(-1),
                       (graph.weights[known] > 0).float().reshape(-1))
    at_rest = carried < 4
    assert at_rest.any() and (~at_rest).any()
    assert torch.equal(t[at_rest], torch.zeros(int(at_rest.sum()), 3))
    assert torch.allclose(t[~at_rest], torch.tensor([0.0, 0.0, 0.1]).expand(
        int((~at_rest).sum()), 3), atol=1e-5)
    q0, t0 = predict_node_motion(graph, current, before, known, damping=0.0)
    assert torch.equal(t0, torch.zeros_like(t0))
    assert torch.equal(q0, graph.identity()[0])


@pytest.mark.parametrize("angle", [0.05, 1.5, 3.0])
def test_large_and_small_rotations_are_recovered(angle: float) -> None:
    R = _rotation([1.0, -0.5, 0.3], angle)
    before = _cloud(seed=3)
    current = (before.double() @ R.T).float()
    graph = build_graph(current, num_nodes=8)
    q, _ = predict_node_motion(graph, current, before, torch.ones(len(before), dtype=torch.bool),
                               damping=1.0)
    got = quat_to_rotmat(q).double()
    assert torch.allclose(got, R.expand_as(got), atol=1e-4)


def test_second_order_continues_a_constant_acceleration_exactly() -> None:
    # x(t) = x0 + v t + a t^2 / 2 for every Gaussian: with c = 1 the next position is exact,
    # where continuing the last displacement (damping 1) falls short by a.
    x0 = _cloud(seed=4).double()
    v, a = torch.tensor([0.05, -0.02, 0.01]), torch.tensor([0.0, 0.03, -0.01])
    at = lambda t: (x0 + v * t + 0.5 * a * t * t).float()  # noqa: E731
    graph = build_graph(at(2), num_nodes=16)
    known = torch.ones(len(x0), dtype=torch.bool)
    q, t = predict_node_motion_second_order(graph, at(2), at(1), at(0), known, c=1.0)
    assert torch.allclose(graph.deform_points(at(2), q, t), at(3), atol=2e-5)
    assert torch.allclose(q, torch.tensor([1.0, 0, 0, 0]).expand_as(q), atol=1e-5)
    q1, t1 = predict_node_motion(graph, at(2), at(1), known, damping=1.0)
    off = (graph.deform_points(at(2), q1, t1) - at(3)).norm(dim=1)
    assert torch.allclose(off, a.norm().expand_as(off), atol=1e-4)


def test_second_order_follows_a_sinusoid_with_c_its_cosine() -> None:
    # Every Gaussian oscillates along a direction, w = 0.9 rad a frame: at the turning phases a
    # damping of the last displacement cannot follow; c = cos(w) does, exactly.
    x0 = _cloud(seed=5).double()
    w, amp = 0.9, torch.tensor([0.0, 0.3, 0.1], dtype=torch.float64)
    at = lambda t: (x0 + amp * math.sin(w * t + 0.4)).float()  # noqa: E731
    graph = build_graph(at(2), num_nodes=16)
    known = torch.ones(len(x0), dtype=torch.bool)
    q, t = predict_node_motion_second_order(graph, at(2), at(1), at(0), known, c=math.cos(w))
    assert torch.allclose(graph.deform_points(at(2), q, t), at(3), atol=2e-5)
    best_damped = min(float((graph.deform_points(at(2), *predict_node_motion(
        graph, at(2), at(1), known, damping=d)) - at(3)).norm(dim=1).max())
        for d in (0.25, 0.5, 1.0, 1.5))
    assert best_damped > 0.05  # 5 cm off at best, against float precision


def test_second_order_swing_about_a_pivot_and_its_checks() -> None:
    # A rigid swing about a pivot with a sinusoidal angle: the nodes get the next rotation, and
    # positions up to the curvature the point-wise recurrence does not see, well within what the
    # best damping of the last motion leaves.
    pivot = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    x0 = _cloud(seed=6).double() * torch.tensor([0.2, 0.2, 0.8], dtype=torch.float64)
    w, amp = 0.9, 0.4
    angle = lambda t: amp * math.sin(w * t)  # noqa: E731
    at = lambda t: ((x0 - pivot) @ _rotation([1, 0, 0], angle(t)).T + pivot).float()  # noqa: E731
    graph = build_graph(at(2), num_nodes=12)
    known = torch.ones(len(x0), dtype=torch.bool)
    q, t = predict_node_motion_second_order(graph, at(2), at(1), at(0), known, c=math.cos(w))
    step = _rotation([1, 0, 0], angle(3) - angle(2))
    got = quat_to_rotmat(q).double()
    assert torch.allclose(got, step.expand_as(got), atol=0.03)
    err = float((graph.deform_points(at(2), q, t) - at(3)).norm(dim=1).max())
    assert err < 0.25 * float((at(3) - at(2)).norm(dim=1).max())
    damped = min(float((graph.deform_points(at(2), *predict_node_motion(
        graph, at(2), at(1), known, damping=d)) - at(3)).norm(dim=1).max()) for d in (0.5, 1.0))
    assert err < 0.5 * damped
    # Nodes with too few Gaussians known in all three frames stay at rest; c is a cosine.
    none = torch.zeros(len(x0), dtype=torch.bool)
    q0, t0 = predict_node_motion_second_order(graph, at(2), at(1), at(0), none, c=0.5)
    assert torch.equal(q0, graph.identity()[0]) and torch.equal(t0, torch.zeros_like(t0))
    with pytest.raises(ValueError, match="cos"):
        predict_node_motion_second_order(graph, at(2), at(1), at(0), known, c=1.5)
