"""Stage 1, `prepare`: world point clouds, the ground plane, the calibration check.

Depth of every view is back-projected with its calibration (distortion
included) into one world frame. The ground plane comes from session.yaml when
given, else from RANSAC on clouds fused over a few frames spread through the
sequence, with its up side chosen where the person stands. The calibration
check registers each camera's cloud onto its neighbour's (ICP) on a few frames
and reports how far they disagree, because calibration drift is the first
thing that goes wrong on real rigs.

Writes OUT/prepare/: ground.json, calibration_check.json, clouds/*.ply (fused,
coloured clouds of the checked frames, for a person to open).
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from intercap.calib.alignment import (
    check_calibration,
    format_agreement,
    isolated_cameras,
    refine_rig,
    suspect_cameras,
    unchecked_cameras,
)
from intercap.config import Config
from intercap.geometry.cameras import Cameras, depth_to_point_grid, pixel_rays
from intercap.geometry.ground import GroundPlane, fit_ground_plane, up_hint_from_cameras
from intercap.geometry.pointclouds import fuse_points
from intercap.io.files import write_json, write_point_cloud_ply
from intercap.io.importing import camera_entry
from intercap.session.session import REFINED_CALIBRATION

log = logging.getLogger(__name__)

# What happens when no floor is found (then no ground.json is written, ground_unavailable.json says why).
GRAVITY_FALLBACK = "gravity from the tracked object's free flight (global stage: OUT/global/gravity.json)"


def spread_frames(frame_ids: np.ndarray, count: int) -> np.ndarray:
    """`count` frame ids evenly spread over the sequence (all when fewer)."""
    if len(frame_ids) <= count:
        return np.asarray(frame_ids)
    return np.asarray(frame_ids)[np.round(np.linspace(0, len(frame_ids) - 1, count)).astype(int)]


def checkable_frames(session, count: int) -> np.ndarray:
    """`count` frame ids spread over the frames every view has depth of (when at least `count` have;
    else over those the most views have, at least two): a pair whose view dropped some of the checked
    frames would be judged on fewer frames than the rest, where ICP walks off on an exact rig. All
    frames when every view has them all (the frames `spread_frames` picks)."""
    frame_ids = np.asarray(session.frame_ids)
    views = session.availability()["depth"].sum(axis=0)  # (T,) views with depth, per frame
    for least in range(int(views.max(initial=0)), 1, -1):
        if (views >= least).sum() >= count:
            return spread_frames(frame_ids[views >= least], count)
    return spread_frames(frame_ids[views >= 2] if (views >= 2).any() else frame_ids, count)


class ViewClouds:
    """World point clouds of one frame's views, with each camera's undistorted
    pixel rays computed once per run (undistortion is the costly part)."""

    def __init__(self, session, cameras: Cameras, cfg):
        self.session, self.cameras, self.cfg = session, cameras, cfg
        self._rays: dict[int, torch.Tensor] = {}

    def rays(self, c: int) -> torch.Tensor:
        if c not in self._rays:
            info = self.session.cameras[c]
            self._rays[c] = pixel_rays(self.cameras.select([c]), info.height, info.width, self.cfg.pixel_stride)
        return self._rays[c]

    def frame(self, frame_id: int) -> list[dict]:
        """Per view: world points (N, 3), colours (N, 3) uint8 and person flags (N,).

        A dropped view gives empty arrays. Views may differ in resolution, so
        this loops over the few cameras, each vectorised over its pixels."""
        cfg, stride = self.cfg, self.cfg.pixel_stride
        views = []
        for c in range(len(self.session.cameras)):
            depth = self.session.read_depth(c, frame_id)
            if depth is None:
                views.append({"points": np.zeros((0, 3)), "colors": np.zeros((0, 3), np.uint8), "person": np.zeros(0, bool)})
                continue
            points, valid = depth_to_point_grid(
                torch.from_numpy(depth)[None].to(self.cameras.K.dtype), self.cameras.select([c]), stride,
                cfg.depth_min_m, cfg.depth_max_m, rays=self.rays(c),
            )
            valid = valid[0].numpy()
            count = int(valid.sum())
            color = self.session.read_color(c, frame_id)
            colors = color[::stride, ::stride].reshape(-1, 3)[valid] if color is not None else np.full((count, 3), 160, np.uint8)
            person = self.session.read_mask(c, frame_id, "person")
            person = person[::stride, ::stride].reshape(-1)[valid] if person is not None else np.zeros(count, bool)
            views.append({"points": points[0].numpy()[valid].astype(np.float64), "colors": colors, "person": person})
        return views


def estimate_ground(session, clouds: ViewClouds, cfg, progress: bool) -> tuple[GroundPlane, str]:
    """The ground plane from session.yaml, or RANSAC on fused clouds of a few frames."""
    if session.ground is not None:
        point, normal = session.ground
        normal = np.asarray(normal, float) / np.linalg.norm(normal)
        return GroundPlane(point=np.asarray(point, float), normal=normal, inlier_ratio=float("nan"), rmse_m=float("nan")), "session"
    scene, person = [], []
    for frame_id in tqdm(spread_frames(session.frame_ids, cfg.ground_frames), desc="prepare: ground", disable=not progress):
        for view in clouds.frame(int(frame_id)):
            scene.append(view["points"][~view["person"]])
            person.append(view["points"][view["person"]])
    fused = fuse_points(scene, cfg.voxel_size_m)
    person_points = np.concatenate(person) if person else np.zeros((0, 3))
    plane = fit_ground_plane(
        fused,
        distance_threshold=cfg.plane_distance_m,
        iterations=cfg.plane_iterations,
        seed=cfg.seed,
        person_points=person_points if len(person_points) > 100 else None,
        up_hint=up_hint_from_cameras(clouds.cameras.T_world_from_cam.double().numpy()),
    )
    return plane, "ransac"


AGREEMENT_FIELDS = ("cam_a", "cam_b", "overlap_points", "median_distance_mm", "icp_rmse_mm", "correction_rotation_deg",
                    "correction_translation_mm", "fitness", "unobservable", "full_translation_mm", "full_rotation_deg",
                    "translation_sigma_mm", "rotation_sigma_deg", "observable_dof", "significance", "flagged",
                    "blocks", "judged", "agreement_gain_pct")


def agreement_rows(results: list, frames: int) -> list[dict]:
    """The calibration check's per-pair figures as JSON-ready rows."""
    return [{**{key: getattr(r, key) for key in AGREEMENT_FIELDS}, "frames": frames} for r in results]


def check_views(points_per_view: list, names: list[str], centers, pcfg) -> list:
    """The calibration check with `prepare`'s settings: per view, its world points of each checked frame."""
    return check_calibration(points_per_view, names, centers, max_distance=pcfg.icp_max_distance_m,
                             voxel_size=max(2 * pcfg.voxel_size_m, 0.02), k_sigma=pcfg.calib_k_sigma,
                             min_mm=pcfg.calib_warn_mm, min_deg=pcfg.calib_warn_deg, min_blocks=pcfg.calib_min_blocks)


def refine_views(points_per_view: list, names: list[str], centers, pcfg):
    """The calibration refinement (`refine_rig`) with `prepare`'s settings, as `check_views` is the check."""
    return refine_rig(points_per_view, names, centers, max_distance=pcfg.icp_max_distance_m,
                      voxel_size=max(2 * pcfg.voxel_size_m, 0.02), iterations=pcfg.calib_refine_iterations,
                      prior=pcfg.calib_refine_prior, linear_beyond_m=pcfg.calib_refine_linear_beyond_m)


def view_points(session, clouds: ViewClouds, frame_ids, stage_dir: Path | None, desc: str,
                progress: bool) -> tuple[list[list[np.ndarray]], int]:
    """Per camera, its world points of each of `frame_ids` with at least two views (a dropped view
    keeps the frame, without its points), and how many frames that is. With `stage_dir`, each
    frame's fused coloured cloud goes to stage_dir/clouds/ for a person to open."""
    per_view = [[] for _ in session.cameras]
    used = 0
    for frame_id in tqdm(frame_ids, desc=desc, disable=not progress):
        views = clouds.frame(int(frame_id))
        if stage_dir is not None:
            write_point_cloud_ply(
                stage_dir / "clouds" / f"{int(frame_id):06d}.ply",
                np.concatenate([v["points"] for v in views]),
                np.concatenate([v["colors"] for v in views]),
            )
        if sum(len(v["points"]) > 0 for v in views) < 2:
            continue
        used += 1
        for c, v in enumerate(views):
            per_view[c].append(v["points"] if len(v["points"]) else np.zeros((0, 3)))
    return per_view, used


def check_rig(session, clouds: ViewClouds, checked, stage_dir: Path, pcfg,
              progress: bool) -> tuple[list, int, list[str]]:
    """The calibration check on the `checked` frames (their clouds saved): per-pair agreements, frames used,
    and the cameras without a single depth point in them.
    Frames are matched only with themselves (the person moves), and the person and object in several
    poses constrain what the floor leaves free."""
    per_view, used = view_points(session, clouds, checked, stage_dir if pcfg.save_clouds else None,
                                 "prepare: calibration check", progress)
    if not used:
        return [], 0, []
    per_view, used = with_every_view(session, clouds, per_view, checked, progress)
    blind = [name for name, view in zip(session.camera_names, per_view) if not any(len(f) for f in view)]
    return check_views(per_view, session.camera_names, clouds.cameras.centers.numpy(), pcfg), used, blind


def complete(per_view: list) -> list[int]:
    """The frames (indices into each view's list) where every view has points."""
    return [k for k in range(len(per_view[0])) if all(len(view[k]) for view in per_view)]


def with_every_view(session, clouds: ViewClouds, per_view: list, checked, progress: bool) -> tuple[list, int]:
    """The check's frames with every view's points: a frame where a view read nothing (a depth file that
    is there but unreadable, a view that saw nothing) is replaced by other frames every view has, so no
    pair is judged on fewer frames than the rest (ICP then walks off on an exact rig). As given when every
    frame is complete, or when no other frame is."""
    keep = complete(per_view)
    if len(keep) == len(per_view[0]):
        return per_view, len(keep)
    others = np.setdiff1d(checkable_frames(session, len(session.frame_ids)), checked)
    extra, _ = view_points(session, clouds, spread_frames(others, min(len(others), 3 * len(checked))), None,
                           "prepare: calibration check (frames every view has)", progress) if len(others) else ([], 0)
    picked = [[view[k] for k in keep] for view in per_view]
    for k in complete(extra) if extra else []:
        if len(picked[0]) >= len(checked):
            break
        for c, view in enumerate(extra):
            picked[c].append(view[k])
    if not picked[0]:
        return per_view, len(per_view[0])
    return picked, len(picked[0])


def refine_cameras(session, clouds: ViewClouds, stage_dir: Path, pcfg, progress: bool) -> dict:
    """Correct the cameras' poses so all views agree (`refine_rig`), in `session` and in
    OUT/prepare/calibration_refined.json (the session's calibration with the new poses, usable as a
    calibration.json); the figures for metrics.json."""
    frames = checkable_frames(session, pcfg.calib_refine_frames)
    per_view, used = view_points(session, clouds, frames, None, "prepare: refining the calibration", progress)
    if not used:
        return {"calibration_refined": False}
    names = session.camera_names
    result = refine_views(per_view, names, clouds.cameras.centers.numpy(), pcfg)
    cameras = [dataclasses.replace(c, T_world_from_cam=T @ c.T_world_from_cam)
               for c, T in zip(session.cameras, result.corrections)]
    rows = [{"name": c.name, "moved_mm": round(float(mm), 2), "turned_deg": round(float(deg), 3)}
            for c, mm, deg in zip(cameras, result.moved_mm, result.turned_deg)]
    write_json(stage_dir / REFINED_CALIBRATION.name, {
        "world": "the session's world frame; camera poses corrected by `intercap run`'s prepare stage so all "
                 "views' depth agrees (calibration_check.json: before and after)",
        "cameras": [camera_entry(c.name, c.width, c.height, c.K, c.dist, c.T_world_from_cam) for c in cameras],
        "corrections": rows, "frames": [int(f) for f in frames], "pairs": result.pairs,
        "iterations": result.iterations, "residual_before_mm": result.residual_before_mm,
        "residual_after_mm": result.residual_after_mm,
    })
    session.cameras = cameras
    log.info("calibration refined on %d frames (%d view pairs, %d steps; residual %.2f -> %.2f mm): %s", used,
             result.pairs, result.iterations, result.residual_before_mm, result.residual_after_mm,
             ", ".join(f"{r['name']} {r['moved_mm']:.1f} mm / {r['turned_deg']:.2f} deg" for r in rows))
    return {"calibration_refined": True, "calibration_refined_max_mm": float(result.moved_mm.max()),
            "calibration_refined_max_deg": float(result.turned_deg.max())}


def report_check(results: list, used_frames: int, blind: list[str], pcfg) -> tuple[list[dict], list[str]]:
    """Log the check's table and warnings; its JSON rows and the suspect cameras (`blind`: cameras without
    depth in the checked frames, which meet no other view for want of points, not for a wrong pose)."""
    pairs = agreement_rows(results, used_frames)
    isolated = [c for c in isolated_cameras(results) if c not in blind]
    suspects = suspect_cameras(results)
    suspects += [c for c in isolated if c not in suspects]
    for camera in isolated:
        log.warning("camera %s: its depth meets no other view's (nothing within %.0f cm of its neighbours' points): "
                    "its pose in calibration.json looks wrong (inverted? another rig's? millimetres?)",
                    camera, 100 * pcfg.icp_max_distance_m)
    if results:
        log.info("calibration check (%d frames)\n%s", used_frames, format_agreement(results, **check_thresholds(pcfg)))
    for p in pairs:
        if p["flagged"]:
            log.warning("cameras %s and %s disagree by %.1f+-%.1f mm / %.2f+-%.2f deg: check the calibration",
                        p["cam_a"], p["cam_b"], p["correction_translation_mm"], p["translation_sigma_mm"],
                        p["correction_rotation_deg"], p["rotation_sigma_deg"])
    if suspects:
        log.warning("CHECK CALIBRATION of camera(s): %s", ", ".join(suspects))
    return pairs, suspects


def check_thresholds(pcfg) -> dict:
    return {"warn_mm": pcfg.calib_warn_mm, "warn_deg": pcfg.calib_warn_deg, "k_sigma": pcfg.calib_k_sigma}


def run(session, cfg: Config, out_dir: Path, progress: bool = True) -> dict:
    """Run the prepare stage; returns the figures that go into metrics.json."""
    pcfg = cfg.prepare
    stage_dir = Path(out_dir) / "prepare"
    (stage_dir / REFINED_CALIBRATION.name).unlink(missing_ok=True)  # a killed earlier run's; decided again below
    clouds = ViewClouds(session, Cameras.from_infos(session.cameras, dtype=torch.float32), pcfg)
    checked = checkable_frames(session, pcfg.calib_frames)
    results, used_frames, blind = check_rig(session, clouds, checked, stage_dir, pcfg, progress)
    pairs, suspects = report_check(results, used_frames, blind, pcfg)
    check = {"frames": [int(f) for f in checked], "pairs": pairs, **check_thresholds(pcfg),
             "flagged": [p for p in pairs if p["flagged"]], "suspect_cameras": suspects,
             "unchecked_cameras": [c for c in unchecked_cameras(results) if c not in suspects]}
    if check["unchecked_cameras"]:
        log.warning("calibration of camera(s) %s not checked: too little surface shared with the other views "
                    "(a camera close in, the floor out of its image); used as given",
                    ", ".join(check["unchecked_cameras"]))
    refined = {"calibration_refined": False}
    if pcfg.calib_refine == "always" or (pcfg.calib_refine == "auto" and check["flagged"]):
        refined = refine_cameras(session, clouds, stage_dir, pcfg, progress)
    if refined["calibration_refined"]:  # the check again, and everything after it, with the refined poses
        clouds = ViewClouds(session, Cameras.from_infos(session.cameras, dtype=torch.float32), pcfg)
        log.info("the calibration check again, with the refined poses")
        after, _, blind = check_rig(session, clouds, checked, stage_dir, pcfg, progress)
        after_pairs, after_suspects = report_check(after, used_frames, blind, pcfg)
        check["after_refinement"] = {"pairs": after_pairs, "flagged": [p for p in after_pairs if p["flagged"]],
                                     "suspect_cameras": after_suspects}
    write_json(stage_dir / "calibration_check.json", check)

    try:
        plane, source = estimate_ground(session, clouds, pcfg, progress)
    except ValueError as error:  # no floor in view: the global stage takes up from the object's free flight
        plane, source = None, "unavailable"
        (stage_dir / "ground.json").unlink(missing_ok=True)
        write_json(stage_dir / "ground_unavailable.json", {"error": str(error), "fallback": GRAVITY_FALLBACK})
        log.warning("no ground plane (%s); %s", error, GRAVITY_FALLBACK)
    else:
        (stage_dir / "ground_unavailable.json").unlink(missing_ok=True)
        write_json(stage_dir / "ground.json", {**plane.to_dict(), "source": source})
        log.info("ground plane (%s): normal %s, rmse %.1f mm", source, np.round(plane.normal, 4), plane.rmse_m * 1e3)

    corrections = [p["correction_translation_mm"] for p in pairs if np.isfinite(p["correction_translation_mm"])]
    figures = {
        "ground_source": source,
        **({"ground_fallback": GRAVITY_FALLBACK} if plane is None else {}),
        "ground_rmse_mm": plane.rmse_m * 1e3 if plane is not None else None,
        "ground_inlier_ratio": plane.inlier_ratio if plane is not None else None,
        "calibration_max_correction_mm": max(corrections) if corrections else None,
        "calibration_pairs_flagged": len(check["flagged"]),
        "calibration_suspect_cameras": suspects,
        **refined,
    }
    if "after_refinement" in check:
        figures["calibration_pairs_flagged_after_refinement"] = len(check["after_refinement"]["flagged"])
    return figures


def load_ground(out_dir: Path) -> GroundPlane:
    """The ground plane a finished prepare stage saved."""
    from intercap.io.files import read_json

    data = read_json(Path(out_dir) / "prepare" / "ground.json")
    return GroundPlane(point=np.array(data["point"]), normal=np.array(data["normal"]),
                       inlier_ratio=data["inlier_ratio"], rmse_m=data["rmse_m"])

