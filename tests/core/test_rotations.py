"""core.rotations (scipy's Rotation, scalar-first): round trips, the w >= 0 convention, the zero
quaternion, and agreement with the differentiable torch version the rasterizer uses."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from core.rotations import quat_to_rotmat, rotmat_to_quat
from native.reference import quat_to_rotmat as torch_quat_to_rotmat


def test_scalar_first_order():
    a = 0.7
    q = np.array([np.cos(a / 2), 0.0, 0.0, np.sin(a / 2)])  # w, x, y, z: a turn about z
    np.testing.assert_allclose(quat_to_rotmat(q), [[np.cos(a), -np.sin(a), 0],
                                                   [np.sin(a), np.cos(a), 0], [0, 0, 1]],
                               atol=1e-15)
    np.testing.assert_allclose(rotmat_to_quat(quat_to_rotmat(q)), q, atol=1e-15)


def test_round_trip_with_half_turns_and_any_norm():
    rng = np.random.default_rng(4)
    turns = [np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1]), np.eye(3)]
    random = quat_to_rotmat(rng.normal(size=(50, 4)) * 3.0)  # any norm
    for R in turns + list(random):
        q = rotmat_to_quat(R)
        assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[0] >= 0
        np.testing.assert_allclose(quat_to_rotmat(q), R, atol=1e-12)
    assert rotmat_to_quat(random).shape == (50, 4)
    np.testing.assert_allclose(random @ random.transpose(0, 2, 1), np.broadcast_to(
        np.eye(3), (50, 3, 3)), atol=1e-12)


def test_batches_zero_quaternions_and_shapes():
    q = np.zeros((2, 3, 4))
    q[0, 1] = [0.0, 2.0, 0.0, 0.0]
    R = quat_to_rotmat(q)
    assert R.shape == (2, 3, 3, 3)
    np.testing.assert_array_equal(R[1, 2], np.eye(3))  # zero: the identity
    np.testing.assert_allclose(R[0, 1], np.diag([1.0, -1, -1]), atol=1e-15)
    assert quat_to_rotmat(np.zeros((0, 4))).shape == (0, 3, 3)
    with pytest.raises(ValueError, match=r"q: expected shape \(\.\.\., 4\)"):
        quat_to_rotmat(np.zeros(3))
    with pytest.raises(ValueError, match=r"R: expected shape \(\.\.\., 3, 3\)"):
        rotmat_to_quat(np.eye(4))


def test_agrees_with_the_differentiable_torch_version():
    q = np.random.default_rng(2).normal(size=(100, 4))
    ours = quat_to_rotmat(q)
    theirs = torch_quat_to_rotmat(torch.from_numpy(q)).numpy()
    np.testing.assert_allclose(ours, theirs, atol=1e-14)
