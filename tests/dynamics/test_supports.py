"""Fixed supports: body points on a mesh (reach, depth, normals), a still object, the joints carrying a
contact, and the contact solve with supports, grips and the joint-torque prior."""
import numpy as np
import trimesh

from intercap.dynamics import contact_forces as cf
from intercap.dynamics import supports as sup

UP = np.array([0.0, 0.0, 1.0])
W = 70 * 9.81


def seat_box():
    """A 0.4 m cube seat whose top is at z = 0.45."""
    return trimesh.creation.box(extents=(0.4, 0.4, 0.45), transform=trimesh.transformations.translation_matrix((0, 0, 0.225)))


def test_body_points_touch_a_seat_within_reach_and_depth():
    points = np.array([[[0.0, 0.0, 0.47],   # 2 cm above the top: touching
                        [0.0, 0.0, 0.60],   # 15 cm above: not
                        [0.05, 0.0, 0.42],  # 3 cm into the top (a soft seat): touching
                        [0.0, 0.0, 0.20],   # 20 cm deep inside: not (the fit is elsewhere)
                        [0.215, 0.0, 0.3]]])  # 1.5 cm off a side: touching, pushed sideways
    active, normals, which = sup.support_contacts([seat_box()], points, 0.03, 0.05)
    assert active[0].tolist() == [True, False, True, False, True]
    assert np.allclose(normals[0, [0, 2]], UP) and np.allclose(normals[0, 4], [1, 0, 0])
    assert which[0].tolist() == [0, -1, 0, -1, 0]
    reach = np.array([0.03, 0.2, 0.03, 0.03, 0.03])  # a reach per point
    assert sup.support_contacts([seat_box()], points, reach, 0.05)[0][0, 1]


def test_a_still_object_is_static_and_a_moved_one_is_not():
    rng = np.random.default_rng(0)
    T = 40
    R = np.tile(np.eye(3), (T, 1, 1))
    t = np.tile([1.0, 0.5, 0.2], (T, 1)) + rng.normal(0, 0.002, (T, 3))
    valid = np.ones(T, bool)
    assert sup.is_static(R, t, valid, 0.02, 5.0)
    moved = t.copy()
    moved[20:, 0] += 0.05
    assert not sup.is_static(R, moved, valid, 0.02, 5.0)
    turned = R.copy()
    a = np.radians(10)
    turned[20:] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    assert not sup.is_static(turned, t, valid, 0.02, 5.0)
    assert not sup.is_static(R, t, np.arange(T) < 10, 0.02, 5.0)  # tracked in a quarter of the frames


def test_a_joint_carries_the_contacts_below_it():
    parents = np.array([-1, 0, 1, 2, 0, 4])  # root -> hip -> knee -> foot, root -> spine -> arm
    carried = sup.carried_by(parents, np.array([2, 4]), np.array([3, 5, 1]))
    assert carried.tolist() == [[True, False, False], [False, True, False]]


def _hanging(grip):
    """A 70 kg body at rest whose needs are its weight, hands at 2 m, feet off the floor."""
    wrench = np.array([[0, 0, W, 0, 0, 0]], float)
    root = np.array([[0.0, 0.0, 1.0]])
    feet = np.zeros((1, 2, 2, 3))
    hands = np.array([[[0.0, 0.2, 2.0], [0.0, -0.2, 2.0]]])
    return cf.solve_contacts(wrench, root, feet, np.zeros((1, 2, 2), bool), UP, 0.5, hand_points=hands,
                             grip_active=np.array([[grip, grip]]))


def test_a_hanging_body_is_carried_by_its_grip():
    held = _hanging(True)
    assert np.linalg.norm(held.body_residual[0]) < 1.0
    assert np.allclose(held.hand_force[0].sum(0), [0, 0, -W], atol=1.0)  # the hands pull down on the bar
    assert np.allclose(held.hand_force[0, 0, 2], held.hand_force[0, 1, 2], rtol=0.01)
    free = _hanging(False)
    assert np.allclose(free.body_residual[0, :3], [0, 0, W])  # nothing holds it


def _seated(prior):
    """A still body whose weight acts at the root, over a seat (two points) and two feet (two points
    each, under the same vertical line): the root balance alone cannot tell them apart."""
    wrench = np.array([[0, 0, W, 0, 0, 0]], float)
    root = np.array([[0.0, 0.0, 0.5]])
    feet = np.array([[[[0.1, 0.1, 0.0], [0.1, -0.1, 0.0]], [[-0.1, 0.1, 0.0], [-0.1, -0.1, 0.0]]]])
    seat = np.array([[[0.1, 0.0, 0.45], [-0.1, 0.0, 0.45]]])
    knee = cf.TorquePrior(np.array([[[0.3, 0.0, 0.25]]]), np.zeros((1, 1, 3)), np.zeros((1, 2), bool),
                          np.ones((1, 4), bool), np.zeros((1, 2), bool), weight=1e-2)  # carries the feet only
    return cf.solve_contacts(wrench, root, feet, np.ones((1, 2, 2), bool), UP, 0.5, support_points=seat,
                             support_normals=np.tile(UP, (1, 2, 1)), support_active=np.ones((1, 2), bool),
                             torque_prior=knee if prior else None)


def test_the_torque_prior_puts_a_seated_weight_through_the_seat():
    plain, effort = _seated(False), _seated(True)
    for sol in (plain, effort):
        assert np.linalg.norm(sol.body_residual[0]) < 0.02 * W
        total = sol.support_point_force[0].sum(0) + sol.foot_point_force[0].sum((0, 1))
        assert np.allclose(total, [0, 0, W], atol=0.02 * W)
    seat_plain = plain.support_point_force[0, :, 2].sum() / W
    seat_effort = effort.support_point_force[0, :, 2].sum() / W
    assert 0.2 < seat_plain < 0.8  # shared by the regulariser alone
    assert seat_effort > 0.95  # pushing through the feet would load the knee


def test_pyramids_of_many_normals_are_each_normals_pyramid():
    rng = np.random.default_rng(1)
    normals = rng.normal(size=(5, 7, 3))
    normals[0, 0], normals[0, 1], normals[1, 2] = np.nan, 0.0, [0.95, 0.1, 0.1]  # unusable; x-most normal
    many = cf.friction_pyramids(normals, 0.5, 6)
    assert many.shape == (5, 7, 3, 6)
    assert np.all(many[0, :2] == 0)
    for i, j in [(1, 2), (2, 3), (4, 6)]:  # every edge on the cone round its own normal
        n = normals[i, j] / np.linalg.norm(normals[i, j])
        fn = many[i, j].T @ n
        ft = np.linalg.norm(many[i, j].T - fn[:, None] * n, axis=1)
        assert np.allclose(fn, 1.0) and np.allclose(ft, 0.5)
