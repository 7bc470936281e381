"""`intercap report OUT [--gt SESSION]`: one self-contained HTML page per results folder.

OUT/report/index.html holds the session summary, per-stage timings, the calibration check,
per-frame curves (keypoint reprojection, cloud-to-fit, object confidence, trusted frames,
contact per body region, penetration, body and object acceleration, physics forces), the
InterCap-style figures (penetration CDF, contact heat map on the rest body), overlay
thumbnails linking to the full images beside the page, and with ground truth (--gt SESSION, else
the session's own ground_truth/ folder) the evaluation table and error-over-time curves. Stage
and evaluation figures are small tables of name, value and unit. Figures are PNGs embedded as
base64; the overlay images and the video sit in OUT/report/ (relative links), so the folder opens
without a network.

Everything is computed from saved arrays; a stage that has not run shows "not run". The
session path comes from the caller, else from OUT/run.json (written by `intercap run`) or
OUT/report/session.json (an earlier report), else from --gt.
"""
from __future__ import annotations

import base64
import html
import io
import json
import logging
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from tqdm import tqdm

from intercap.evaluation.overlays import OVERLAY_STAGES, load_stage_meshes

log = logging.getLogger(__name__)

STAGE_ORDER = ["prepare", "detect", "object", "body", "contact", "global", "physics", "export"]
STAGE_COLOURS = {"object": "tab:green", "body": "tab:blue", "global": "tab:red", "gt": "black"}
PHYSICS_COLOURS = {"left hand |F|": "tab:blue", "right hand |F|": "tab:orange", "left foot |F|": "tab:green",
                   "right foot |F|": "tab:red", "object-ground |F|": "tab:brown", "root residual |F|": "tab:purple",
                   "object residual |F|": "tab:gray"}


# -- page building ---------------------------------------------------------------------------
@dataclass
class Page:
    """Sections of the page, in order: (id, title, html body)."""

    sections: list[tuple[str, str, str]] = field(default_factory=list)

    def add(self, ident: str, title: str, body: str) -> None:
        self.sections.append((ident, title, body))

    def not_run(self, ident: str, title: str, why: str) -> None:
        self.add(ident, title, f'<p class="notrun">not run: {html.escape(why)}</p>')

    def render(self, title: str, subtitle: str) -> str:
        nav = " · ".join(f'<a href="#{i}">{html.escape(t)}</a>' for i, t, _ in self.sections)
        body = "\n".join(f'<section id="{i}"><h2>{html.escape(t)}</h2>\n{b}\n</section>' for i, t, b in self.sections)
        return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>
body{{font-family:sans-serif;margin:1.5em auto;max-width:1200px;color:#222;padding:0 1em}}
h1{{margin-bottom:0.1em}} h2{{border-bottom:1px solid #ccc;padding-bottom:0.2em;margin-top:1.6em}}
table{{border-collapse:collapse;margin:0.5em 0;font-size:0.9em}}
td,th{{border:1px solid #ccc;padding:0.2em 0.6em;text-align:right}} th{{background:#f2f2f2}}
td:first-child,th:first-child{{text-align:left}}
.notrun{{color:#a33;font-style:italic}} .warn{{color:#a60}} .sub{{color:#666}}
table{{max-width:100%}} th{{white-space:normal}} .unit{{text-align:left;color:#555}}
.cards{{display:flex;flex-wrap:wrap;gap:0.4em 1.2em;align-items:flex-start}} .card{{flex:1 1 330px;max-width:560px}}
table.calib td:last-child{{text-align:left}} .card h3{{margin:0.6em 0 0.1em;font-size:1em}}
table.figures{{width:100%}} table.figures td{{padding:0.1em 0.4em;white-space:pre-line}}
table.figures td:first-child{{white-space:nowrap}}
img.fig{{max-width:100%}} .strip{{display:flex;flex-wrap:wrap;gap:4px}} .strip figure{{margin:0}}
.strip figcaption{{font-size:0.75em;color:#555;text-align:center}} nav{{font-size:0.9em;margin:0.5em 0 1em}}
</style></head><body>
<h1>{html.escape(title)}</h1><p class="sub">{html.escape(subtitle)}</p>
<nav>{nav}</nav>
{body}
</body></html>
"""


def table(rows: list[dict], columns: list[str] | None = None, cls: str = "") -> str:
    """An HTML table of dict rows (numbers shown with 4 significant digits); cls: its CSS class."""
    if not rows:
        return "<p>(empty)</p>"
    columns = columns or list(dict.fromkeys(k for r in rows for k in r))

    def cell(v):
        if isinstance(v, float):
            return "–" if not np.isfinite(v) else f"{v:.4g}"
        if isinstance(v, (list, tuple)):
            return html.escape(", ".join(str(x) for x in v))
        return html.escape("–" if v is None else str(v))

    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    body = "".join("<tr>" + "".join(f"<td>{cell(r.get(c))}</td>" for c in columns) + "</tr>" for r in rows)
    attr = f' class="{cls}"' if cls else ""
    return f"<table{attr}><tr>{head}</tr>{body}</table>"


def png_data_uri(data: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(data).decode("ascii")


def figure_html(fig, alt: str) -> str:
    """A matplotlib figure as an embedded PNG <img> (the figure is closed)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=72, bbox_inches="tight", pad_inches=0.05)
    plt.close(fig)
    return f'<img class="fig" alt="{html.escape(alt)}" src="{png_data_uri(buf.getvalue())}">'


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def series_colours(names, given: dict[str, str] | None = None) -> dict[str, str]:
    """A colour per series name, no two alike: `given`, else the stage's colour (a name starting with
    "body", "object", "global" or "gt" and a space or colon), else the next tab10 / tab20 colour not
    yet taken. Names of one stage share its colour (told apart by line style)."""
    from matplotlib import colormaps
    from matplotlib.colors import to_hex

    given = dict(given or {})
    out = {n: given.get(n) or STAGE_COLOURS.get(n.split(" ")[0].rstrip(":")) for n in names}
    taken = {to_hex(c) for c in out.values() if c}
    spare = [to_hex(c) for c in (*colormaps["tab10"].colors, *colormaps["tab20"].colors[1::2])]
    spare = [c for c in dict.fromkeys(spare) if c not in taken]
    for n in names:
        if not out[n]:
            out[n] = spare.pop(0) if spare else "#444444"
    return out


def curves(title: str, ylabel: str, series: dict[str, np.ndarray], frame_ids: np.ndarray, log_y: bool = False,
           note: str = "", colours: dict[str, str] | None = None, styles: dict[str, str] | None = None) -> str:
    """One line plot over frames of several named (T,) series (NaN gaps are gaps), each its own colour
    (`series_colours`) or line style; `styles` overrides the style (default dashed for a stage's object series)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(11, 2.8))
    fig.subplots_adjust(left=0.07, right=0.99, bottom=0.17, top=0.9)
    colour = series_colours(list(series), colours)
    styles = styles or {}
    for name, values in series.items():
        ax.plot(frame_ids[:len(values)], values, label=name, color=colour[name],
                ls=styles.get(name, "--" if "object" in name.split(" ")[1:] else "-"),
                marker="." if len(values) < 80 else None, lw=1.2)
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("frame")
    ax.set_ylabel(ylabel)
    if log_y:
        ax.set_yscale("symlog", linthresh=1.0)
    ax.grid(alpha=0.3)
    if len(series) > 3:  # beside the plot, where it hides no line
        fig.subplots_adjust(right=0.82)
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    elif len(series) > 1:
        ax.legend(fontsize=8, loc="upper right")
    out = figure_html(fig, title)
    return out + (f'<p class="sub">{html.escape(note)}</p>' if note else "")


# -- inputs ----------------------------------------------------------------------------------
def _npz(path: Path) -> dict | None:
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as exc:  # noqa: BLE001 - a broken file is a note, not a crash
        log.warning("report: cannot read %s (%s)", path, exc)
        return None


def _json(path: Path):
    try:
        return json.loads(path.read_text()) if path.is_file() else None
    except (OSError, ValueError) as exc:
        log.warning("report: cannot read %s (%s)", path, exc)
        return None


def find_session(out_dir: Path, session=None, gt=None):
    """The session the results were made from: the argument, the one `intercap run` recorded in OUT/run.json
    (or a previous report in OUT/report/session.json), or --gt."""
    from intercap.session import Session

    if session is not None:
        return session if isinstance(session, Session) else _with_refined_calibration(Session.load(session), out_dir)
    recorded = [(_json(out_dir / name) or {}).get("session") for name in ("run.json", "report/session.json")]
    for candidate in (*recorded, gt):
        if candidate and Path(candidate).is_dir():
            try:
                return _with_refined_calibration(Session.load(candidate), out_dir)
            except Exception as exc:  # noqa: BLE001
                log.warning("report: cannot load session %s (%s)", candidate, exc)
    return None


def _with_refined_calibration(session, out_dir: Path):
    """The session with the cameras the run's `prepare` refined and the frames it took, as the fits saw them."""
    session.use_run_frames(out_dir)
    session.use_refined_calibration(out_dir)
    return session


def frame_sample(T: int, most: int) -> np.ndarray:
    """Up to `most` frame indices spread evenly over T frames."""
    return np.unique(np.linspace(0, T - 1, min(T, max(most, 2))).round().astype(int)) if T else np.zeros(0, int)


# -- per-frame figures computed from saved arrays --------------------------------------------
def reprojection_px(session, out_dir: Path, keypoints3d: np.ndarray, frames: np.ndarray,
                    min_conf: float = 0.2) -> np.ndarray:
    """(T,) mean pixel distance between the projected 3D keypoints (T, 67, 3) and the 2D detections
    (the session's OpenPose JSON, else the detect stage's) over confident joints of all views."""
    import torch

    from intercap.geometry.cameras import Cameras, project
    from intercap.session.openpose import openpose_to_array

    cams = Cameras.from_infos(session.cameras, dtype=torch.float64)
    out = np.full(session.num_frames, np.nan)
    J = min(keypoints3d.shape[1], 67)
    for i in frames:
        kp = np.asarray(keypoints3d[i, :J], np.float64)
        if not np.isfinite(kp).all():
            continue
        pix = project(torch.from_numpy(kp), cams)[0].numpy()  # (C, J, 2)
        errs = []
        for c, cam in enumerate(session.cameras):
            fid = int(session.frame_ids[i])
            det = session.read_keypoints(c, fid)
            if det is None:
                path = out_dir / "detect" / cam.name / "keypoints" / f"{fid:06d}.json"
                if path.is_file():
                    try:
                        det = openpose_to_array(json.loads(path.read_text()))[0]
                    except (OSError, ValueError):
                        det = None
            if det is None:
                continue
            ok = det[:J, 2] > min_conf
            errs.append(np.linalg.norm(pix[c, ok] - det[:J][ok, :2], axis=1))
        if errs and sum(len(e) for e in errs):
            out[i] = float(np.concatenate(errs).mean())
    return out


@dataclass
class DepthPoints:
    """Per frame (of `frames`), the person's and the object's depth points (world), from the masks."""

    frames: np.ndarray
    person: list[np.ndarray]
    object: list[np.ndarray]


def depth_points(session, frames: np.ndarray, per_view: int, seed: int = 0) -> DepthPoints | None:
    """Masked depth points of each frame, `per_view` per view and kind; None without masks."""
    import torch

    from intercap.geometry.cameras import Cameras, pixel_rays

    if not (all(session.has_kind("mask_person")) or all(session.has_kind("mask_object"))):
        return None
    rng = np.random.default_rng(seed)
    rays = []
    for cam in session.cameras:
        r = pixel_rays(Cameras.from_infos([cam], dtype=torch.float64), cam.height, cam.width)[0].numpy()
        rays.append(np.c_[r, np.ones(len(r))])  # (H*W, 3) camera-frame direction with z = 1
    person, obj = [], []
    for i in frames:
        fid = int(session.frame_ids[i])
        got = {"person": [], "object": []}
        for c, cam in enumerate(session.cameras):
            depth = session.read_depth(c, fid)
            if depth is None:
                continue
            T = np.asarray(cam.T_world_from_cam, np.float64)
            for kind in got:
                mask = session.read_mask(c, fid, kind)
                if mask is None:
                    continue
                idx = np.flatnonzero(mask.reshape(-1) & (depth.reshape(-1) > 0))
                if len(idx) > per_view:
                    idx = rng.choice(idx, per_view, replace=False)
                p = rays[c][idx] * depth.reshape(-1)[idx, None]
                got[kind].append(p @ T[:3, :3].T + T[:3, 3])
        person.append(np.concatenate(got["person"]) if got["person"] else np.zeros((0, 3)))
        obj.append(np.concatenate(got["object"]) if got["object"] else np.zeros((0, 3)))
    return DepthPoints(frames, person, obj)


def _surface_distance(mesh, points: np.ndarray) -> np.ndarray:
    """Exact distances (N,) of points (N, 3), object coordinates, to the object mesh's surface."""
    from intercap.geometry.surfaces import TriangleSurface

    if not len(points):
        return np.zeros(0)
    if getattr(mesh, "_report_surface", None) is None:  # built once per mesh object
        mesh._report_surface = TriangleSurface(mesh.vertices, mesh.faces)
    return mesh._report_surface.closest(points)[0]


def vertex_faces(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """(V, M) ids of the faces around each vertex, padded with -1."""
    f = np.asarray(faces, np.int64)
    owner = f.reshape(-1)
    face = np.repeat(np.arange(len(f)), 3)
    order = np.argsort(owner, kind="stable")
    owner, face = owner[order], face[order]
    count = np.bincount(owner, minlength=num_vertices)
    slot = np.arange(len(owner)) - np.repeat(np.cumsum(count) - count, count)
    out = np.full((num_vertices, max(int(count.max()), 1)), -1, np.int64)
    out[owner, slot] = face
    return out


def _body_distances(body_vertices, faces, frames, points: list[np.ndarray], near: int = 4) -> list:
    """Per frame of `frames`, distances (N,) of its points to that frame's body surface (None where
    the body is unknown): exact point-to-triangle over the faces around each point's `near`
    nearest vertices (on a dense body mesh the closest face is among them but for rare sliver
    cases; a KD-tree per frame instead of a full closest-triangle search)."""
    from scipy.spatial import cKDTree

    from intercap.geometry.surfaces import closest_points_on_triangles

    faces = np.asarray(faces, np.int64)
    out = [None] * len(frames)
    around = None
    for k, i in enumerate(frames):
        v = np.asarray(body_vertices[i], np.float64)
        if not np.isfinite(v).all() or not len(points[k]):
            continue
        if around is None:
            around = vertex_faces(faces, len(v))
        p = np.asarray(points[k], np.float64)
        _, j = cKDTree(v).query(p, near)  # (N, near)
        cand = around[j].reshape(len(p), -1)  # (N, near * M), -1 padded
        tri = v[faces[np.maximum(cand, 0)]]  # (N, C, 3, 3)
        q, _ = closest_points_on_triangles(p[:, None], tri[..., 0, :], tri[..., 1, :], tri[..., 2, :])
        d = np.where(cand >= 0, np.linalg.norm(q - p[:, None], axis=-1), np.inf)
        out[k] = d.min(1)
    return out


def cloud_to_fit_mm(points: DepthPoints, T: int, body_vertices=None, faces=None, R=None, t=None,
                    mesh=None) -> tuple[np.ndarray, np.ndarray]:
    """(T,) median distance (mm) of the person's depth points to the body surface and of the object's
    to the posed object, NaN where unknown. Medians: mask edges carry mixed-depth outliers."""
    body, obj = np.full(T, np.nan), np.full(T, np.nan)
    if body_vertices is not None:
        for i, d in zip(points.frames, _body_distances(body_vertices, faces, points.frames, points.person)):
            if d is not None:
                body[i] = 1000 * float(np.median(d))
    if mesh is not None and R is not None:
        ok = [k for k, i in enumerate(points.frames) if len(points.object[k]) and np.isfinite(R[i]).all()
              and np.isfinite(t[i]).all()]
        if ok:
            local = [(points.object[k] - t[points.frames[k]]) @ R[points.frames[k]] for k in ok]
            d = _surface_distance(mesh, np.concatenate(local))
            for k, part in zip(ok, np.split(d, np.cumsum([len(x) for x in local])[:-1])):
                obj[points.frames[k]] = 1000 * float(np.median(part))
    return body, obj


def vertex_acceleration(vertices, fps: float, frames: np.ndarray | None = None) -> np.ndarray:
    """(T,) mean vertex acceleration (m/s^2) at each frame (central second difference; NaN at the ends
    and next to missing frames). vertices (T, V, 3), possibly memory-mapped."""
    T = len(vertices)
    acc = np.full(T, np.nan)
    idx = np.arange(1, T - 1) if frames is None else frames[(frames > 0) & (frames < T - 1)]
    for i in idx:
        v = np.asarray(vertices[i - 1:i + 2], np.float64)
        a = np.linalg.norm(v[2] - 2 * v[1] + v[0], axis=-1) * fps ** 2
        if np.isfinite(a).all():
            acc[i] = float(a.mean())
    return acc


def posed(mesh_vertices: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(T, K, 3) object vertices under poses R (T, 3, 3), t (T, 3)."""
    return np.einsum("tij,kj->tki", R, mesh_vertices) + t[:, None]


def penetration_mm(body_vertices, R, t, surface, frames: np.ndarray) -> np.ndarray:
    """(T,) deepest body vertex inside the posed object (mm), on `frames` where both are known."""
    from intercap.evaluation.metrics import penetration_depths

    T = len(R)
    out = np.full(T, np.nan)
    ok = [i for i in frames if np.isfinite(R[i]).all() and np.isfinite(t[i]).all()
          and np.isfinite(np.asarray(body_vertices[i][:1])).all()]
    if ok:
        ok = np.asarray(ok)
        out[ok] = 1000 * penetration_depths(np.asarray(body_vertices[ok]), R[ok], t[ok], surface)
    return out


def vertex_contact_frequency(body_vertices, R, t, mesh, frames: np.ndarray, distance_m: float) -> np.ndarray | None:
    """(V,) fraction of `frames` (with a body and object) in which each vertex lies within
    `distance_m` of the posed object's surface; None without such frames."""
    lo, hi = np.asarray(mesh.vertices).min(0) - distance_m, np.asarray(mesh.vertices).max(0) + distance_m
    count, n = None, 0
    for i in frames:
        v = np.asarray(body_vertices[i], np.float64)
        if not (np.isfinite(v).all() and np.isfinite(R[i]).all() and np.isfinite(t[i]).all()):
            continue
        local = (v - t[i]) @ R[i]  # object coordinates
        box = np.flatnonzero(((local >= lo) & (local <= hi)).all(1))  # only these can be that close
        near = np.zeros(len(v))
        near[box] = _surface_distance(mesh, local[box]) < distance_m
        count = near if count is None else count + near
        n += 1
    return None if count is None else count / n


def heatmap_image(rest_vertices: np.ndarray, faces: np.ndarray, frequency: np.ndarray, size: int = 360,
                  feet: np.ndarray | None = None) -> bytes:
    """PNG of the rest body coloured by contact frequency, front and back, side by side (pyrender).
    feet: vertex ids of the feet (they set which end of the body is down; else the sparser end)."""
    import trimesh

    from intercap.evaluation.overlays import import_pyrender

    plt = _plt()
    pr = import_pyrender()
    v = np.asarray(rest_vertices, np.float64)
    centre = (v.max(0) + v.min(0)) / 2
    axes = np.linalg.svd(v - v.mean(0), full_matrices=False)[2]  # rows: longest (up), arms, front-back
    up, depth_axis = axes[0], axes[2]
    h = (v - centre) @ up
    if feet is not None and len(feet):
        flip = h[feet].mean() > 0
    else:  # the head end holds more vertices (face) than the feet end
        flip = (h > 0.4 * np.ptp(h)).sum() < (h < -0.4 * np.ptp(h)).sum()
    up = -up if flip else up
    height = float(np.ptp((v - centre) @ up))
    colours = (plt.get_cmap("inferno")(0.15 + 0.85 * np.clip(frequency / max(frequency.max(), 1e-9), 0, 1))[:, :3]
               * 255).astype(np.uint8)
    colours[frequency <= 0] = (205, 205, 210)
    mesh = trimesh.Trimesh(v, faces, vertex_colors=np.c_[colours, np.full(len(colours), 255, np.uint8)], process=False)
    scene = pr.Scene(ambient_light=(0.55, 0.55, 0.55), bg_color=(1.0, 1.0, 1.0, 1.0))
    scene.add(pr.Mesh.from_trimesh(mesh, smooth=True))
    cam = scene.add(pr.PerspectiveCamera(yfov=np.radians(30.0), aspectRatio=0.75), pose=np.eye(4))
    light = scene.add(pr.DirectionalLight(intensity=2.0), pose=np.eye(4))
    renderer = pr.OffscreenRenderer(int(size * 0.75), size)
    images = []
    try:
        for sign in (1.0, -1.0):
            back = sign * depth_axis  # the camera sits on this side and looks back (OpenGL: along -z)
            x = np.cross(up, back)
            pose = np.eye(4)
            pose[:3, 0], pose[:3, 1], pose[:3, 2] = x / np.linalg.norm(x), up, back
            pose[:3, 3] = centre + back * height * 2.1
            scene.set_pose(cam, pose)
            scene.set_pose(light, pose)
            images.append(renderer.render(scene)[0])
    finally:
        renderer.delete()
    fig, axs = plt.subplots(1, 3, figsize=(7.5, 4.2), gridspec_kw={"width_ratios": [1, 1, 0.08]})
    for ax, img, name in zip(axs, images, ("side A", "side B")):
        ax.imshow(img)
        ax.set_title(name, fontsize=9)
        ax.axis("off")
    import matplotlib as mpl

    mpl.colorbar.ColorbarBase(axs[2], cmap=plt.get_cmap("inferno"),
                              norm=mpl.colors.Normalize(0, 100 * float(frequency.max())), label="% of contact frames")
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


# -- the report ------------------------------------------------------------------------------
def _overlay_strip(report_dir: Path, images: list, width: int) -> str:
    """Embedded thumbnails, each linking to the full image beside the page."""
    import cv2

    items = []
    for fid, cam, rel in images:
        img = cv2.imread(str(report_dir / rel))
        if img is None:
            continue
        h = int(round(img.shape[0] * width / img.shape[1]))
        ok, jpg = cv2.imencode(".jpg", cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA),
                               [cv2.IMWRITE_JPEG_QUALITY, 80])
        uri = "data:image/jpeg;base64," + base64.b64encode(jpg.tobytes()).decode("ascii")
        items.append(f'<figure><a href="{html.escape(rel)}"><img src="{uri}" width="{width}" height="{h}" '
                     f'alt="frame {fid} {html.escape(cam)}"></a><figcaption>{fid} · {html.escape(cam)}</figcaption>'
                     "</figure>")
    return f'<div class="strip">{"".join(items)}</div>'


def _report_config(out_dir: Path):
    """OUT/config.yaml when readable, else the defaults (with only its report settings when it is from another
    version)."""
    from intercap.config import Config, ConfigError, load_config

    try:
        return load_config(out_dir / "config.yaml") if (out_dir / "config.yaml").is_file() else Config()
    except ConfigError as exc:  # a tree from another version: keep only its report settings
        cfg = Config()
        try:
            saved = (yaml.safe_load((out_dir / "config.yaml").read_text()) or {}).get("report") or {}
            cfg = load_config(None, [f"report.{k}={json.dumps(v)}" for k, v in saved.items()])
        except (ConfigError, OSError, yaml.YAMLError, AttributeError):
            log.warning("report: %s; using the default settings", exc)
        return cfg


def _summary_section(page: Page, session, report_dir: Path) -> None:
    """The session summary: its folder, frames, cameras and which inputs each camera has."""
    if session is None:
        page.not_run("summary", "Session", "session folder unknown (pass --session SESSION or --gt SESSION)")
    else:
        (report_dir / "session.json").write_text(json.dumps({"session": str(Path(session.root).resolve())}) + "\n")
        avail = session.availability()
        rows = []
        for c, cam in enumerate(session.cameras):
            row = {"camera": cam.name, "size": f"{cam.width}x{cam.height}",
                   "fx": float(np.asarray(cam.K)[0, 0]), "distortion": len(np.asarray(cam.dist).reshape(-1))}
            for kind, have in avail.items():
                if session.has_kind(kind)[c]:
                    row[kind] = f"{int(have[c].sum())}/{session.num_frames}"
            rows.append(row)
        obj = session.object
        facts = [f"<b>{html.escape(str(session.root))}</b>",
                 f"{session.num_frames} frames ({session.frame_ids[0]}..{session.frame_ids[-1]}) at {session.fps:g} fps",
                 f"{session.num_cameras} cameras", f"body model: {html.escape(session.body_model)}",
                 "object: " + (html.escape(f"{obj.name or ''} ({Path(obj.mesh_path).name})") if obj else "none"),
                 "contact annotation: " + ("yes" if session.contact_frames is not None else "no"),
                 "ground truth: " + ("yes" if session.ground_truth() is not None else "no")]
        page.add("summary", "Session", "<p>" + " · ".join(facts) + "</p>" + table(rows)
                 + '<p class="sub">per input kind: frames present / frames</p>')


# metrics.json keys: the last unit word(s) of a key name its unit; words after it are statistics
_UNITS = {("pct", "bw"): "% body weight", ("mm", "s"): "mm/s", ("mps2",): "m/s²", ("mps",): "m/s",
          ("mm",): "mm", ("px",): "px", ("deg",): "°", ("pct",): "%", ("kg",): "kg", ("n",): "N",
          ("nm",): "N m", ("ms",): "ms", ("m",): "m", ("s",): "s"}
_WORDS = {"gt": "ground truth", "add": "ADD", "adds": "ADD-S", "mpjpe": "MPJPE", "sym": "symmetric", "rmse": "RMSE",
          "icp": "ICP", "2d": "2D", "3d": "3D"}
_STATS = {"mean", "median", "max", "min", "p90", "p95", "p99", "sum", "std"}
_FIGURE_NAMES = {  # keys whose words do not read well by themselves: (label, unit)
    "seconds_per_frame_fit": ("fit time per frame", "s"), "physics_seconds_per_frame": ("solve time per frame", "s"),
    "glb_bytes": ("glb file size", "MB"), "gravity_up": ("up (against gravity)", ""),
    "keypoint_energy_ratio": ("keypoint energy after / before", "×"), "dataset_keys": ("dataset arrays", ""),
    "gt_accuracy_2d_pct": ("2D baseline agrees with ground truth", "%"),
    "gt_accuracy_3d_pct": ("3D baseline agrees with ground truth", "%"),
}
_FIGURES_SHOWN_ELSEWHERE = {"seconds", "seconds_per_frame", "orientation_hypotheses", "energy_before", "energy_after"}


def figure_name(key: str) -> tuple[str, str]:
    """(readable label, unit) of a metrics.json key: "penetration_mm_max" -> ("penetration (max)", "mm")."""
    if key in _FIGURE_NAMES:
        return _FIGURE_NAMES[key]
    words = key.split("_")
    stats = []
    while len(words) > 1 and words[-1] in _STATS:
        stats.insert(0, words.pop())
    unit = ""
    for n in (2, 1):
        if len(words) > n and tuple(words[-n:]) in _UNITS:
            unit, words = _UNITS[tuple(words[-n:])], words[:-n]
            break
    while len(words) > 1 and words[-1] in _STATS:  # "ground_reaction_mean_n"
        stats.insert(0, words.pop())
    label = " ".join(_WORDS.get(w, w) for w in words)
    return label + (f" ({', '.join(stats)})" if stats else ""), unit


def figure_value(key: str, value, unit: str) -> str | None:
    """A metrics.json value as short text (None: nothing worth a row)."""
    if value is None or (isinstance(value, (list, tuple, dict)) and not len(value)):
        return None
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, (int, np.integer)):
        return f"{value / 1e6:.1f}" if unit == "MB" else str(int(value))
    if isinstance(value, (float, np.floating)):
        return "–" if not np.isfinite(value) else f"{value:.3g}"
    if isinstance(value, str):
        p = Path(value)
        if "/" in value and p.suffix:  # a file in the results: its folder and name
            return f"{p.parent.name}/{p.name}"
        return value.replace("_", " ") if re.fullmatch(r"[a-z0-9_]+", value) else value
    if isinstance(value, dict):
        items = [f"{str(k).replace('_', ' ')} {figure_value(k, v, '') or '–'}" for k, v in value.items()]
        return "\n".join(items) if len(items) <= 8 else None  # one per line (white-space: pre-line)
    if isinstance(value, (list, tuple)):
        if all(isinstance(v, (int, float)) for v in value) and len(value) == 3 and unit == "":
            return "(" + ", ".join(f"{v:.3g}" for v in value) + ")"
        text = [("–".join(str(x) for x in v) if isinstance(v, (list, tuple)) else str(v)) for v in value]
        return ", ".join(text[:12]) + (f" … ({len(text)} in all)" if len(text) > 12 else "")
    return str(value)


def stage_figures_table(figs: dict) -> str:
    """A stage's figures (metrics.json) as a table of figure, value and unit."""
    rows = []
    for key, value in figs.items():
        if key in _FIGURES_SHOWN_ELSEWHERE:
            continue
        label, unit = figure_name(key)
        text = figure_value(key, value, unit)
        if text is not None:
            rows.append(f"<tr><td>{html.escape(label)}</td><td>{html.escape(text)}</td>"
                        f"<td class=\"unit\">{html.escape(unit)}</td></tr>")
    return f'<table class="figures">{"".join(rows)}</table>' if rows else ""


def energy_table(before: dict, after: dict) -> str:
    """The joint fit's energy per term, before and after, with the change in per cent."""
    rows = []
    for term in dict.fromkeys([*before, *after]):
        b, a = before.get(term), after.get(term)
        change = 100 * (a - b) / b if isinstance(a, (int, float)) and isinstance(b, (int, float)) and b else None
        rows.append({"term": term.replace("_", " "), "before": b, "after": a, "change (%)": change})
    return table(rows, cls="figures")


def _stages_section(page: Page, out_dir: Path, metrics: dict) -> None:
    """Each stage's status and timings, then its figures (metrics.json) as a small table with units."""
    rows, cards = [], []
    for name in STAGE_ORDER:
        figs = metrics.get(name, {})
        status = "done" if (out_dir / name / "DONE.json").is_file() else ("started, unfinished" if (out_dir / name / "STARTED.json").is_file()
                                      else ("present" if (out_dir / name).is_dir() else "not run"))
        rows.append({"stage": name, "status": status, "time (s)": figs.get("seconds"),
                     "per frame (s)": figs.get("seconds_per_frame")})
        body = stage_figures_table(figs) if isinstance(figs, dict) else ""
        if body:
            cards.append(f'<div class="card"><h3>{html.escape(name)}</h3>{body}</div>')
        before, after = (figs.get(k) if isinstance(figs, dict) else None for k in ("energy_before", "energy_after"))
        if isinstance(before, dict) and isinstance(after, dict):
            cards.append(f'<div class="card"><h3>{html.escape(name)}: energy per term, before and after the fit</h3>'
                         + energy_table(before, after) + "</div>")
    total = sum(float(m.get("seconds", 0) or 0) for m in metrics.values() if isinstance(m, dict))
    page.add("stages", "Stages and timings", table(rows) + f"<p>total {total:.1f} s</p>"
             + (f'<div class="cards">{"".join(cards)}</div>' if cards else ""))


def _plus_minus(value, sigma) -> str | None:
    """"1.95 ± 1.23" (3 significant digits), the value alone without a finite sigma; None without a value."""
    if not isinstance(value, (int, float)) or not np.isfinite(value):
        return None
    text = f"{value:.3g}"
    return text + (f" ± {sigma:.2g}" if isinstance(sigma, (int, float)) and np.isfinite(sigma) else "")


def calibration_pairs_table(pairs: list[dict]) -> str:
    """The calibration check per camera pair: a few readable columns in mm and degrees, and a verdict."""
    rows = []
    for p in pairs:
        if p.get("flagged"):
            verdict = "disagrees: check the calibration"
        elif p.get("judged") is False:
            verdict = "too little overlap to judge"
        else:
            verdict = "agrees"
        if p.get("unobservable"):
            verdict += "; not constrained: " + "; ".join(str(u) for u in p["unobservable"])
        row = {"cameras": f"{p.get('cam_a')} – {p.get('cam_b')}", "overlap (points)": p.get("overlap_points"),
               "gap (mm)": p.get("median_distance_mm"), "residual (mm)": p.get("icp_rmse_mm"),
               "correction (mm)": _plus_minus(p.get("correction_translation_mm"), p.get("translation_sigma_mm")),
               "correction (°)": _plus_minus(p.get("correction_rotation_deg"), p.get("rotation_sigma_deg")),
               "verdict": verdict}
        rows.append({k: v for k, v in row.items() if v is not None})
    columns = [c for c in ("cameras", "overlap (points)", "gap (mm)", "residual (mm)", "correction (mm)",
                           "correction (°)", "verdict") if any(c in r for r in rows)]
    return table(rows, columns, "calib")


def _calibration_section(page: Page, out_dir: Path) -> None:
    """The calibration check of the prepare stage (and its check after refining the poses)."""
    calib = _json(out_dir / "prepare" / "calibration_check.json")
    if calib is None:
        page.not_run("calibration", "Calibration check", "no OUT/prepare/calibration_check.json (stage prepare)")
    else:
        flagged = calib.get("flagged") or []
        msg = (f'<p class="warn">{len(flagged)} camera pair(s) disagree by more than {calib.get("warn_mm")} mm: '
               "check the calibration</p>") if flagged else "<p>no camera pair flagged</p>"
        if calib.get("unchecked_cameras"):
            msg += (f'<p class="warn">not checked: {", ".join(calib["unchecked_cameras"])} (too little surface '
                    "shared with the other views; poses used as given)</p>")
        refined = _json(out_dir / "prepare" / "calibration_refined.json")
        after = calib.get("after_refinement")
        if refined is not None and after is not None:
            still = after.get("flagged") or []
            msg += ("<p>The cameras' poses were refined so all views' depth agrees (prepare.calib_refine); "
                    "every later stage used them (OUT/prepare/calibration_refined.json, a calibration.json):</p>"
                    + table([{"camera": c.get("name"), "moved (mm)": c.get("moved_mm"),
                              "turned (°)": c.get("turned_deg")} for c in refined.get("corrections") or []])
                    + "<p>The check again with the refined poses:</p>"
                    + calibration_pairs_table(after.get("pairs") or [])
                    + (f'<p class="warn">{len(still)} camera pair(s) still disagree: check the calibration</p>' if still
                       else "<p>no camera pair flagged after refining</p>"))
        page.add("calibration", "Calibration check",
                 f"<p>ICP between neighbouring cameras' clouds, frames {calib.get('frames')}</p>"
                 + calibration_pairs_table(calib.get("pairs") or [])
                 + '<p class="sub">gap: median distance between the two clouds where they overlap; residual: '
                 "ICP's RMS point-to-plane residual (the sensors' noise floor); correction: the part of ICP's move "
                 "the overlap constrains, ± one standard deviation</p>" + msg)


def _orientation_section(page: Page, figures: dict) -> None:
    """The object stage's orientation checks: per check, each axis-aligned orientation's E_O after its
    short fit, lowest first, and the margin between the two lowest (a small one: look at the overlays)."""
    checks = figures.get("orientation_hypotheses")
    if not checks:
        return
    rows = []
    for check in checks:
        fitted = [e for e in check.get("energies") or [] if e is not None]
        rows.append({"frame": check.get("frame"), "checked at": str(check.get("why", "")).replace("_", " "),
                     "lowest E_O": fitted[0] if fitted else None,
                     "next orientation": fitted[1] if len(fitted) > 1 else None,
                     "margin": fitted[1] / fitted[0] if len(fitted) > 1 and fitted[0] > 0 else None,
                     "E_O of the orientations fitted": ", ".join(f"{e:.3g}" for e in fitted)})
    page.add("orientations", "Object orientation checks",
             "<p>Where a track starts, where the object first moves and where E_O stays high, every "
             "axis-aligned turn of the mesh (its symmetries left out) is fitted and scored by E_O; the lowest "
             "wins. A margin near 1 means two orientations explain the views about equally well.</p>" + table(rows))


def write_report(out_dir, session=None, gt=None, cfg=None, progress: bool = True) -> Path:
    """Write OUT/report/index.html (and the overlay images and video beside it); returns its path.

    session: a Session or its path (default: found as `find_session` says); gt: a session folder
    with ground_truth/ for the evaluation section; cfg: an intercap Config (default: OUT/config.yaml
    when readable, else the defaults)."""
    start = time.perf_counter()
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise FileNotFoundError(f"results folder {out_dir} not found")
    if cfg is None:
        cfg = _report_config(out_dir)
    rcfg = cfg.report
    report_dir = out_dir / "report"
    report_dir.mkdir(parents=True, exist_ok=True)
    session = find_session(out_dir, session, gt)
    if gt is None and session is not None and (Path(session.root) / "ground_truth").is_dir():
        gt = session.root  # the session carries its own ground truth (synthetic or annotated)
    page = Page()
    metrics = _json(out_dir / "metrics.json") or {}
    steps = ["summary", "overlays", "curves", "contact", "penetration", "motion", "physics", "evaluation"]
    bar = tqdm(total=len(steps), desc="report", unit="section", disable=not progress)
    bar.set_postfix_str(steps[0])

    _summary_section(page, session, report_dir)
    _stages_section(page, out_dir, metrics)
    _calibration_section(page, out_dir)
    _orientation_section(page, metrics.get("object") or {})
    _advance(bar, steps)

    # overlays
    stages = {s: load_stage_meshes(out_dir, s) for s in OVERLAY_STAGES}
    if session is None:
        page.not_run("overlays", "Mesh overlays", "needs the session's colour images")
    else:
        page.add("overlays", "Mesh overlays", _overlays_section(session, out_dir, report_dir, stages, rcfg, progress))
    _advance(bar, steps)

    T = session.num_frames if session is not None else _frames_in(stages)
    fids = np.asarray(session.frame_ids) if session is not None else np.arange(T)
    fps = session.fps if session is not None else 30.0
    frames = frame_sample(T, rcfg.max_frames)
    mesh = surface = None
    if session is not None and session.object is not None:
        from intercap.geometry.surfaces import TriangleSurface

        mesh = session.object.load_mesh()
        surface = TriangleSurface(mesh.vertices, mesh.faces)

    page.add("curves", "Per-frame fit", _fit_section(session, out_dir, stages, frames, T, fids, mesh, rcfg))
    _advance(bar, steps)
    page.add("contact", "Contact", _contact_section(out_dir, stages, frames, fids, mesh, rcfg))
    _advance(bar, steps)
    page.add("penetration", "Penetration", _penetration_section(stages, frames, fids, surface, out_dir, gt))
    _advance(bar, steps)
    page.add("motion", "Motion (acceleration)", fit_against_data_warning(metrics.get("global") or {}, cfg, fps)
             + unsynchronised_warning(metrics.get("global") or {}, cfg)
             + _motion_section(stages, frames, fids, fps, mesh, gt))
    _advance(bar, steps)
    physics = _npz(out_dir / "physics" / "physics.npz")
    if physics is None:
        page.not_run("physics", "Physics", "no OUT/physics/physics.npz (stage physics)")
    else:
        page.add("physics", "Physics", physics_section(physics, fids))
    _advance(bar, steps)
    if gt is not None:
        page.add("evaluation", "Evaluation against ground truth", _evaluation_section(out_dir, gt, fids))
    else:
        page.not_run("evaluation", "Evaluation against ground truth",
                     "the session has no ground_truth/ folder and none was given (--gt SESSION)")
    _advance(bar, steps)
    bar.close()

    seconds = time.perf_counter() - start
    title = f"intercap report: {Path(session.root).name if session is not None else out_dir.name}"
    subtitle = f"{out_dir.resolve()} · written {time.strftime('%Y-%m-%d %H:%M:%S')} in {seconds:.1f} s"
    path = report_dir / "index.html"
    tmp = report_dir / ".index.html.part"
    tmp.write_text(page.render(title, subtitle), encoding="utf-8")
    tmp.replace(path)
    log.info("report: %s (%.1f s)", path, seconds)
    return path


def _advance(bar, steps: list[str]) -> None:
    """Count a finished section on the progress bar and name the next (the evaluation can take a while)."""
    bar.update(1)
    if bar.n < len(steps):
        bar.set_postfix_str(steps[bar.n])


def _frames_in(stages: dict) -> int:
    for m in stages.values():
        if m is not None:
            return m.num_frames
    return 0


def _overlays_section(session, out_dir, report_dir, stages, rcfg, progress) -> str:
    from intercap.evaluation.overlays import OverlayRenderer, render_overlays

    parts = []
    wanted = [s for s in OVERLAY_STAGES if s in rcfg.overlay_stages]
    ran = [s for s in wanted if stages.get(s) is not None]
    video_stage = ran[-1] if ran and rcfg.video else None
    renderer = None
    try:
        for stage in wanted:
            if stages.get(stage) is None:
                parts.append(f'<h3>{stage}</h3><p class="notrun">not run</p>')
                continue
            if renderer is None:
                mesh = session.object.load_mesh() if session.object is not None else None
                renderer = OverlayRenderer(session.cameras, mesh)
            res = render_overlays(session, out_dir, stage, report_dir, every=rcfg.overlay_every, alpha=rcfg.alpha,
                                  video_camera=rcfg.video_camera or 0, video=stage == video_stage,
                                  renderer=renderer, progress=progress, codec=rcfg.video_codec)
            html_part = f"<h3>{stage}</h3>"
            if res.get("video"):
                rel = html.escape(res["video"])
                html_part += (f'<p><video controls loop muted preload="auto" '
                              f'width="{min(640, session.cameras[0].width * 2)}" src="{rel}"></video><br>'
                              f'<a href="{rel}">{rel}</a> (the whole sequence, one camera)</p>')
            if res.get("iou"):
                html_part += ("<p>silhouette IoU with the session's masks (drawn frames, all views): "
                              + ", ".join(f"{k} {v:.3f}" for k, v in res["iou"].items()) + "</p>")
            html_part += _overlay_strip(report_dir, res.get("images", []), rcfg.thumbnail_width)
            parts.append(html_part)
    finally:
        if renderer is not None:
            renderer.close()
    legend = ('<p class="sub">body blue, object green, body regions touching the object (OUT/contact) red; '
              f"every {rcfg.overlay_every}-th frame, every camera; click a thumbnail for the full image</p>")
    return legend + "".join(parts)


def _fit_section(session, out_dir, stages, frames, T, fids, mesh, rcfg) -> str:
    parts = []
    body_stages = {s: stages[s] for s in ("body", "global") if stages.get(s) is not None
                   and stages[s].body_vertices is not None}
    # keypoint reprojection
    series = {}
    if session is not None:
        for s in body_stages:
            kp = out_dir / s / "keypoints3d.npy"
            if kp.is_file():
                series[s] = reprojection_px(session, out_dir, np.load(kp, mmap_mode="r"), frames)
    if series:
        parts.append(curves("2D keypoint reprojection error (mean over confident joints, all views)", "px",
                            series, fids))
    else:
        parts.append('<p class="notrun">keypoint reprojection: not run (no body fit or no session)</p>')
    # cloud to fit
    if session is not None:
        pts = depth_points(session, frames, rcfg.points_per_view)
        series = {}
        if pts is not None:
            for s, m in body_stages.items():
                series[f"{s}: person points to body"] = cloud_to_fit_mm(pts, T, m.body_vertices, m.body_faces)[0]
            for s in ("object", "global"):
                m = stages.get(s)
                if m is not None and m.object_R is not None and mesh is not None:
                    series[f"{s}: object points to object"] = cloud_to_fit_mm(pts, T, R=m.object_R, t=m.object_t, mesh=mesh)[1]
        if series:
            parts.append(curves("Depth cloud to fitted surface (median over masked depth points)", "mm", series, fids))
        else:
            parts.append('<p class="notrun">cloud-to-fit: not run (no masks or no fit)</p>')
    # object confidence and trusted frames
    obj = _npz(out_dir / "object" / "object_poses.npz")
    if obj is not None and "confidence" in obj:
        plt = _plt()
        fig, ax = plt.subplots(figsize=(10, 2.8))
        ax.plot(fids[:len(obj["confidence"])], obj["confidence"], color="tab:green", marker=".", label="confidence")
        valid = obj.get("valid", np.isfinite(obj["R"]).all((1, 2)))
        for i in np.flatnonzero(~np.asarray(valid, bool)):
            ax.axvspan(fids[i] - 0.5, fids[i] + 0.5, color="tab:red", alpha=0.25, lw=0)
        ax.set_ylim(0, 1.02)
        ax.set_title("Object tracking confidence (mean silhouette IoU); red: untrusted frames", fontsize=10)
        ax.set_xlabel("frame")
        ax.grid(alpha=0.3)
        parts.append(figure_html(fig, "object confidence"))
    else:
        parts.append('<p class="notrun">object confidence: not run (stage object)</p>')
    rows = {}
    if obj is not None:
        rows["object"] = np.asarray(obj.get("valid", np.isfinite(obj["R"]).all((1, 2))), bool)
    for s in ("body", "global"):
        p = _npz(out_dir / s / "body_params.npz")
        if p is not None and "valid" in p:
            rows[f"{s} body"] = np.asarray(p["valid"], bool)
    g = _npz(out_dir / "global" / "object_poses.npz")
    if g is not None and "valid" in g:
        rows["global object"] = np.asarray(g["valid"], bool)
    if rows:
        parts.append(_raster("Trusted (green) and untrusted (red) frames", rows, fids, ("#d9534f", "#5cb85c")))
    return "".join(parts)


def _raster(title: str, rows: dict[str, np.ndarray], fids: np.ndarray, colours=("#eeeeee", "#d9534f")) -> str:
    """A timeline of boolean rows (one per name)."""
    plt = _plt()
    from matplotlib.colors import ListedColormap

    fig, ax = plt.subplots(figsize=(10, 0.45 * len(rows) + 1.0))
    data = np.stack([np.asarray(v, float)[:len(fids)] for v in rows.values()])
    ax.imshow(data, aspect="auto", cmap=ListedColormap(list(colours)), vmin=0, vmax=1, interpolation="nearest",
              extent=(fids[0] - 0.5, fids[0] + data.shape[1] - 0.5, len(rows) - 0.5, -0.5))
    ax.set_yticks(range(len(rows)))
    ax.set_yticklabels(list(rows), fontsize=8)
    ax.set_xlabel("frame")
    ax.set_title(title, fontsize=10)
    return figure_html(fig, title)


def _final_stage(stages) -> tuple[str, object] | tuple[None, None]:
    """The most refined stage with both a body and object poses (global), else body with the object stage's poses."""
    g = stages.get("global")
    if g is not None and g.body_vertices is not None and g.object_R is not None:
        return "global", g
    b, o = stages.get("body"), stages.get("object")
    if b is not None and b.body_vertices is not None and o is not None:
        from intercap.evaluation.overlays import StageMeshes

        return "body", StageMeshes("body", b.body_vertices, b.body_faces, o.object_R, o.object_t)
    return None, None


def _contact_section(out_dir, stages, frames, fids, mesh, rcfg) -> str:
    parts = []
    contact = _npz(out_dir / "contact" / "contact.npz")
    if contact is None:
        parts.append('<p class="notrun">contact timeline: not run (stage contact)</p>')
    else:
        names = [str(n) for n in contact.get("region_names", [])]
        rows = {"contact (" + str(contact.get("method", "")) + ")": contact["contact"]}
        for k, n in enumerate(names):
            rows[n] = contact["region_contact"][:, k]
        for key in ("annotated", "overlap_2d", "distance_3d"):
            if key in contact:
                rows[f"source: {key}"] = contact[key]
        if "held" in contact and np.asarray(contact["held"]).any():  # `contact.held_frames`
            rows["source: held (no fall)"] = contact["held"]
        if "carried" in contact and np.asarray(contact["carried"]).any():  # `contact.carried_gaps`
            rows["source: carried (short gap)"] = contact["carried"]
        parts.append(_raster("Contact per frame and body region", rows, fids))
        dist = contact.get("region_distance_m")
        if dist is not None and dist.size:
            near = {n: np.clip(dist[:, k] * 1000, 0, None) for k, n in enumerate(names)
                    if np.nanmin(np.r_[dist[:, k], np.inf]) < 0.3}
            if near:
                parts.append(curves("Body region to object surface distance (regions that come within 30 cm)",
                                    "mm (symlog)", near, fids, log_y=True))
    name, final = _final_stage(stages)
    if final is None or mesh is None:
        parts.append('<p class="notrun">contact heat map: not run (needs a body fit and object poses)</p>')
        return "".join(parts)
    on = frames
    if contact is not None:
        on = frames[np.asarray(contact["contact"], bool)[frames]]
    freq = vertex_contact_frequency(final.body_vertices, final.object_R, final.object_t, mesh, on,
                                    rcfg.heatmap_distance_m) if len(on) else None
    if freq is None or not freq.any():
        parts.append('<p class="sub">contact heat map: no body vertex within '
                     f'{rcfg.heatmap_distance_m * 1000:.0f} mm of the object in any contact frame</p>')
        return "".join(parts)
    rest = contact.get("rest_vertices") if contact is not None else None
    where = "the rest mesh"
    if rest is None or len(rest) != len(freq):
        best = on[int(np.argmax([np.isfinite(np.asarray(final.body_vertices[i][:1])).all() for i in on]))]
        rest, where = np.asarray(final.body_vertices[best]), f"the fitted mesh of frame {fids[best]} (no rest mesh saved)"
    try:
        names = [str(n) for n in contact.get("region_names", [])] if contact is not None else []
        feet = None
        if "region_vertex_ids" in (contact or {}) and any(n.endswith("_foot") for n in names):
            ids = np.split(contact["region_vertex_ids"], np.cumsum(contact["region_sizes"])[:-1])
            feet = np.concatenate([ids[k] for k, n in enumerate(names) if n.endswith("_foot")])
        png = heatmap_image(rest, final.body_faces, freq, feet=feet)
        parts.append(f'<img class="fig" alt="contact heat map" src="{png_data_uri(png)}">')
    except Exception as exc:  # noqa: BLE001 - rendering trouble must not lose the rest of the report
        log.warning("report: contact heat map not rendered (%s)", exc)
        parts.append(f'<p class="warn">contact heat map not rendered: {html.escape(str(exc))}</p>')
    parts.append(f'<p class="sub">vertex contact frequency ({name} result): share of the {len(on)} contact frames in '
                 f"which a vertex lies within {rcfg.heatmap_distance_m * 1000:.0f} mm of the object, on {where}</p>")
    return "".join(parts)


def _gt_arrays(gt) -> dict:
    if gt is None:
        return {}
    folder = Path(gt) / "ground_truth"
    out = {}
    if (folder / "body_vertices.npy").is_file():
        out["body_vertices"] = np.load(folder / "body_vertices.npy", mmap_mode="r")
    z = _npz(folder / "object_poses.npz")
    if z is not None:
        out["R"], out["t"] = z["R"].astype(np.float64), z["t"].astype(np.float64)
    if (folder / "contact.npy").is_file():
        out["contact"] = np.load(folder / "contact.npy").astype(bool)
    return out


def _penetration_section(stages, frames, fids, surface, out_dir, gt) -> str:
    if surface is None:
        return '<p class="notrun">not run: no object mesh (session unknown or body-only)</p>'
    series = {}
    b, o, g = stages.get("body"), stages.get("object"), stages.get("global")
    if b is not None and b.body_vertices is not None and o is not None:
        series["body (per-frame fits)"] = penetration_mm(b.body_vertices, o.object_R, o.object_t, surface, frames)
    if g is not None and g.body_vertices is not None and g.object_R is not None:
        series["global"] = penetration_mm(g.body_vertices, g.object_R, g.object_t, surface, frames)
    gta = _gt_arrays(gt)
    if series and "body_vertices" in gta and "R" in gta:  # beside a fit; alone it says nothing of the run
        series["gt"] = penetration_mm(gta["body_vertices"], gta["R"], gta["t"], surface, frames)
    if not series:
        return '<p class="notrun">not run: needs a body fit and object poses</p>'
    parts = [curves("Deepest body vertex inside the object, per frame", "mm", series, fids)]
    contact = _npz(out_dir / "contact" / "contact.npz")
    on = np.asarray(contact["contact"], bool) if contact is not None else gta.get("contact")
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5, 3.2))
    rows = []
    colour = series_colours(list(series))
    for name, d in series.items():
        sel = d[on] if on is not None and on.any() else d
        sel = np.sort(sel[np.isfinite(sel)])
        if not len(sel):
            continue
        ax.step(sel, np.arange(1, len(sel) + 1) / len(sel), where="post", label=name, color=colour[name])
        rows.append({"result": name, "frames": len(sel), "mean (mm)": float(sel.mean()),
                     "median (mm)": float(np.median(sel)), "max (mm)": float(sel.max()),
                     "frames over 5 mm (%)": float(100 * (sel > 5).mean())})
    ax.set_xlabel("penetration depth (mm)")
    ax.set_ylabel("fraction of frames")
    ax.set_title("Penetration CDF" + (" (contact frames)" if on is not None and on.any() else ""), fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    parts.append(figure_html(fig, "penetration CDF"))
    parts.append(table(rows))
    return "".join(parts)


def fit_against_data_warning(global_metrics: dict, cfg, fps: float) -> str:
    """A warning paragraph when the joint fit raised the keypoints' energy past
    `global.max_keypoint_energy_ratio` (the motion terms and the data disagree: often a wrong fps)."""
    ratio, limit = global_metrics.get("keypoint_energy_ratio"), cfg.global_.max_keypoint_energy_ratio
    if ratio is None or limit <= 0 or ratio <= limit:
        return ""
    from intercap.evaluation.warnings import data_disagreement

    text = data_disagreement(ratio, fps)
    return f'<p class="warn">{html.escape(text[0].upper() + text[1:], quote=False)}.</p>'


def unsynchronised_warning(global_metrics: dict, cfg) -> str:
    """A warning paragraph naming cameras whose frames lag or lead the others' past
    `global.max_camera_offset_ms` (calib.time_offsets)."""
    from intercap.evaluation.warnings import unsynchronised

    text = unsynchronised(global_metrics.get("camera_time_offsets_ms") or {}, cfg.global_.max_camera_offset_ms)
    return f'<p class="warn">Cameras {html.escape(text, quote=False)}.</p>' if text else ""


def _motion_section(stages, frames, fids, fps, mesh, gt) -> str:
    body, obj = {}, {}
    for s in ("body", "global"):
        m = stages.get(s)
        if m is not None and m.body_vertices is not None:
            body[s] = vertex_acceleration(m.body_vertices, fps, frames)
    for s in ("object", "global"):
        m = stages.get(s)
        if m is not None and m.object_R is not None and mesh is not None:
            obj[s] = vertex_acceleration(posed(np.asarray(mesh.vertices), m.object_R, m.object_t), fps, frames)
    gta = _gt_arrays(gt)
    if body and "body_vertices" in gta:
        body["gt"] = vertex_acceleration(gta["body_vertices"], fps, frames)
    if obj and "R" in gta and mesh is not None:
        obj["gt"] = vertex_acceleration(posed(np.asarray(mesh.vertices), gta["R"], gta["t"]), fps, frames)
    parts = []
    for title, series in (("Body: mean vertex acceleration", body), ("Object: mean vertex acceleration", obj)):
        if series:
            parts.append(curves(title, "m/s²", series, fids))
        else:
            parts.append(f'<p class="notrun">{title}: not run</p>')
    return "".join(parts)


def physics_section(physics: dict, fids: np.ndarray) -> str:
    series = {}
    names = {"hand_force": ("left hand", "right hand"), "foot_force": ("left foot", "right foot")}
    for key, labels in names.items():
        if key in physics and physics[key].ndim == 3:
            for k, label in enumerate(labels):
                series[f"{label} |F|"] = np.linalg.norm(physics[key][:, k], axis=-1)
    for key, label in (("object_ground_force", "object-ground |F|"), ("residual_force", "root residual |F|"),
                       ("object_residual_force", "object residual |F|")):
        if key in physics and physics[key].ndim == 2:
            series[label] = np.linalg.norm(physics[key], axis=-1)
    if not series:
        return '<p class="notrun">physics.npz holds none of the force arrays</p>'
    T = len(next(iter(series.values())))
    pf = np.asarray(physics.get("frame_ids", fids[:T]))
    parts = [curves("Forces (N)", "N", series, pf, colours=PHYSICS_COLOURS,
                    styles={n: "--" for n in series if "residual" in n})]
    facts = [f"{k.split('_')[0]} mass: {float(physics[k]):.3g} kg" for k in ("body_mass_kg", "object_mass_kg")
             if k in physics]
    if "valid" in physics:
        facts.append(f"valid frames: {int(np.asarray(physics['valid'], bool).sum())}/{len(physics['valid'])}")
    if "flight_episodes" in physics and len(physics["flight_episodes"]):
        rows = [{"first": int(a), "last": int(b)} for a, b in physics["flight_episodes"]]
        for r, k in zip(rows, range(len(rows))):
            if "flight_gravity_angle_deg" in physics:
                r["angle to gravity (deg)"] = float(physics["flight_gravity_angle_deg"][k])
            if "flight_acceleration" in physics:
                r["|a| m/s²"] = float(np.linalg.norm(physics["flight_acceleration"][k]))
        facts.append("free-flight episodes:" + table(rows))
    if len(physics.get("flight_runs_held", ())):
        facts.append("touching nothing by the contact labels, but not falling (a missed contact, not a flight): "
                     + ", ".join(f"frames {int(a)}-{int(b)}" for a, b in physics["flight_runs_held"]))
    return "".join(parts) + "<p>" + "<br>".join(facts) + "</p>"


_METRIC_GROUPS = {"keypoint": "body", "hand": "body", "jitter": "motion", "penetration": "contact"}


def metrics_table(metrics: dict) -> str:
    """The evaluation's figures in small tables by subject (body, object, contact, ...): a readable
    name (the key in its title), the value and its unit."""
    groups: dict[str, list[str]] = {}
    for key, value in metrics.items():
        first = key.split("_")[0]
        group = _METRIC_GROUPS.get(first, first)
        label, unit = figure_name(key)
        if group == first and group not in ("body", "contact", "frames") and label.startswith(first + " "):
            label = label[len(first) + 1:]  # "physics foot skating" under "physics"
        text = figure_value(key, value, unit)
        groups.setdefault(group, []).append(
            f'<tr><td title="{html.escape(key)}">{html.escape(label)}</td><td>{html.escape(text or "–")}</td>'
            f'<td class="unit">{html.escape(unit)}</td></tr>')
    cards = [f'<div class="card"><h3>{html.escape(g)}</h3><table class="figures">{"".join(rows)}</table></div>'
             for g, rows in groups.items()]
    return f'<div class="cards">{"".join(cards)}</div>'


def _evaluation_section(out_dir: Path, gt, fids) -> str:
    from intercap.evaluation.evaluate import RESULT_FILES, evaluate
    from intercap.evaluation.table import write_json

    cached = out_dir / "eval.json"
    newest = max([(out_dir / f).stat().st_mtime for f in RESULT_FILES if (out_dir / f).is_file()], default=0.0)
    saved = _json(cached) if cached.is_file() and cached.stat().st_mtime > newest else None
    if saved is not None and saved.get("gt") == str(Path(gt).resolve()):
        metrics, per_frame, notes = saved["metrics"], saved["per_frame"], saved.get("notes", [])
        notes = notes + [f"figures from {cached} (newer than the results)"]
    else:
        try:
            result = evaluate(out_dir, gt)
        except (FileNotFoundError, ValueError) as exc:
            return f'<p class="notrun">not run: {html.escape(str(exc))}</p>'
        except Exception as exc:  # noqa: BLE001 - an evaluation failure must not lose the rest of the report
            log.warning("report: evaluation against %s failed (%s)", gt, exc)
            return f'<p class="warn">evaluation failed: {html.escape(str(exc))}</p>'
        metrics, per_frame, notes = result.metrics, result.per_frame, result.notes
        write_json(result, cached)  # what `intercap eval` writes, so the next report reuses it
        data = json.loads(cached.read_text())
        cached.write_text(json.dumps({**data, "gt": str(Path(gt).resolve())}, indent=2) + "\n")
    parts = [metrics_table(metrics)]
    pf = {k: np.asarray([np.nan if x is None else x for x in v], float) for k, v in per_frame.items() if k != "frame"}
    groups = (("Body error over time", "mm", ("body_surface_mm", "keypoint_mpjpe_mm", "hand_keypoint_mm")),
              ("Object error over time", "mm", ("object_add_mm", "object_adds_mm", "object_translation_mm")),
              ("Object rotation error over time", "degrees", ("object_rotation_deg", "object_rotation_sym_deg")),
              ("Penetration on ground-truth contact frames", "mm", ("penetration_mm",)))
    palette = ("tab:blue", "tab:orange", "tab:green")
    for title, unit, keys in groups:
        series = {figure_name(k)[0]: pf[k] for k in keys if k in pf}
        if series:
            parts.append(curves(title, unit, series, fids, colours=dict(zip(series, palette)),
                                styles={n: "-" for n in series}))
    if notes:
        parts.append("<ul>" + "".join(f"<li>{html.escape(n)}</li>" for n in notes) + "</ul>")
    return "".join(parts)
