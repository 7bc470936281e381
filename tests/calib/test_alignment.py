"""Calibration check (ICP between neighbouring cameras) on synthetic scenes with known truth."""
import numpy as np
from conftest import FLOOR_NORMAL, FLOOR_POINT, floor_basis

from intercap.calib import check_calibration, format_agreement, neighbour_pairs


def box_surface(rng, center, size, yaw, n, with_normals=False):
    """n points on the 5 visible faces (no bottom) of a box standing on z=0 (and their
    outward face normals)."""
    pts = rng.uniform(-0.5, 0.5, size=(n, 3)) * size
    face = rng.integers(0, 5, n)
    axis = np.array([0, 0, 1, 1, 2])[face]
    sign = np.array([-1, 1, -1, 1, 1])[face]
    pts[np.arange(n), axis] = sign * size[axis] / 2
    normals = np.zeros((n, 3))
    normals[np.arange(n), axis] = sign
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    pts = pts @ R.T + center + [0, 0, size[2] / 2]
    return (pts, normals @ R.T) if with_normals else pts


TWO_VIEW_CENTERS = np.array([[-2.0, 0.0, 1.5], [2.0, 0.0, 1.5]])


def two_view_scene(seed=0, noise=0.001):
    """A floor with four boxes, sampled twice independently, each time only the box faces turned
    to that view (a depth camera sees a surface from its own side); view a sees x < 0.5,
    view b sees x > -0.5, so they overlap in a 1 m band holding two boxes."""
    rng = np.random.default_rng(seed)
    boxes = [([-0.2, 0.3, 0], [0.5, 0.4, 0.6], 0.3), ([0.25, -0.4, 0], [0.4, 0.6, 0.4], -0.5),
             ([-1.0, -0.2, 0], [0.5, 0.5, 0.5], 0.1), ([1.0, 0.5, 0], [0.6, 0.4, 0.8], 0.8)]

    def sample(camera):
        parts = [np.column_stack([rng.uniform(-1.6, 1.6, 60000), rng.uniform(-1.2, 1.2, 60000), np.zeros(60000)])]
        for c, s, y in boxes:
            pts, n = box_surface(rng, np.array(c), np.array(s), y, 15000, with_normals=True)
            parts.append(pts[((camera - pts) * n).sum(axis=1) > 0])
        pts = np.concatenate(parts)
        return pts + rng.normal(0, noise, pts.shape)

    a, b = sample(TWO_VIEW_CENTERS[0]), sample(TWO_VIEW_CENTERS[1])
    return a[a[:, 0] < 0.5], b[b[:, 0] > -0.5]


def rotation(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    t = np.radians(deg)
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def test_check_calibration_aligned_and_drifted():
    a, b = two_view_scene()
    centers = TWO_VIEW_CENTERS
    good = check_calibration([a, b], ["left", "right"], centers)
    assert len(good) == 1 and (good[0].cam_a, good[0].cam_b) == ("left", "right")
    g = good[0]
    print(f"aligned: correction {g.correction_rotation_deg:.3f} deg {g.correction_translation_mm:.2f} mm, "
          f"median {g.median_distance_mm:.2f} mm, icp rmse {g.icp_rmse_mm:.2f} mm, overlap {g.overlap_points}")
    assert g.correction_translation_mm < 2.0 and g.correction_rotation_deg < 0.2
    assert g.overlap_points > 5000 and g.median_distance_mm < 1.5

    # drift view a by 1.5 deg about its overlap centre plus 20 mm
    centre = a[np.abs(a[:, 0]) < 0.5].mean(axis=0)
    R = rotation([0.3, 0.5, 0.8], 1.5)
    t = 0.020 * np.array([1.0, -1.0, 0.5]) / np.linalg.norm([1.0, -1.0, 0.5])
    drifted = (a - centre) @ R.T + centre + t
    bad = check_calibration([drifted, b], ["left", "right"], centers)[0]
    print(f"drifted 20 mm / 1.5 deg: correction {bad.correction_rotation_deg:.3f} deg "
          f"{bad.correction_translation_mm:.2f} mm, median {bad.median_distance_mm:.2f} mm, "
          f"icp rmse {bad.icp_rmse_mm:.2f} mm")
    # measured where the views overlap, not at the drift's pivot: the 1.5 deg turn moves it a few mm more
    assert abs(bad.correction_translation_mm - 20.0) < 4.0
    # the turn about the vertical shows only on box faces both views see (their sides along the
    # baseline, which do not hold it), so at least the tilt (0.88 deg, held by the floor) is found
    assert 0.8 < bad.correction_rotation_deg < 1.8 and bad.flagged
    # the correction undoes the drift where it is observed: the clouds agree to their noise again
    assert bad.icp_rmse_mm < 2.0 and g.icp_rmse_mm < 2.0
    table = format_agreement(good + [bad], warn_mm=10.0)
    print(table)
    lines = table.splitlines()
    assert lines[2].endswith("ok") and lines[3].endswith("CHECK CALIBRATION")


def test_check_calibration_reports_views_without_overlap():
    a, b = two_view_scene()
    far = b + [10.0, 0, 0]
    res = check_calibration([a, far], ["a", "b"], np.array([[0, 0, 0], [1.0, 0, 0]]))[0]
    assert res.overlap_points == 0 and np.isnan(res.median_distance_mm)
    assert "NO OVERLAP" in format_agreement([res])


def ring_centers(angles_deg, radius=3.0):
    """Camera centres on a tilted circle (the rig plane is not a world plane)."""
    e1, e2 = floor_basis(FLOOR_NORMAL)
    a = np.radians(angles_deg)
    return FLOOR_POINT + 1.5 * FLOOR_NORMAL + radius * (np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2)


def test_neighbour_pairs_ring_arc_and_pair():
    # camera indices do not follow ring order: positions at 0, 180, 90, 270 degrees
    pairs = neighbour_pairs(ring_centers([0, 180, 90, 270]))
    assert {frozenset(p) for p in pairs} == {frozenset(p) for p in [(0, 2), (2, 1), (1, 3), (3, 0)]}
    assert len(pairs) == 4
    for (a0, b0), (a1, _) in zip(pairs, pairs[1:] + pairs[:1]):
        assert b0 == a1  # ring order
    # six cameras in a 150 degree arc in front: a chain, no pair across the empty back
    arc = neighbour_pairs(ring_centers([60, 0, 30, 120, 150, 90]))
    assert {frozenset(p) for p in arc} == {frozenset(p) for p in [(1, 2), (2, 0), (0, 5), (5, 3), (3, 4)]}
    assert neighbour_pairs(ring_centers([0, 90])) == [(0, 1)]
    assert neighbour_pairs(ring_centers([0])) == []


def planar_room_views(seed=0, noise=0.010, n_box=6000):
    """Two views of a floor (z=0) and a wall (x=2) with a little clutter (one small
    box, ~5% of points), each sampled independently with `noise` along its viewing
    rays, as depth noise is: planes dominate the overlap."""
    rng = np.random.default_rng(seed)
    centers = np.array([[-1.5, -2.5, 1.8], [-1.5, 2.5, 1.8]])

    def sample(center):
        floor = np.column_stack([rng.uniform(-1.5, 2.0, 40000), rng.uniform(-2.0, 2.0, 40000), np.zeros(40000)])
        wall = np.column_stack([np.full(20000, 2.0), rng.uniform(-2.0, 2.0, 20000), rng.uniform(0.0, 2.5, 20000)])
        box = box_surface(rng, np.array([0.3, 0.0, 0.0]), np.array([0.4, 0.3, 0.5]), 0.4, n_box)
        to_centre = np.array([0.3, 0.0, 0.25])
        facing = ((box - to_centre) * (center - box)).sum(1) > 0  # roughly: the faces turned to this view
        pts = np.concatenate([floor, wall, box[facing]])
        rays = pts - center
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        return pts + rays * rng.normal(0, noise, (len(pts), 1))

    return [sample(c) for c in centers], centers


def test_check_calibration_planar_scene_exact_is_not_flagged():
    views, centers = planar_room_views()
    good = check_calibration(views, ["a", "b"], centers)[0]
    print(f"planar exact: observable {good.correction_translation_mm:.2f} mm {good.correction_rotation_deg:.3f} deg, "
          f"full 6-dof {good.full_translation_mm:.2f} mm {good.full_rotation_deg:.3f} deg, "
          f"median {good.median_distance_mm:.2f} mm, unobservable {good.unobservable}")
    assert good.correction_translation_mm < 5.0 and good.correction_rotation_deg < 0.3
    assert good.observable_translation_mm == good.correction_translation_mm
    assert "NO OVERLAP" not in format_agreement([good]) and format_agreement([good]).splitlines()[2].endswith("ok")
    # the floor's normal translation is always observable: a 20 mm drop of view a is found and flagged
    dropped = check_calibration([views[0] - [0, 0, 0.020], views[1]], ["a", "b"], centers)[0]
    print(f"planar, view a 20 mm low: {dropped.correction_translation_mm:.2f} mm {dropped.correction_rotation_deg:.3f} deg")
    assert abs(dropped.correction_translation_mm - 20.0) < 3.0 and dropped.correction_rotation_deg < 0.3
    assert abs(dropped.correction[2, 3] - 0.020) < 0.003
    assert format_agreement([dropped]).splitlines()[2].endswith("CHECK CALIBRATION")


def ring_scene_views(seed=0, frames=2, noise=0.002):
    """Four cameras on a ring (radius 3 m, 1.6 m high) looking at a floor with two boxes and a
    'person' (a vertical cylinder) at another place each frame. Each view samples, per frame,
    the surfaces turned towards it within 4.5 m, with noise along its rays."""
    rng = np.random.default_rng(seed)
    az = np.radians([45, 135, 225, 315])
    centers = np.column_stack([3 * np.cos(az), 3 * np.sin(az), np.full(4, 1.6)])
    boxes = [([-0.4, 0.5, 0], [0.5, 0.4, 0.6], 0.3), ([0.5, -0.3, 0], [0.4, 0.6, 0.4], -0.5)]

    def surfaces(person_xy):
        floor = np.column_stack([rng.uniform(-2.5, 2.5, (20000, 2)), np.zeros(20000)])
        parts, normals = [floor], [np.tile([0, 0, 1.0], (20000, 1))]
        for c, s, y in boxes:
            pts, n = box_surface(rng, np.array(c), np.array(s), y, 6000, with_normals=True)
            parts.append(pts), normals.append(n)
        t = rng.uniform(0, 2 * np.pi, 8000)
        radial = np.column_stack([np.cos(t), np.sin(t), np.zeros_like(t)])
        parts.append(np.column_stack([person_xy[0] + 0.15 * radial[:, 0], person_xy[1] + 0.15 * radial[:, 1],
                                      rng.uniform(0, 1.7, 8000)]))
        normals.append(radial)
        return np.concatenate(parts), np.concatenate(normals)

    views = [[] for _ in centers]
    for f in range(frames):
        person = rng.uniform(-0.8, 0.8, 2)
        for c, centre in enumerate(centers):
            pts, n = surfaces(person)
            ray = pts - centre
            dist = np.linalg.norm(ray, axis=1)
            seen = ((n * -ray).sum(1) > 0.1 * dist) & (dist < 4.5)
            ray = ray[seen] / dist[seen, None]
            views[c].append(pts[seen] + ray * rng.normal(0, noise, (int(seen.sum()), 1)))
    return views, centers


def test_ring_exact_not_flagged_drifted_camera_named():
    from intercap.calib.alignment import suspect_cameras

    views, centers = ring_scene_views()
    names = ["c0", "c1", "c2", "c3"]
    exact = check_calibration(views, names, centers)
    print(format_agreement(exact))
    assert len(exact) == 4 and not any(r.flagged for r in exact) and suspect_cameras(exact) == []
    assert all(r.correction_translation_mm < 3.0 for r in exact)
    # camera c2 moved by 10 mm and 0.5 deg (about the rig centre), as a drifted extrinsic would move its points
    R = rotation([0.2, -0.4, 0.9], 0.5)
    t = 0.010 * np.array([0.6, 0.8, 0.0])
    moved = [v if i != 2 else [f @ R.T + t for f in v] for i, v in enumerate(views)]
    drifted = check_calibration(moved, names, centers)
    print(format_agreement(drifted))
    flagged = {(r.cam_a, r.cam_b) for r in drifted if r.flagged}
    assert flagged == {("c1", "c2"), ("c2", "c3")}
    assert suspect_cameras(drifted) == ["c2"]


def test_two_sides_of_a_thin_part_are_not_matched():
    """Two cameras facing each other across a 3 cm board (an arm, a box wall seen from both
    sides): each sees only its own face. Those faces lie within the matching distance, but
    their normals face opposite ways, so they are not taken as one surface: no false alarm."""
    rng = np.random.default_rng(3)
    centers = np.array([[-2.5, 0.0, 1.5], [2.5, 0.0, 1.5]])

    def view(camera, side):
        floor = np.column_stack([rng.uniform(-1.5, 1.5, (30000, 2)), np.zeros(30000)])
        board = np.column_stack([np.full(20000, side * 0.015), rng.uniform(-0.6, 0.6, 20000),
                                 rng.uniform(0.0, 1.6, 20000)])
        box, n = box_surface(rng, np.array([0.0, 1.0, 0.0]), np.array([0.4, 0.4, 0.5]), 0.6, 8000, with_normals=True)
        pts = np.concatenate([floor, board, box[((camera - box) * n).sum(axis=1) > 0]])
        rays = (pts - camera) / np.linalg.norm(pts - camera, axis=1, keepdims=True)
        return pts + rays * rng.normal(0, 0.002, (len(pts), 1))

    result = check_calibration([view(centers[0], -1), view(centers[1], 1)], ["a", "b"], centers)[0]
    print(format_agreement([result]))
    assert result.overlap_points > 1000
    assert result.correction_translation_mm < 3.0 and result.correction_rotation_deg < 0.2 and not result.flagged


def test_sample_session_exact_not_flagged_and_a_bumped_camera_named():
    """The committed sample's rig as prepare checks it (3 frames: floor, walls, table, person):
    its exact calibration raises no flag, and camera 2 turned by 0.5 deg about its own centre
    and moved 10 mm (a bumped camera) is flagged in both its pairs and named alone."""
    from conftest import SAMPLE_SESSION

    from intercap.calib.alignment import suspect_cameras
    from intercap.config import PrepareConfig
    from intercap.stages.prepare.stage import check_views
    from tools.bench_calibration_check import drift_transform, load_views

    cfg = PrepareConfig()
    session, centers, per_view = load_views(SAMPLE_SESSION, cfg.calib_frames)
    names = [c.name for c in session.cameras]
    exact = check_views(per_view, names, centers, cfg)
    print(format_agreement(exact))
    assert not any(r.flagged for r in exact)
    assert max(r.correction_translation_mm for r in exact) < 5.0
    T = drift_transform(0.5, 10.0, seed=2, pivot=centers[2])
    moved = [v if c != 2 else [f @ T[:3, :3].T + T[:3, 3] for f in v] for c, v in enumerate(per_view)]
    drifted = check_views(moved, names, centers, cfg)
    print(format_agreement(drifted))
    assert {(r.cam_a, r.cam_b) for r in drifted if r.flagged} == {("cam1", "cam2"), ("cam2", "cam3")}
    assert suspect_cameras(drifted) == ["cam2"]


def test_refine_rig_brings_a_drifted_camera_back_and_leaves_an_exact_rig():
    """All four views' clouds aligned at once: camera c2 moved 10 mm and turned 0.5 deg puts the
    subject 20+ mm away from where the others put it (5+ mm on average over the four cameras);
    after refining, the cameras agree within a third of that. On the exact rig the corrections
    stay within 2 mm at the subject."""
    from intercap.calib.alignment import refine_rig
    from tools.bench_calibration_refine import subject_errors

    views, centers = ring_scene_views(frames=3)
    names = ["c0", "c1", "c2", "c3"]
    subject = np.array([0.0, 0.0, 0.8])
    exact = refine_rig(views, names, centers)
    assert exact.pairs == 12
    assert subject_errors(exact.corrections, subject)[0] < 2.0
    drift = np.eye(4)[None].repeat(4, axis=0)
    drift[2, :3, :3] = rotation([0.2, -0.4, 0.9], 0.5)
    drift[2, :3, 3] = centers[2] - drift[2, :3, :3] @ centers[2] + 0.010 * np.array([0.6, 0.8, 0.0])
    moved = [[f @ D[:3, :3].T + D[:3, 3] for f in v] for v, D in zip(views, drift)]
    result = refine_rig(moved, names, centers)
    before, after = subject_errors(drift, subject)[0], subject_errors(result.corrections @ drift, subject)[0]
    print(f"cameras apart at the subject: {before:.1f} -> {after:.1f} mm")
    assert before > 5.0 and after < before / 3
    assert result.residual_after_mm < result.residual_before_mm


def test_a_view_that_shares_only_part_of_the_person_is_not_judged(tmp_path):
    """The sample with camera 1 close in (its upper 150 rows: head to thighs, no floor): its pairs
    share a few patches of the person, too few clusters for the sandwich to be evidence, so the
    exact rig raises no flag and those pairs say they were not judged; the others are judged."""
    from conftest import SAMPLE_SESSION

    from intercap.calib.alignment import unchecked_cameras
    from intercap.config import PrepareConfig
    from intercap.stages.prepare.stage import check_views
    from intercap.synth.partial import crop_view
    from tools.bench_calibration_check import load_views

    cfg = PrepareConfig()
    session, centers, per_view = load_views(crop_view(SAMPLE_SESSION, tmp_path / "s", "cam1", (0, 0, 320, 150)),
                                            cfg.calib_frames)
    exact = check_views(per_view, [c.name for c in session.cameras], centers, cfg)
    print(format_agreement(exact))
    assert not any(r.flagged for r in exact)
    for r in exact:
        assert r.judged == ("cam1" not in (r.cam_a, r.cam_b)), (r.cam_a, r.cam_b, r.blocks)
    assert unchecked_cameras(exact) == ["cam1"]


def test_a_camera_whose_depth_meets_no_other_view_is_suspected():
    """A pose that puts a camera's depth where no neighbour's is (an inverted T_world_from_cam) is named;
    a camera merely without a judged pair, or a two-view rig without overlap, is not."""
    from types import SimpleNamespace

    from intercap.calib.alignment import isolated_cameras

    def pair(a, b, overlap):
        return SimpleNamespace(cam_a=a, cam_b=b, overlap_points=overlap)

    ring = [pair("cam3", "cam0", 21169), pair("cam0", "cam2", 0), pair("cam2", "cam1", 0)]
    assert isolated_cameras(ring) == ["cam2"]
    assert isolated_cameras([pair("cam0", "cam1", 500), pair("cam1", "cam2", 300), pair("cam2", "cam0", 40)]) == []
    assert isolated_cameras([pair("cam0", "cam1", 0)]) == []  # two views: nothing to tell which is off
    assert isolated_cameras([pair("cam0", "cam1", 0), pair("cam1", "cam2", 0)]) == []  # nothing overlaps at all


def test_a_view_cut_across_the_floor_is_not_flagged_and_a_bumped_camera_still_is(tmp_path):
    """The sample with camera 0 seeing only the right half of its image: its neighbours see floor beyond
    the cut, as beyond the shadow a table or a shelf casts, where camera 0 saw nothing. Matched to the last
    floor camera 0 saw, those points all lean outward, and the exact rig read cam3 -> cam0 as 154 mm off
    (flagged). Now no pair is flagged, while camera 2 bumped by 15 mm and 0.5 deg is flagged in both its
    pairs and named alone, and so is camera 0 itself, bumped."""
    from conftest import SAMPLE_SESSION

    from intercap.calib.alignment import suspect_cameras
    from intercap.config import PrepareConfig
    from intercap.stages.prepare.stage import check_views
    from intercap.synth.partial import crop_view
    from tools.bench_calibration_check import drift_transform, load_views

    cfg = PrepareConfig()
    cut = crop_view(SAMPLE_SESSION, tmp_path / "s", "cam0", (160, 0, 160, 288))
    session, centers, per_view = load_views(cut, cfg.calib_frames)
    names = [c.name for c in session.cameras]
    exact = check_views(per_view, names, centers, cfg)
    print(format_agreement(exact))
    assert not any(r.flagged for r in exact) and max(r.correction_translation_mm for r in exact) < 5.0
    bumps = ((2, 2, {("cam1", "cam2"), ("cam2", "cam3")}), (0, 5, {("cam0", "cam1"), ("cam3", "cam0")}))
    for camera, seed, pairs in bumps:
        T = drift_transform(0.5, 15.0, seed=seed, pivot=centers[camera])
        moved = [v if c != camera else [f @ T[:3, :3].T + T[:3, 3] for f in v] for c, v in enumerate(per_view)]
        drifted = check_views(moved, names, centers, cfg)
        print(format_agreement(drifted))
        assert {(r.cam_a, r.cam_b) for r in drifted if r.flagged} == pairs
        assert suspect_cameras(drifted) == [names[camera]]


def test_voxel_averages_of_a_surface_do_not_depend_on_what_else_the_view_holds():
    """Views average their points on one world grid: adding a far point (another view's cloud reaching
    lower) leaves every other average where it was. On grids from each cloud's own bounds, depth
    noise thicker than a voxel splits a floor into layers of averages whose heights differ between
    views, and an exact high-resolution pair read as several mm apart."""
    from intercap.calib.alignment import voxel_average

    rng = np.random.default_rng(3)
    floor = np.column_stack([rng.uniform(0, 1, 50000), rng.uniform(0, 1, 50000), rng.normal(0, 0.01, 50000)])
    alone = voxel_average(floor, 0.02)
    more = voxel_average(np.vstack([floor, [[-1.2345, -0.987, -0.0531]]]), 0.02)
    assert len(more) == len(alone) + 1
    assert np.allclose(np.sort(more[more[:, 0] >= 0], axis=0), np.sort(alone, axis=0))


def test_dense_noisy_views_of_an_exact_rig_agree():
    """Two exact views of a floor and boxes, densely sampled (as a 1920x1080 depth camera is) with
    10 mm of depth noise along each camera's rays: they match over most of their overlap, are not
    flagged, and the correction stays within 3 mm (on each cloud's own voxel grid: 7 mm and 2 deg,
    matched in a tenth of the overlap)."""
    a, b = two_view_scene(seed=4, noise=0.0)
    rng = np.random.default_rng(5)

    def dense(points, camera):
        p = np.repeat(points, 12, axis=0)
        ray = (p - camera) / np.linalg.norm(p - camera, axis=1, keepdims=True)
        return p + ray * rng.normal(0, 0.01, (len(p), 1))

    result = check_calibration([dense(a, TWO_VIEW_CENTERS[0]), dense(b, TWO_VIEW_CENTERS[1])], ["a", "b"],
                               TWO_VIEW_CENTERS)[0]
    print(format_agreement([result]))
    assert result.overlap_points > 10000
    assert not result.flagged
    assert result.correction_translation_mm < 3.0 and result.correction_rotation_deg < 0.2
