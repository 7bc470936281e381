"""Contact forces: friction pyramids, and a friction demand above mu N leaves a residual."""
import numpy as np
import pytest

from intercap.dynamics import contact_forces as cf

UP = np.array([0.0, 0.0, 1.0])


def test_pyramid_edges_lie_on_the_cone():
    D = cf.friction_pyramid(UP, 0.5, 4)
    fn = D.T @ UP
    ft = np.linalg.norm(D.T - fn[:, None] * UP, axis=1)
    assert np.allclose(ft, 0.5 * fn)
    assert not cf.cone_violation(D.T * 100, UP, 0.5).any()
    assert cf.cone_violation(np.array([[60.0, 0, 100.0], [0, 0, -50.0]]), UP, 0.5).all()


def sliding_block(a_horizontal, mu=0.5, m=70.0, h=0.3, T=3):
    """A block whose COM (h above the floor) accelerates horizontally, standing on four sole points
    (+-0.5 m); its needed wrench about the COM."""
    g = np.array([0, 0, -9.81])
    F = m * (np.array([a_horizontal, 0, 0]) - g)
    root = np.tile([0.0, 0.0, h], (T, 1))
    wrench = np.tile(np.r_[F, 0, 0, 0], (T, 1))
    corners = np.array([[0.5, 0.2, 0], [0.5, -0.2, 0], [-0.5, 0.2, 0], [-0.5, -0.2, 0]])
    feet = np.tile(corners.reshape(1, 2, 2, 3), (T, 1, 1, 1))
    active = np.ones((T, 2, 2), bool)
    return cf.solve_contacts(wrench, root, feet, active, UP, mu), m


@pytest.mark.parametrize("a", [0.0, 3.0, 4.5])
def test_friction_demand_within_the_cone_is_explained(a):
    sol, m = sliding_block(a)
    assert np.abs(sol.body_residual[:, :3]).max() < 0.01 * m * 9.81
    assert np.abs(sol.body_residual[:, 3:]).max() < 1.0
    total = sol.foot_point_force.sum((1, 2))
    assert np.allclose(total, [m * a, 0, m * 9.81], rtol=0.01, atol=1.0)
    assert np.isnan(sol.object_residual).all()  # no object in this problem


@pytest.mark.parametrize("a", [6.0, 9.0])
def test_friction_demand_above_mu_leaves_a_residual(a):
    sol, m = sliding_block(a)
    # the floor gives at most mu N sideways: the residual is the demand's distance to the cone
    expected = m * (a - 0.5 * 9.81) / np.sqrt(1 + 0.5**2)
    assert np.linalg.norm(sol.body_residual[:, :3], axis=1) == pytest.approx(np.full(3, expected), rel=0.02)
    total = sol.foot_point_force.sum((1, 2))
    assert np.allclose(total[:, 0], 0.5 * total[:, 2], rtol=0.01)


def test_unconstrained_solve_counts_the_violation():
    g = 9.81
    wrench = np.array([[70 * 6.0, 0, 70 * g, 0, 0, 0]])
    feet = np.array([[0.5, 0.2, 0], [0.5, -0.2, 0], [-0.5, 0.2, 0], [-0.5, -0.2, 0]]).reshape(1, 2, 2, 3)
    free = cf.unconstrained_feet(wrench, np.array([[0, 0, 0.3]]), feet, np.ones((1, 2, 2), bool))
    assert np.allclose(free.sum((1, 2))[0], wrench[0, :3], rtol=1e-3)
    assert cf.cone_violation(free.sum((1, 2)), UP, 0.5).all()
    assert not cf.cone_violation(free.sum((1, 2)), UP, 0.9).any()
