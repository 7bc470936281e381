"""Do exact views overlap? Direct point-to-surface distances, no ICP.

With a session's own calibration, back-projects every view and measures
(1) each view's floor and wall points against the generator's true planes
(signed, mm; z = 0 floor, walls at ring_radius + 1.3 - 0.025), by range; and
(2) for each neighbouring pair and frame, view a's points against view b's
local tangent planes, per surface class (person, object, static), and the
6-dof linearised correction those residuals imply (one Gauss-Newton step).

    python -m tools.diag_calibration_overlap SESSION [--frames 3] [--stride 2]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree


def view_points(session, cameras, c, frame_id, stride):
    from intercap.geometry.cameras import depth_to_point_grid

    depth = session.read_depth(c, frame_id)
    pts, valid = depth_to_point_grid(torch.from_numpy(depth)[None].double(), cameras.select([c]), stride, 0.2, 8.0)
    valid = valid[0].numpy()
    cls = np.zeros(valid.shape, int)  # 0 static, 1 person, 2 object
    for k, kind in ((1, "person"), (2, "object")):
        m = session.read_mask(c, frame_id, kind)
        if m is not None:
            cls[m[::stride, ::stride].reshape(-1)] = k
    return pts[0].numpy()[valid], cls[valid]


def main(argv=None) -> None:
    from intercap.calib.alignment import local_planes, neighbour_pairs
    from intercap.geometry.cameras import Cameras
    from intercap.session import Session
    from intercap.stages.prepare.stage import spread_frames

    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("session", type=Path)
    p.add_argument("--frames", type=int, default=3)
    p.add_argument("--stride", type=int, default=2)
    args = p.parse_args(argv)
    session = Session.load(args.session)
    cameras = Cameras.from_infos(session.cameras, dtype=torch.float64)
    info = json.loads((args.session / "ground_truth" / "info.json").read_text())["config"]
    wall = info["ring_radius"] + 1.3 - 0.025
    centers = cameras.centers.numpy()
    frames = spread_frames(session.frame_ids, args.frames)
    print(f"{args.session}: clean_depth={info['clean_depth']} ring {info['ring_radius']} m / {info['ring_height']} m")
    views = {(c, int(f)): view_points(session, cameras, c, int(f), args.stride)
             for c in range(len(session.cameras)) for f in frames}
    print("(1) against the true planes: signed mm, median [mean] by range from the camera")
    for c in range(len(session.cameras)):
        pts = np.concatenate([views[c, int(f)][0] for f in frames])
        cls = np.concatenate([views[c, int(f)][1] for f in frames])
        rng = np.linalg.norm(pts - centers[c], axis=1)
        floor = (cls == 0) & (np.abs(pts[:, 2]) < 0.1) & (pts[:, 1] < wall - 0.2) & (pts[:, 0] > -wall + 0.2)
        wy = (cls == 0) & (np.abs(pts[:, 1] - wall) < 0.1) & (pts[:, 2] > 0.2)
        row = []
        for lo, hi in ((0, 3), (3, 4), (4, 9)):
            sel = floor & (rng >= lo) & (rng < hi)
            if sel.sum() > 20:
                z = pts[sel, 2] * 1000
                row.append(f"floor {lo}-{hi} m: {np.median(z):+.2f} [{z.mean():+.2f}] n={sel.sum()}")
        if wy.sum() > 20:
            d = (pts[wy, 1] - wall) * 1000
            row.append(f"wall y: {np.median(d):+.2f} [{d.mean():+.2f}]")
        print(f"  {session.cameras[c].name}: " + "; ".join(row))
    print("(2) view a against view b's tangent planes (same frame), signed mm: median [mean] per class")
    for a, b in neighbour_pairs(centers):
        rows, Js, rs = [], [], []
        for f in frames:
            pa, ca = views[a, int(f)]
            pb, _ = views[b, int(f)]
            qb, nb, ok = local_planes(pb, 0.03)
            tree = cKDTree(qb[ok])
            d, i = tree.query(pa, distance_upper_bound=0.03)
            hit = np.isfinite(d)
            r = ((pa[hit] - qb[ok][i[hit]]) * nb[ok][i[hit]]).sum(1)
            rows.append((r, ca[hit]))
            Js.append(np.hstack([np.cross(pa[hit], nb[ok][i[hit]]), nb[ok][i[hit]]]))
            rs.append(r)
        r = np.concatenate([x[0] for x in rows])
        cl = np.concatenate([x[1] for x in rows])
        text = []
        for k, name in enumerate(("static", "person", "object")):
            s = (cl == k) & (np.abs(r) < 0.03)
            if s.sum() > 20:
                text.append(f"{name} {np.median(r[s]) * 1000:+.2f} [{r[s].mean() * 1000:+.2f}] n={s.sum()}")
        J, rr = np.concatenate(Js), np.concatenate(rs)
        s = np.abs(rr) < 0.03
        x = -np.linalg.lstsq(J[s], rr[s], rcond=None)[0]
        text.append(f"implied 6-dof step: rot {np.degrees(np.linalg.norm(x[:3])):.3f} deg, "
                    f"trans(origin) {np.linalg.norm(x[3:]) * 1000:.1f} mm")
        print(f"  {session.cameras[a].name}->{session.cameras[b].name}: " + "; ".join(text))


if __name__ == "__main__":
    main()
