"""Where a fit's overlay silhouette IoU with the session's masks is lost.

For each stage result (body, global) of OUT, and the ground truth of a synthetic session:
rendered silhouettes (the report's renderer: calibration, lens distortion, mutual occlusion
of body and object) against the session's person / object masks, pooled and per view and
frame; then the body's lost pixels attributed to body parts: a pixel of the mask that the fit
misses belongs to the ground-truth part rendered there, a pixel the fit covers outside the mask
to the fitted part there. Also how far the lost pixels lie from the mask's border (a thin rim of
lost pixels all around is a sub-pixel / millimetre boundary error, lost blobs are pose errors)
and, the topology being the ground truth's, the per-part vertex error in 3D.

    OMP_NUM_THREADS=1 python -m tools.bench_overlay_iou OUT [--session S] [--stages body,global] [--every 1]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

PARTS = ("head and neck", "torso", "upper arms", "forearms", "hands", "thighs", "lower legs", "feet")
OBJECT_LABEL = 250


def part_of(bone: str) -> str:
    """Coarse body part of an anny bone label."""
    from intercap.body_models.anny_backend import is_hand_bone

    b = bone.lower()
    if is_hand_bone(b) or b.startswith("wrist"):
        return "hands"
    for prefix, part in (("lowerarm", "forearms"), (("upperarm", "shoulder", "clavicle"), "upper arms"),
                         (("foot", "toe"), "feet"), ("lowerleg", "lower legs"), ("upperleg", "thighs"),
                         (("spine", "pelvis", "root", "breast"), "torso")):
        if b.startswith(prefix):
            return part
    return "head and neck"


def vertex_parts(num_vertices: int) -> np.ndarray:
    """(V,) part index of each anny vertex: the part of its most weighted bone."""
    from intercap.body_models.anny_backend import build_anny

    core = build_anny(None, "lbs")
    ids = core.vertex_bone_indices.long().numpy()
    w = core.vertex_bone_weights.double().numpy()
    dominant = ids[np.arange(len(ids)), w.argmax(1)]
    if len(dominant) != num_vertices:
        raise SystemExit(f"the body has {num_vertices} vertices, anny {len(dominant)}: not an anny mesh")
    lookup = np.array([PARTS.index(part_of(b)) for b in core.bone_labels])
    return lookup[dominant]


def label_image(renderer, view: int, vertices, faces, face_part, object_pose) -> np.ndarray:
    """(H, W) uint8: 1 + part index where a body part is visible, OBJECT_LABEL on the object, 0 else."""
    pr = renderer.pr
    renderer.set_frame(None, None, None, object_pose)
    nodes = []
    v = np.asarray(vertices, np.float32)
    for k in range(len(PARTS)):
        f = faces[face_part == k]
        if len(f):
            nodes.append((k, renderer.scene.add(pr.Mesh([pr.Primitive(positions=v, indices=f)]))))
    try:
        renderer.render(view, silhouettes=False)  # sets the camera and viewport
        seg_map = {n: (0, 0, 0) for n in renderer.scene.mesh_nodes}
        for k, node in nodes:
            seg_map[node] = (k + 1, 0, 0)
        if renderer.object_node is not None:
            seg_map[renderer.object_node] = (OBJECT_LABEL, 0, 0)
        seg, _ = renderer.renderer.render(renderer.scene, flags=pr.RenderFlags.SEG, seg_node_map=seg_map)
    finally:
        for _, node in nodes:
            renderer.scene.remove_node(node)
    mx, my = renderer.maps[view]
    return cv2.remap(seg[..., 0], mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def pose(R, t, i):
    if R is None or not (np.isfinite(R[i]).all() and np.isfinite(t[i]).all()):
        return None
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R[i], t[i]
    return T


def analyse(session, renderer, name, V, F, R, t, gt, face_part, frames) -> None:
    """Print the breakdown of one result (V (T, N, 3) body, R, t object poses) against the masks."""
    P = len(PARTS)
    C = session.num_cameras
    inter = np.zeros((len(frames), C))
    union = np.zeros((len(frames), C))
    oi = ou = 0
    missed, extra = np.zeros(P + 1), np.zeros(P + 1)  # last: pixels the fit's object covers / no GT part
    part_i, part_u = np.zeros(P), np.zeros(P)
    rim = np.zeros(4)  # lost pixels within 1, 2, 3 px of the mask border, all
    for k, i in enumerate(frames):
        fid = int(session.frame_ids[i])
        for c in range(C):
            person = session.read_mask(c, fid, "person")
            thing = session.read_mask(c, fid, "object")
            fit = label_image(renderer, c, V[i], F, face_part, pose(R, t, i))
            ref = label_image(renderer, c, gt.body_vertices[i], F, face_part, pose(gt.object_R, gt.object_t, i))
            body = (fit > 0) & (fit <= P)
            inter[k, c], union[k, c] = np.count_nonzero(body & person), np.count_nonzero(body | person)
            if thing is not None and thing.sum() >= 20:
                oi += np.count_nonzero((fit == OBJECT_LABEL) & thing)
                ou += np.count_nonzero((fit == OBJECT_LABEL) | thing)
            lost_in = person & ~body
            lost_out = body & ~person
            lab_in = ref[lost_in].astype(int)
            lab_in = np.where((lab_in > 0) & (lab_in <= P), lab_in - 1, P)
            missed += np.bincount(lab_in, minlength=P + 1)
            extra += np.bincount(fit[lost_out].astype(int) - 1, minlength=P + 1)[:P + 1]
            for p in range(P):
                a, b = ref == p + 1, fit == p + 1
                part_i[p] += np.count_nonzero(a & b)
                part_u[p] += np.count_nonzero(a | b)
            u8 = person.astype(np.uint8)
            # pixels from the mask's border: inside, to the nearest outside pixel (1 next to it), and vice versa
            dist = np.where(person, cv2.distanceTransform(u8, cv2.DIST_L2, 5),
                            cv2.distanceTransform(1 - u8, cv2.DIST_L2, 5))
            d = dist[lost_in | lost_out]
            rim += [np.count_nonzero(d <= r + 0.01) for r in (1, 2, 3)] + [len(d)]
    total_u = union.sum()
    iou = inter.sum() / total_u
    print(f"\n== {name}: body IoU {iou:.4f}, object IoU {oi / max(ou, 1):.4f} "
          f"({len(frames)} frames x {C} views, pooled)")
    print("  per view: " + ", ".join(f"{session.cameras[c].name} {inter[:, c].sum() / union[:, c].sum():.3f}"
                                     for c in range(C)))
    per_frame = inter.sum(1) / union.sum(1)
    worst = np.argsort(per_frame)[:5]
    print("  per frame: min {:.3f} max {:.3f}; worst ".format(per_frame.min(), per_frame.max())
          + ", ".join(f"{int(session.frame_ids[frames[j]])}: {per_frame[j]:.3f}" for j in worst))
    lost = missed.sum() + extra.sum()
    if lost == 0:
        print("  no pixel lost")
        return
    print(f"  lost pixels: {lost / total_u:.1%} of the union; mask pixels the fit misses {missed.sum() / lost:.0%}, "
          f"fit pixels outside the mask {extra.sum() / lost:.0%}")
    print(f"  lost pixels within 1 / 2 / 3 px of the mask border: {rim[0] / rim[3]:.0%} / {rim[1] / rim[3]:.0%} / "
          f"{rim[2] / rim[3]:.0%}")
    print("  part            IoU   missed  extra  (share of 1 - IoU lost there)")
    for p, part in enumerate(PARTS):
        print(f"  {part:14s} {part_i[p] / max(part_u[p], 1):.3f}  {missed[p] / total_u:6.2%} {extra[p] / total_u:6.2%}")
    print(f"  {'(object/none)':14s}   -    {missed[P] / total_u:6.2%}")


def vertex_errors(name, V, gt, parts, frames) -> None:
    """Per part mean vertex distance (mm) of the fit to the ground truth, and the mean offset."""
    err = np.linalg.norm(np.asarray(V[frames], float) - gt.body_vertices[frames], axis=-1)  # (F, N)
    offset = (np.asarray(V[frames], float) - gt.body_vertices[frames]).mean(1)  # (F, 3)
    print(f"  3D vertex error vs ground truth ({name}): mean {1000 * np.nanmean(err):.1f} mm; mean offset "
          f"{np.round(1000 * np.nanmean(offset, 0), 1)} mm; per part "
          + ", ".join(f"{part} {1000 * np.nanmean(err[:, parts == p]):.1f}" for p, part in enumerate(PARTS)))


def main() -> None:
    from intercap.evaluation.overlays import OverlayRenderer, load_stage_meshes
    from intercap.session import Session

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("out")
    parser.add_argument("--session", default=str(Path(__file__).resolve().parents[1] / "data_samples" / "sample"))
    parser.add_argument("--stages", default="body,global")
    parser.add_argument("--every", type=int, default=1, help="every n-th frame")
    args = parser.parse_args()
    session = Session.load(args.session)
    gt = session.ground_truth()
    if gt is None:
        raise SystemExit(f"{args.session}: no ground_truth/ (the breakdown compares with it)")
    out = Path(args.out)
    frames = np.arange(0, session.num_frames, args.every)
    F = np.asarray(gt.body_faces, np.int64)
    parts = vertex_parts(gt.body_vertices.shape[1])
    face_part = parts[F[:, 0]]
    print("vertices per part: " + ", ".join(f"{p} {np.count_nonzero(parts == k)}" for k, p in enumerate(PARTS)))
    renderer = OverlayRenderer(session.cameras, session.object.load_mesh() if session.object else None)
    obj = load_stage_meshes(out, "object")
    try:
        analyse(session, renderer, "ground truth", gt.body_vertices, F, gt.object_R, gt.object_t, gt, face_part,
                frames)
        for stage in args.stages.split(","):
            m = load_stage_meshes(out, stage)
            if m is None or m.body_vertices is None:
                print(f"\n== {stage}: not run")
                continue
            R, t = (m.object_R, m.object_t) if m.object_R is not None else (
                (obj.object_R, obj.object_t) if obj is not None else (None, None))
            V = np.asarray(m.body_vertices)
            analyse(session, renderer, stage, V, F, R, t, gt, face_part, frames)
            vertex_errors(stage, V, gt, parts, frames)
    finally:
        renderer.close()


if __name__ == "__main__":
    main()
