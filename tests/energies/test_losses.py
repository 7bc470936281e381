"""E_D's model-to-data half: every visible vertex is pulled onto the nearest segmented point."""
import numpy as np
import torch

from intercap.energies.losses import hand_contact, nearest_points, visible_vertices_to_points


def patch(offset_m: float):
    """A 10 x 10 vertex grid in z = 0 (normals +z) and the same grid of points `offset_m` above it."""
    xy = np.stack(np.meshgrid(np.linspace(0, 0.3, 10), np.linspace(0, 0.3, 10)), -1).reshape(-1, 2)
    vertices = torch.tensor(np.concatenate([xy, np.zeros((100, 1))], 1), dtype=torch.float32)[None]  # (1, 100, 3)
    points = vertices.clone()
    points[..., 2] += offset_m
    normals = torch.zeros_like(vertices)
    normals[..., 2] = 1.0
    return vertices, normals, points[:, None]  # points (1, C=1, 100, 3)


def test_visible_vertices_are_pulled_onto_their_points():
    vertices, normals, points = patch(0.02)
    visible = torch.ones(1, 1, 100, dtype=torch.bool)
    nearest = nearest_points(vertices, visible, points, torch.ones(1, 1, 100, dtype=torch.bool), 0.10)
    assert (nearest[0, 0] == torch.arange(100)).all()  # each vertex's own point, straight above it
    vertices.requires_grad_(True)
    energy = visible_vertices_to_points(vertices, normals, points, nearest, scale=0.05)
    expected = 0.02**2 / (0.02**2 + 0.05**2) * 0.05**2  # Geman-McClure of the 2 cm gap, times scale^2
    assert torch.allclose(energy, torch.tensor([expected]), rtol=1e-4)
    energy.sum().backward()
    assert (vertices.grad[0, :, 2] < 0).all()  # descent moves every vertex up, onto the points
    assert torch.allclose(vertices.grad[0, :, :2], torch.zeros(100, 2), atol=1e-9)


def test_hidden_vertices_and_far_points_pull_nothing():
    """A vertex its view does not see, or whose nearest point is beyond the limit (a part the
    object hides), has no match and costs nothing."""
    vertices, normals, points = patch(0.02)
    visible = torch.ones(1, 1, 100, dtype=torch.bool)
    visible[0, 0, :50] = False
    valid = torch.ones(1, 1, 100, dtype=torch.bool)
    nearest = nearest_points(vertices, visible, points, valid, 0.10)
    assert (nearest[0, 0, :50] == -1).all() and (nearest[0, 0, 50:] >= 0).all()
    none = nearest_points(vertices, visible, points, valid, 0.01)  # every point 2 cm away
    assert (none == -1).all()
    assert float(visible_vertices_to_points(vertices, normals, points, none, scale=0.05)) == 0.0


def test_hand_contact_equals_its_definition_with_gradients():
    """E_C' picks its pairs without gradient: value and gradients must be those of the plain
    definition (the `count` hand vertices nearest to the graspable points, each to its nearest)."""
    g = torch.Generator().manual_seed(0)
    hand = (torch.randn(5, 60, 3, generator=g) * 0.05).requires_grad_(True)
    grasp = (torch.randn(5, 80, 3, generator=g) * 0.05 + 0.02).requires_grad_(True)
    grasping = torch.tensor([1.0, 0.0, 1.0, 1.0, 0.0])
    distance = torch.cdist(hand, grasp).min(-1).values
    plain = torch.topk(distance, 7, dim=-1, largest=False).values.pow(2).mean(-1) * grasping
    plain_grads = torch.autograd.grad(plain.sum(), (hand, grasp))
    fast = hand_contact(hand, grasp, grasping, 7)
    fast_grads = torch.autograd.grad(fast.sum(), (hand, grasp))
    assert torch.allclose(plain, fast, atol=1e-8)
    assert fast[1] == 0 and fast[0] > 0
    for a, b in zip(plain_grads, fast_grads):
        assert torch.allclose(a, b, atol=1e-7)
        assert (b != 0).sum() > 0
