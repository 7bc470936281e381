"""Train the learned motion smoothness priors (intercap/energies/motion_prior.py) on the CMU mocap in ../shared/data.

    python tools/train_motion_prior.py                  # both priors, writes intercap/data/motion_prior_*.npz
    python tools/train_motion_prior.py --cache /tmp/cmu_markers.npz   # keep the retargeted markers for reruns

Steps:
1. Markers on anny's rest mesh (neutral phenotype), left-right symmetric: body markers by
   farthest-point sampling of the left half (no eyes, fingers) mirrored, plus the midline;
   hand markers on the back of the hand and the palm (wrist and metacarpal skin, no fingers) of
   the right hand, mirrored for the left; small vertex groups at the hips, neck and wrists for
   the heading frame and the wrist point.
2. Every clip read at 60 fps (every 2nd of 120 fps frames), solver glitches flagged
   (`cmu_mocap.glitch_frames`), retargeted to anny (`cmu_mocap.retarget_to_anny`, root
   translation from CMU's forward kinematics) and skinned at the marker vertices only (linear
   blend skinning of anny, checked against the full model).
3. Both 30 fps phases (even and odd 60 fps frames) of every glitch-free stretch of at least
   WINDOW frames become training sequences: velocity features of intercap.energies.motion_prior (heading
   frame, m/s), plus their left-right mirror images.
4. A temporal convolutional autoencoder per prior: loss = reconstruction MSE of the clean windows
   and of jittered copies (i.i.d. position jitter, sigma up to --noise-mm) + w_smooth * mean
   ||z_{t+1} - z_t||^2 + w_scale * (per-channel latent variance - 1)^2, the last two on the clean
   windows only (the variance term stops the encoder from shrinking its code to make it look
   smooth; reconstructing the jitter stops it from filtering the jitter away). Held-out clips (one
   per subject) are only scored.
5. Only the encoder ships (float16), with the marker layout, the input normalisation and a
   short held-out example motion that the tests use.

Data credit: "The data used in this project was obtained from mocap.cs.cmu.edu.
The database was created with funding from NSF EIA-0196217."
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from intercap.energies import motion_prior as mp  # noqa: E402
from tools import cmu_mocap  # noqa: E402

DEFAULT_DATA = ROOT.parent / "shared" / "data" / "cmu_mocap"
HELD_OUT = ("01_09", "02_01", "03_04")  # as the pose prior: playground, walk, uneven terrain
EXAMPLE_CLIP = "03_04"
STEP = 2  # 120 fps -> 60 fps; the two 30 fps phases are its even and odd frames
WINDOW = 48  # frames (30 fps) per training window
REF_VERTICES = 12  # vertices averaged for the hip, neck and wrist points
UP = torch.tensor([0.0, 0.0, 1.0])  # anny model axes (CMU y-up converted), the training up
SETTINGS = {  # per prior: markers, network and training
    "body": dict(left_markers=26, mid_markers=6, channels=(192,), latent=96, kernel=3),
    "hand": dict(markers=10, channels=(64,), latent=32, kernel=3),
}


# ----------------------------------------------------------------------------- marker layout
def rest_geometry(model) -> tuple[np.ndarray, np.ndarray, list[str], np.ndarray]:
    """(rest vertices (V, 3), bone heads (J, 3), bone labels, dominant bone per vertex (V,)), model axes."""
    rest = model.core(None, None)
    vertices = rest["vertices"][0].detach().double().numpy()
    heads = rest["bone_poses"][0, :, :3, 3].detach().double().numpy()
    dominant = model.core.dense_vertex_bone_weights.detach().numpy().argmax(1)
    return vertices, heads, list(model.joint_names), dominant


def farthest_points(points: np.ndarray, count: int) -> np.ndarray:
    """Greedy farthest-point sampling started at the highest point (deterministic): ids into points."""
    chosen = [int(np.argmax(points[:, 2]))]
    dist = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(1, count):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return np.array(chosen)


def marker_layout(model) -> dict[str, dict[str, np.ndarray]]:
    """anny vertex ids of every point group of both priors, and the body's mirror permutation."""
    V, heads, labels, dominant = rest_geometry(model)
    mirror = cKDTree(V).query(V * np.array([-1.0, 1.0, 1.0]))[1]  # vertex -> its mirror image (anny is symmetric)
    bone = np.array(labels)[dominant]
    excluded = np.array([b.startswith(("eye", "finger", "metacarpal")) for b in bone])
    left = np.flatnonzero(~excluded & (V[:, 0] > 0.02))
    mid = np.flatnonzero(~excluded & (np.abs(V[:, 0]) < 1e-3))
    s = SETTINGS["body"]
    body_left = left[farthest_points(V[left], s["left_markers"])]
    body_mid = mid[farthest_points(V[mid], s["mid_markers"])]
    body = np.concatenate([body_left, mirror[body_left], body_mid])
    n = len(body_left)
    body_mirror = np.concatenate([np.arange(n, 2 * n), np.arange(n), np.arange(2 * n, len(body))])

    def near(label: str) -> np.ndarray:
        return np.argsort(np.linalg.norm(V - heads[labels.index(label)], axis=1))[:REF_VERTICES]

    hip_l = near("upperleg01.L")
    neck = near("neck01")
    hand_r = np.flatnonzero(np.isin(bone, ["wrist.R"] + [f"metacarpal{k}.R" for k in range(1, 5)]))
    hand_r = hand_r[farthest_points(V[hand_r], SETTINGS["hand"]["markers"])]
    wrist_r = near("wrist.R")
    common = dict(hip_L=hip_l, hip_R=mirror[hip_l], neck=neck)
    return {
        "body": dict(markers=body, mirror=body_mirror, **common),
        "hand": dict(markers_R=hand_r, markers_L=mirror[hand_r], wrist_R=wrist_r, wrist_L=mirror[wrist_r], **common),
    }


def compact_layout(groups: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Point groups as anny vertex ids -> point_ids (U,) plus every group as ids into point_ids."""
    point_ids = np.unique(np.concatenate([g for k, g in groups.items() if k != "mirror"]))
    where = {v: i for i, v in enumerate(point_ids)}
    out = {"point_ids": point_ids.astype(np.int64)}
    for k, g in groups.items():
        out[k] = g.astype(np.int64) if k == "mirror" else np.array([where[v] for v in g], np.int64)
    return out


# ----------------------------------------------------------------------------- skinning at markers
class MarkerSkinner:
    """anny at a few vertices only: linear blend skinning of the neutral rest shape (world coordinates)."""

    def __init__(self, model, vertex_ids: np.ndarray):
        core = model.core
        self.model = model
        params = model.init_params(1)
        with torch.no_grad():
            _, phen, local, face = core.get_tensor_inputs(None, params.shape, None, params.expression)
            coeffs = core._get_phenotype_blendshape_coefficients(phen, local, face)
            rest = core.get_rest_model(coeffs)
        self.rest_bone_poses = rest["rest_bone_poses"]
        ids = torch.as_tensor(vertex_ids)
        self.rest_points = rest["rest_vertices"][0, ids]  # (N, 3)
        self.weights = core.dense_vertex_bone_weights[ids]  # (N, J)

    def points(self, body_pose: torch.Tensor, orient: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
        """Differentiable: (B, 65, 3), (B, 3), (B, 3) -> (B, N, 3) world points."""
        params = self.model.init_params(body_pose.shape[0])
        params.body_pose, params.global_orient, params.transl = body_pose, orient, transl
        rot = self.model.bone_rotations(params)  # (B, J, 3, 3)
        bottom = rot.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(*rot.shape[:2], 1, 4)
        H = torch.cat([torch.cat([rot, rot.new_zeros(*rot.shape[:2], 3, 1)], -1), bottom], -2)  # (B, J, 4, 4)
        transforms, _ = self.model.core.get_bone_transforms(H, self.rest_bone_poses)
        blend = torch.einsum("nj,bjik->bnik", self.weights, transforms[..., :3, :])  # (B, N, 3, 4)
        points = (blend[..., :3] * self.rest_points[None, :, None, :]).sum(-1) + blend[..., 3]
        return self.model.to_world(points, params)

    @torch.no_grad()
    def __call__(self, body_pose: np.ndarray, orient: np.ndarray, transl: np.ndarray, chunk: int = 1024) -> np.ndarray:
        """(T, 65, 3), (T, 3), (T, 3) -> (T, N, 3) float32 world points."""
        t = lambda a: torch.from_numpy(np.ascontiguousarray(a)).float()  # noqa: E731
        return np.concatenate([
            self.points(t(body_pose[s:s + chunk]), t(orient[s:s + chunk]), t(transl[s:s + chunk])).numpy()
            for s in range(0, len(body_pose), chunk)
        ])


def read_clip(asf: Path, amc: Path, rest: cmu_mocap.AnnyRest, skinner: MarkerSkinner):
    """One clip at 60 fps: (points (T, N, 3), glitch (T,) bool, body_pose, orient, transl)."""
    skeleton, motion = cmu_mocap.load_clip(asf, amc, step=1)
    glitch = cmu_mocap.glitch_frames(skeleton, motion)
    motion = {k: v[::STEP] for k, v in motion.items()}
    glitch = glitch[: len(glitch) // STEP * STEP].reshape(-1, STEP).any(1)[: len(motion["root"])]
    glitch = np.pad(glitch, (0, len(motion["root"]) - len(glitch)), constant_values=True)
    names, ends, G = cmu_mocap.forward_kinematics(skeleton, motion)
    body, orient = cmu_mocap.retarget_to_anny(skeleton, G, rest)
    transl = (ends[:, 0] @ cmu_mocap.CMU_TO_ANNY.T).astype(np.float32)
    return skinner(body, orient, transl), glitch, body, orient, transl


def good_stretches(glitch: np.ndarray, min_len: int) -> list[tuple[int, int]]:
    """[start, end) runs of frames without glitches, at least min_len long."""
    runs, start = [], None
    for t, bad in enumerate(np.append(glitch, True)):
        if not bad and start is None:
            start = t
        elif bad and start is not None:
            if t - start >= min_len:
                runs.append((start, t))
            start = None
    return runs


def load_sequences(data: Path, model, point_ids: np.ndarray, cache: Path | None, only: tuple[str, ...] = ()):
    """clip -> list of 30 fps point sequences (T, N, 3) without glitches (clips in `only`, or all); the example
    motion (anny parameters of 45 held-out frames) and frame counts. A cache file keeps all clips."""
    if cache is not None and cache.exists():
        stored = np.load(cache, allow_pickle=False)
        if np.array_equal(stored["point_ids"], point_ids):
            clips = {}
            for key in stored.files:
                if key.startswith("seq/") and (not only or key.split("/")[1] in only):
                    clips.setdefault(key.split("/")[1], []).append(stored[key])
            example = {k[len("example/"):]: stored[k] for k in stored.files if k.startswith("example/")}
            return clips, example, {k: int(v) for k, v in zip(stored["count_names"], stored["counts"])}
    rest = cmu_mocap.AnnyRest.from_model(model)
    skinner = MarkerSkinner(model, point_ids)
    clips, example, counts = {}, {}, {"frames_60fps": 0, "glitch_frames_60fps": 0}
    for asf, amc in cmu_mocap.list_clips(data):
        if only and cache is None and amc.stem not in only:
            continue
        points, glitch, body, orient, transl = read_clip(asf, amc, rest, skinner)
        counts["frames_60fps"] += len(glitch)
        counts["glitch_frames_60fps"] += int(glitch.sum())
        seqs = []
        for a, b in good_stretches(glitch, 2 * WINDOW):
            for phase in range(2):  # 60 -> 30 fps, both phases
                seqs.append(points[a + phase:b:2])
        clips[amc.stem] = seqs
        if amc.stem == EXAMPLE_CLIP:  # 1.5 s of held-out walking at 30 fps, for the tests
            a = good_stretches(glitch, 4 * WINDOW)[0][0] + 2 * WINDOW
            keep = slice(a, a + 90, 2)
            example = dict(body_pose=body[keep], global_orient=orient[keep], transl=transl[keep])
    if cache is not None:
        arrays = {f"seq/{c}/{k}": s for c, seqs in clips.items() for k, s in enumerate(seqs)}
        arrays.update({f"example/{k}": v for k, v in example.items()})
        np.savez(cache, point_ids=point_ids, count_names=np.array(list(counts)), counts=np.array(list(counts.values())),
                 **arrays)
    if only:
        clips = {c: q for c, q in clips.items() if c in only}
    return clips, example, counts


# ----------------------------------------------------------------------------- features, model
def make_prior(kind: str, layout: dict[str, np.ndarray], channels, kernel, num_vertices, mean=None, std=None):
    n = 3 * len(layout["markers"] if kind == "body" else layout["markers_R"])
    arrays = dict(layout, feature_mean=np.zeros(n, np.float32) if mean is None else mean,
                  feature_std=np.ones(n, np.float32) if std is None else std)
    return mp.MotionPrior(kind, arrays, channels, kernel, num_vertices)


def raw_features(prior: mp.MotionPrior, seqs: list[np.ndarray], mirror: np.ndarray | None) -> list[torch.Tensor]:
    """Velocity features (3M, T-1) of every sequence (unnormalised prior), plus mirror images."""
    out = []
    with torch.no_grad():
        for seq in seqs:
            pts = torch.from_numpy(seq).float()[None]
            if prior.kind == "body":
                f = prior.features(pts, mp.MODEL_FPS, torch.tensor([0.0, 0.0, 1.0]))[0]  # (3M, T-1)
                m = f.view(-1, 3, f.shape[-1])[torch.as_tensor(mirror)] * torch.tensor([-1.0, 1.0, 1.0])[:, None]
                out += [f, m.reshape(f.shape)]
            else:
                for side in ("R", "L"):
                    out.append(prior.features(pts, mp.MODEL_FPS, torch.tensor([0.0, 0.0, 1.0]), side)[0])
    return out


def sample_windows(feats: list[torch.Tensor], count: int, length: int, gen: torch.Generator) -> torch.Tensor:
    """(count, C, length) random crops, sequences drawn in proportion to their length."""
    lengths = torch.tensor([f.shape[-1] - length + 1 for f in feats], dtype=torch.float64).clamp(min=0)
    which = torch.multinomial(lengths, count, replacement=True, generator=gen)
    starts = (torch.rand(count, generator=gen, dtype=torch.float64) * lengths[which]).long()
    return torch.stack([feats[w][:, s:s + length] for w, s in zip(which.tolist(), starts.tolist())])


def losses(encoder, decoder, x: torch.Tensor, w_smooth: float, w_scale: float,
           noisy: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Reconstruction of clean (and jittered) windows (B, C, T); latent smoothness and scale of the clean ones."""
    z = encoder(x)
    rec = (decoder(z) - x).pow(2).mean()
    if noisy is not None:  # the code must carry the jitter too, so jitter shows in it
        rec = (rec + (decoder(encoder(noisy)) - noisy).pow(2).mean()) / 2
    smooth = (z[..., 1:] - z[..., :-1]).pow(2).sum(1).mean()
    scale = (z.var(dim=(0, 2)) - 1.0).pow(2).mean()
    return {"total": rec + w_smooth * smooth + w_scale * scale, "rec": rec, "smooth": smooth, "scale": scale}


def jitter_features(shape: tuple[int, int, int], max_mm: float, scale: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Velocity features (B, C, T) of i.i.d. position jitter, sigma ~ U(0, max_mm) per window; `scale` (C,) =
    fps / feature_std maps a position difference onto the normalised features."""
    B, C, T = shape
    sigma = torch.rand(B, 1, 1, generator=gen) * max_mm / 1000
    n = torch.randn(B, C, T + 1, generator=gen) * sigma
    return (n[..., 1:] - n[..., :-1]) * scale[:, None]


def train(kind: str, train_feats, val_feats, channels, latent, kernel, steps, batch, w_smooth, w_scale,
          noise_mm: float = 0.0, noise_scale: torch.Tensor | None = None, seed=0):
    """Train encoder + decoder; returns the encoder and a log of (step, train and held-out losses)."""
    torch.manual_seed(seed)
    c_in = train_feats[0].shape[0]
    encoder = mp.TemporalConvNet((c_in, *channels, latent), kernel)
    decoder = mp.TemporalConvNet((latent, *channels[::-1], c_in), kernel)
    params = list(encoder.parameters()) + list(decoder.parameters())
    opt = torch.optim.Adam(params, lr=2e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    gen = torch.Generator().manual_seed(seed)
    val = sample_windows(val_feats, 512, WINDOW - 1, torch.Generator().manual_seed(99))
    log = []
    for step in range(steps):
        x = sample_windows(train_feats, batch, WINDOW - 1, gen)
        noisy = x + jitter_features(x.shape, noise_mm, noise_scale, gen) if noise_mm > 0 else None
        out = losses(encoder, decoder, x, w_smooth, w_scale, noisy)
        opt.zero_grad()
        out["total"].backward()
        opt.step()
        sched.step()
        if step % max(1, steps // 5) == 0 or step == steps - 1:
            with torch.no_grad():
                v = losses(encoder, decoder, val, w_smooth, w_scale)
            log.append((step, {k: float(t.detach()) for k, t in out.items()}, {k: float(t) for k, t in v.items()}))
            print(f"  [{kind}] step {step:5d}  train rec {out['rec']:.3f} smooth {out['smooth']:.3f} "
                  f"scale {out['scale']:.3f} | held-out rec {v['rec']:.3f} smooth {v['smooth']:.3f}", flush=True)
    return encoder.eval(), log


def jitter_check(prior: mp.MotionPrior, seqs: list[np.ndarray], sigma_mm: float, seed: int = 0) -> tuple[float, float]:
    """Mean prior value per frame on held-out sequences, clean and with Gaussian jitter of sigma_mm on every vertex."""
    gen = torch.Generator().manual_seed(seed)
    clean, noisy, frames = 0.0, 0.0, 0
    with torch.no_grad():
        for seq in seqs:
            pts = torch.from_numpy(seq).float()
            noise = torch.randn(pts.shape, generator=gen) * sigma_mm / 1000
            sides = ("R",) if prior.kind == "body" else ("R", "L")
            for side in sides:
                clean += float(mp.motion_smoothness(pts, mp.MODEL_FPS, prior, UP, side))
                noisy += float(mp.motion_smoothness(pts + noise, mp.MODEL_FPS, prior, UP, side))
                frames += len(seq)
    return clean / frames, noisy / frames


def save(path: Path, prior: mp.MotionPrior, encoder, layout, kernel, channels, extra: dict) -> None:
    arrays = {k: v for k, v in layout.items() if k != "mirror"}
    arrays.update({f"encoder.{k}": v.detach().numpy().astype(np.float16) for k, v in encoder.state_dict().items()})
    arrays.update(
        channels=np.array(channels), kernel=np.array(kernel), num_vertices=np.array(prior.num_vertices),
        feature_mean=prior.feature_mean.numpy(), feature_std=prior.feature_std.numpy(),
        fps=np.array(mp.MODEL_FPS), held_out_clips=np.array(HELD_OUT),
        source=np.array("CMU Graphics Lab Motion Capture Database, subjects 01-03 (mocap.cs.cmu.edu); "
                        "created with funding from NSF EIA-0196217"),
        **extra,
    )
    np.savez_compressed(path, **arrays)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="CMU folder (subjects/NN/*.asf, *.amc)")
    parser.add_argument("--cache", type=Path, default=None, help="npz to keep / reuse the retargeted marker tracks")
    parser.add_argument("--out-dir", type=Path, default=mp.DATA_DIR)
    parser.add_argument("--kinds", nargs="+", default=["body", "hand"], choices=["body", "hand"])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--w-smooth", type=float, default=0.1, help="weight of the latent smoothness in training")
    parser.add_argument("--w-scale", type=float, default=1.0, help="weight keeping each latent channel's variance at 1")
    parser.add_argument("--noise-mm", type=float, default=10.0,
                        help="jittered copies (sigma up to this, mm) to reconstruct as well; 0: clean only")
    parser.add_argument("--latent", type=int, nargs=2, default=None, metavar=("BODY", "HAND"),
                        help="latent channels (default from SETTINGS)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads (1 keeps small convolutions from spinning on a shared machine)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.latent:
        SETTINGS["body"]["latent"], SETTINGS["hand"]["latent"] = args.latent

    from intercap.body_models import load_body_model

    t0, c0 = time.time(), time.process_time()
    model = load_body_model("anny")
    layouts = {k: compact_layout(v) for k, v in marker_layout(model).items()}
    all_ids = np.unique(np.concatenate([l["point_ids"] for l in layouts.values()]))
    if not args.data.exists() and not (args.cache and args.cache.exists()):
        raise SystemExit(f"CMU mocap folder {args.data} not found (expected ../shared/data/cmu_mocap)")
    args.out_dir.mkdir(parents=True, exist_ok=True)
    t1 = time.time()
    clips, example, counts = load_sequences(args.data, model, all_ids, args.cache)
    missing = [c for c in HELD_OUT if c not in clips]
    if missing:
        raise SystemExit(f"held-out clips {missing} not found")
    n_frames = {c: sum(len(s) for s in seqs) for c, seqs in clips.items()}
    print(f"{len(clips)} clips, {counts['frames_60fps']} frames at 60 fps ({counts['glitch_frames_60fps']} glitch "
          f"frames dropped), {sum(n_frames.values())} frames at 30 fps in glitch-free stretches (both phases); "
          f"{time.time() - t1:.1f} s")
    col = {v: i for i, v in enumerate(all_ids)}
    for kind in args.kinds:
        layout, s = layouts[kind], SETTINGS[kind]
        take = np.array([col[v] for v in layout["point_ids"]])
        seqs = {c: [q[:, take] for q in qs] for c, qs in clips.items()}
        train_seqs = [q for c, qs in seqs.items() if c not in HELD_OUT for q in qs]
        val_seqs = [q for c in HELD_OUT for q in seqs[c]]
        channels = (*s["channels"], s["latent"])
        raw = make_prior(kind, layout, (1, 1), s["kernel"], model.num_vertices)
        train_raw = raw_features(raw, train_seqs, layout.get("mirror"))
        stacked = torch.cat(train_raw, dim=1)
        mean, std = stacked.mean(1), stacked.std(1).clamp(min=1e-3)
        mean = mean.numpy().astype(np.float32)
        std = std.numpy().astype(np.float32)
        norm = lambda fs: [(f - torch.from_numpy(mean)[:, None]) / torch.from_numpy(std)[:, None] for f in fs]  # noqa: E731
        val_raw = raw_features(raw, val_seqs, layout.get("mirror"))
        t2, c2 = time.time(), time.process_time()
        print(f"{kind}: {len(layout['markers'] if kind == 'body' else layout['markers_R'])} markers, "
              f"{stacked.shape[1]} training / {sum(f.shape[1] for f in val_raw)} held-out velocity frames "
              f"(mirrored included)")
        encoder, log = train(kind, norm(train_raw), norm(val_raw), s["channels"], s["latent"], s["kernel"],
                             args.steps, args.batch, args.w_smooth, args.w_scale, args.noise_mm,
                             mp.MODEL_FPS / torch.from_numpy(std))
        train_s, train_cpu = time.time() - t2, time.process_time() - c2
        prior = make_prior(kind, layout, (stacked.shape[0], *channels), s["kernel"], model.num_vertices, mean, std)
        prior.encoder.load_state_dict({k: v.half().float() for k, v in encoder.state_dict().items()})  # as shipped
        prior.eval()
        checks = {}
        for sigma in (2.0, 5.0, 10.0):
            clean, noisy = jitter_check(prior, val_seqs, sigma)
            checks[sigma] = (clean, noisy)
            print(f"  held-out prior per frame: clean {clean:.4f}, +{sigma:.0f} mm jitter {noisy:.4f} "
                  f"(x{noisy / clean:.1f})")
        extra = {f"example_{k}": v.astype(np.float32) for k, v in example.items()} if kind == "body" else {}
        extra["heldout_jitter_check"] = np.array([[sigma, c, n] for sigma, (c, n) in checks.items()])  # mm, clean, noisy
        extra["train_log"] = np.array([[s_, l["rec"], l["smooth"], v["rec"], v["smooth"]] for s_, l, v in log])
        path = args.out_dir / mp.PRIOR_FILES[kind].name
        save(path, prior, encoder, layout, s["kernel"], (stacked.shape[0], *channels), extra)
        print(f"  trained in {train_s:.1f} s wall, {train_cpu:.1f} s CPU; wrote {path} "
              f"({path.stat().st_size / 1024:.1f} KiB)")
    mp._load.cache_clear()
    print(f"total {time.time() - t0:.1f} s wall, {time.process_time() - c0:.1f} s CPU (2 shared cores)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
