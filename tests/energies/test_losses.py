"""E_D (its model-to-data half: every visible vertex is pulled onto the nearest segmented point) and E_C'."""
import numpy as np
import torch

from intercap.energies.losses import depth_pairs, depth_point_to_plane, hand_contact, nearest_points


def patch(offset_m: float):
    """A 10 x 10 vertex grid in z = 0 (normals +z) and the same grid of points `offset_m` above it."""
    xy = np.stack(np.meshgrid(np.linspace(0, 0.3, 10), np.linspace(0, 0.3, 10)), -1).reshape(-1, 2)
    vertices = torch.tensor(np.concatenate([xy, np.zeros((100, 1))], 1), dtype=torch.float32)[None]  # (1, 100, 3)
    points = vertices.clone()
    points[..., 2] += offset_m
    normals = torch.zeros_like(vertices)
    normals[..., 2] = 1.0
    return vertices, normals, points[:, None]  # points (1, C=1, 100, 3)


def model_to_data(vertices, normals, points, nearest):
    """E_D's model-to-data half alone, through `DepthPairs` (no data-to-model pairs)."""
    no_points = torch.zeros(points.shape[:3], dtype=torch.bool)
    pairs = depth_pairs(points, no_points, normals, torch.full(no_points.shape, -1), nearest)
    return depth_point_to_plane(vertices, pairs, scale=0.05)


def test_visible_vertices_are_pulled_onto_their_points():
    vertices, normals, points = patch(0.02)
    visible = torch.ones(1, 1, 100, dtype=torch.bool)
    nearest = nearest_points(vertices, visible, points, torch.ones(1, 1, 100, dtype=torch.bool), 0.10)
    assert (nearest[0, 0] == torch.arange(100)).all()  # each vertex's own point, straight above it
    vertices.requires_grad_(True)
    energy = model_to_data(vertices, normals, points, nearest)
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
    assert float(model_to_data(vertices, normals, points, none)) == 0.0


def test_depth_pairs_give_the_dense_definition_of_e_d():
    """E_D over the flat pairs equals its definition written densely over every (frame, view,
    point) and (frame, view, vertex), masked: per view the robust mean of each half, the
    model-to-data half weighted; values and gradients, with a view that has no pairs at all."""
    g = torch.Generator().manual_seed(1)
    B, C, P, N, scale, tangent_weight, half_weight = 3, 2, 30, 40, 0.05, 0.25, 0.7
    vertices = (torch.randn(B, N, 3, generator=g) * 0.1).requires_grad_(True)
    normals = torch.nn.functional.normalize(torch.randn(B, N, 3, generator=g), dim=-1)
    points = torch.randn(B, C, P, 3, generator=g) * 0.1
    valid = torch.rand(B, C, P, generator=g) > 0.2
    nearest = torch.randint(-1, N, (B, C, P), generator=g)
    to_points = torch.randint(-1, P, (B, C, N), generator=g)
    valid[1, 0], nearest[2, 1], to_points[0, 1] = False, -1, -1  # views without pairs

    def robust_mean(offset, n, usable):  # (B, C, M, 3) offsets -> (B,)
        along = (offset * n).sum(-1, keepdim=True)
        tangent = offset - along * n
        squared = along[..., 0] ** 2 + tangent_weight * (tangent * tangent).sum(-1)
        rho = squared / (squared + scale**2) * usable
        return rho.sum(-1).div(usable.sum(-1).clamp(min=1)).sum(-1) * scale**2

    index = nearest.clamp(min=0).flatten(1)[..., None].expand(-1, -1, 3)
    data_to_model = robust_mean(points - vertices.gather(1, index).view(points.shape),
                                normals.gather(1, index).view(points.shape), valid & (nearest >= 0))
    matched = torch.gather(points, 2, to_points.clamp(min=0)[..., None].expand(B, C, N, 3))
    dense = data_to_model + half_weight * robust_mean(matched - vertices[:, None], normals[:, None], to_points >= 0)
    dense_grad, = torch.autograd.grad(dense.sum(), vertices)

    for compact in (True, False):  # the pairs that exist (the CPU's), or a slot per point and vertex (a GPU's)
        pairs = depth_pairs(points, valid, normals, nearest, to_points, half_weight, compact=compact)
        used = int((valid & (nearest >= 0)).sum() + (to_points >= 0).sum())
        assert len(pairs.vertex) == (used if compact else B * C * (P + N)) and int((pairs.weight > 0).sum()) == used
        flat = depth_point_to_plane(vertices, pairs, scale, tangent_weight)
        flat_grad, = torch.autograd.grad(flat.sum(), vertices)
        assert torch.allclose(flat, dense, rtol=1e-5, atol=1e-9)
        assert torch.allclose(flat_grad, dense_grad, rtol=1e-4, atol=1e-7)
    # a refresh taken in place (what a recorded CUDA graph reads) gives the new pairs' energy
    others = depth_pairs(points, valid, normals, nearest.roll(1, 2), to_points.roll(1, 2), half_weight, compact=False)
    assert pairs.refreshed(others, in_place=False) is others
    assert pairs.refreshed(others, in_place=True) is pairs
    assert torch.equal(depth_point_to_plane(vertices, pairs, scale), depth_point_to_plane(vertices, others, scale))
    assert not torch.allclose(depth_point_to_plane(vertices, others, scale), dense)


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


def test_dense_nearest_search_finds_what_the_trees_find():
    """A GPU's correspondence search (the dense distance matrix, in chunks of frames) returns the
    k-d trees' indices: masked queries and targets, a view with no target, the distance bound."""
    from intercap.energies.losses import nearest_dense, nearest_per_view

    g = torch.Generator().manual_seed(4)
    B, C, Q, T = 5, 3, 60, 45
    queries, targets = torch.rand(B, C, Q, 3, generator=g), torch.rand(B, C, T, 3, generator=g)
    query_mask, target_mask = torch.rand(B, C, Q, generator=g) > 0.2, torch.rand(B, C, T, generator=g) > 0.3
    target_mask[1, 2] = False  # this view has no target
    for bound in (np.inf, 0.08):
        trees = nearest_per_view(queries, query_mask, targets, target_mask, bound)
        dense = nearest_dense(queries, query_mask, targets, target_mask, bound, max_entries=2 * C * Q * T)
        assert (trees == dense).all()
        assert (dense[1, 2] == -1).all() and (dense[~query_mask] == -1).all()
    assert ((trees >= 0).sum() > 0) and ((trees == -1) & query_mask).sum() > 0  # the bound bites, not everywhere


def test_rotation_6d_to_matrix_is_romas_gram_schmidt_with_its_gradients():
    """The written-out backward (`losses._GramSchmidt`) gives roma's matrices and the
    gradients of autograd's chain; the input may be moved in place before the backward pass, as
    the object fits move their poses (the backward reads only what the forward made)."""
    import roma

    from intercap.energies.losses import rotation_6d_to_matrix

    g = torch.Generator().manual_seed(3)
    r6 = torch.randn(4, 2, 6, generator=g, dtype=torch.float64)
    weights = torch.randn(4, 2, 3, 3, generator=g, dtype=torch.float64)
    ours, theirs = r6.clone().requires_grad_(True), r6.clone().requires_grad_(True)
    R = rotation_6d_to_matrix(ours)
    R_roma = roma.special_gramschmidt(torch.stack([theirs[..., :3], theirs[..., 3:]], -1))
    assert torch.allclose(R, R_roma, rtol=0, atol=1e-15)  # the same steps (rounding may differ by layout)
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(4, 2, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(4, 2, dtype=torch.float64))
    with torch.no_grad():
        ours[0] += 1.0  # moved in place after the forward pass
    (R * weights).sum().backward()
    (R_roma * weights).sum().backward()
    assert torch.allclose(ours.grad, theirs.grad, atol=1e-12)
    assert torch.autograd.gradcheck(rotation_6d_to_matrix, (r6[0].clone().requires_grad_(True),))
