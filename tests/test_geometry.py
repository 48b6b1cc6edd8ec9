"""Rigid transforms of point batches (dexflow.geometry): numpy and torch, batched and single."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import RigidTransform, Rotation

from dexflow.geometry import rotate_vectors, transform_points, world_to_object


def _poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rotation = Rotation.random(n, rng=rng)
    return RigidTransform.from_components(rng.normal(size=(n, 3)), rotation).as_matrix()


@pytest.fixture
def data():
    rng = np.random.default_rng(1)
    return _poses(6), rng.normal(size=(6, 40, 3))


def test_batch_equals_one_pose_at_a_time(data):
    poses, points = data
    batch = transform_points(poses, points)
    for pose, p, out in zip(poses, points, batch, strict=True):
        np.testing.assert_allclose(out, transform_points(pose, p), rtol=0, atol=1e-15)
        np.testing.assert_allclose(out, RigidTransform.from_matrix(pose).apply(p), atol=1e-12)
    np.testing.assert_allclose(
        rotate_vectors(poses, points), batch - poses[:, None, :3, 3], rtol=0, atol=1e-12
    )


def test_world_to_object_inverts_the_pose(data):
    poses, points = data
    world = transform_points(poses, points)
    np.testing.assert_allclose(world_to_object(world, poses), points, rtol=0, atol=1e-12)
    # On an exactly rigid pose the general inverse is the rigid one, (R^T, -R^T t).
    rot, trans = poses[:, :3, :3], poses[:, :3, 3]
    rigid = np.einsum("tji,tnj->tni", rot, world - trans[:, None])
    np.testing.assert_allclose(world_to_object(world, poses), rigid, rtol=0, atol=1e-12)


def test_torch_matches_numpy_and_gradients_flow(data):
    poses, points = data
    poses_t = torch.as_tensor(poses).requires_grad_(True)
    points_t = torch.as_tensor(points).requires_grad_(True)
    out = transform_points(poses_t, points_t)
    np.testing.assert_allclose(out.detach().numpy(), transform_points(poses, points), atol=1e-15)
    np.testing.assert_allclose(
        rotate_vectors(poses_t, points_t).detach().numpy(),
        rotate_vectors(poses, points),
        atol=1e-15,
    )
    # d/dp of sum(w . (R p + t)) is R^T w; d/dt is the sum of w over the points.
    weights = torch.randn(out.shape, dtype=out.dtype, generator=torch.Generator().manual_seed(0))
    (out * weights).sum().backward()
    expected = torch.einsum("tji,tnj->tni", poses_t.detach()[:, :3, :3], weights)
    torch.testing.assert_close(points_t.grad, expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(poses_t.grad[:, :3, 3], weights.sum(1), rtol=0, atol=1e-12)
    assert torch.autograd.gradcheck(
        transform_points,
        (poses_t[:2].detach().requires_grad_(), points_t[:2, :3].detach().requires_grad_()),
    )
