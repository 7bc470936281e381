"""Does the learned motion prior help? Measured on held-out CMU clips (real motion, never trained on).

    python tools/bench_motion_prior.py [--cache /tmp/cmu_markers.npz] [--windows 12]

1. Separation: the prior per frame on clean held-out marker tracks against the same tracks with
   Gaussian jitter (2, 5, 10 mm per axis), next to the plain acceleration penalty on the same tracks;
   and a spike (one frame, one limb's markers pushed 5 cm): how far above the clean level the
   learned prior's per-frame latent change rises at the spike.
2. Denoising: 3 s windows of the body's marker points (30 fps) corrupted three ways
     jitter    i.i.d. 10 mm per axis on every point and frame,
     frames    per frame a rigid wobble of the whole body (2 deg, 10 mm) plus 3 mm i.i.d. (what a
               per-frame fit's error looks like: the whole body shifts),
     spikes    3 mm i.i.d. plus, on 5 % of the frames, one limb's markers pushed 5 cm,
   then recovered by L-BFGS (strong Wolfe) on
       sum_t ||y_t - noisy_t||^2 / sigma^2  +  lambda * prior(y),
   prior = the plain acceleration penalty, the learned prior, or both. Each lambda is chosen on
   windows of two training clips, then the error to the clean track (mm, mean over points and
   frames) and the jitter (mean acceleration, m/s^2) are measured on held-out windows.
   Pose space (body): 2 s windows of the held-out clips' anny parameters, every frame's pose
   jittered (3 deg per joint axis, root 1 deg and 5 mm); an anny pose sequence is fitted to the
   jittered poses' points with the same data term and priors (40 L-BFGS iterations), so every
   candidate is a body motion, as in the global stage.
3. The same marker-space test for the hand prior: both hands' markers relative to the wrist point.
4. Speed of the learned prior, forward + backward, on full anny vertex tracks.

The machine's 2 cores are shared with other work: wall and process CPU times are both printed.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from intercap.energies import motion_prior as mp  # noqa: E402
from tools import train_motion_prior as tm  # noqa: E402

TUNE_CLIPS = ("01_05", "02_07", "03_03")  # training clips used only to choose the weights
WINDOW = 90  # frames, 3 s at 30 fps
FPS = mp.MODEL_FPS
UP = torch.tensor([0.0, 0.0, 1.0])
GRID_ACC = (1e-3, 3e-3, 1e-2, 3e-2, 1e-1, 3e-1, 1.0)  # weights tried for the acceleration penalty
COMBINED = ((0.5, 0.5), (0.5, 1.0), (1.0, 0.5), (0.25, 1.0))  # fractions of both best weights, tried together
GRID_LEARNED = (0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0)  # and for the learned prior
LIMB_MARKERS = 8  # markers pushed together by a spike: the nearest ones to a random marker


def windows(seqs: list[np.ndarray], count: int, length: int = WINDOW) -> list[torch.Tensor]:
    """Up to `count` non-overlapping windows (length, U, 3) spread over the first-phase sequences."""
    out = []
    for seq in seqs[::2]:  # even entries: phase 0 (odd ones repeat the same motion shifted by 1/60 s)
        out += [torch.from_numpy(np.ascontiguousarray(seq[s:s + length])).float() for s in range(0, len(seq) - length + 1, length)]
    pick = np.linspace(0, len(out) - 1, min(count, len(out))).round().astype(int)
    return [out[i] for i in sorted(set(pick))]


def corrupt(clean: torch.Tensor, kind: str, gen: torch.Generator, groups: torch.Tensor | None) -> torch.Tensor:
    """(T, U, 3) clean -> noisy track (see the module docstring)."""
    T, U, _ = clean.shape
    noise = lambda sigma_mm: torch.randn(clean.shape, generator=gen) * sigma_mm / 1000  # noqa: E731
    if kind == "jitter":
        return clean + noise(10.0)
    if kind == "frames":
        axis = torch.nn.functional.normalize(torch.randn(T, 3, generator=gen), dim=-1)
        angle = torch.randn(T, 1, generator=gen) * math.radians(2.0)
        from intercap.body_models import axis_angle_to_matrix

        R = axis_angle_to_matrix(axis * angle)  # (T, 3, 3)
        centre = clean.mean(1, keepdim=True)
        shift = torch.randn(T, 1, 3, generator=gen) * 0.010
        return (clean - centre) @ R.transpose(1, 2) + centre + shift + noise(3.0)
    if kind == "spikes":
        out = clean + noise(3.0)
        frames = torch.randperm(T, generator=gen)[: max(1, round(0.05 * T))]
        for t in frames.tolist():
            limb = groups[torch.randint(len(groups), (1,), generator=gen)]
            direction = torch.nn.functional.normalize(torch.randn(3, generator=gen), dim=0)
            out[t, limb] += 0.05 * direction
        return out
    raise ValueError(kind)


def limb_groups(rest_points: torch.Tensor, marker_ids: torch.Tensor) -> torch.Tensor:
    """(M, LIMB_MARKERS) ids into the points: each marker with its nearest markers (a limb piece)."""
    pts = rest_points[marker_ids]
    near = torch.cdist(pts, pts).argsort(1)[:, :LIMB_MARKERS]
    return marker_ids[near]


class Objective:
    """Prior terms of the denoising problem on compact points (T, U, 3)."""

    def __init__(self, prior: mp.MotionPrior, kind: str):
        self.prior, self.kind = prior, kind
        if kind == "body":
            self.tracked = prior.markers
        else:
            self.tracked = torch.cat([prior.markers_L, prior.markers_R, prior.wrist_L, prior.wrist_R])

    def learned(self, y: torch.Tensor) -> torch.Tensor:
        if self.kind == "body":
            return mp.motion_smoothness(y, FPS, self.prior, UP)
        return sum(mp.motion_smoothness(y, FPS, self.prior, UP, s) for s in ("L", "R"))

    def acceleration(self, y: torch.Tensor) -> torch.Tensor:
        return mp.acceleration_penalty(y[:, self.tracked], FPS)

    def error_mm(self, y: torch.Tensor, clean: torch.Tensor) -> float:
        """Body: mean point error over the markers; hands: hand markers relative to their wrist point."""
        if self.kind == "body":
            return float((y - clean)[:, self.prior.markers].norm(dim=-1).mean() * 1000)
        errs = []
        for s in ("L", "R"):
            rel = lambda p: p[:, getattr(self.prior, f"markers_{s}")] - p[:, getattr(self.prior, f"wrist_{s}")].mean(1, keepdim=True)  # noqa: E731,E501
            errs.append((rel(y) - rel(clean)).norm(dim=-1).mean())
        return float(sum(errs) / 2 * 1000)

    def jitter(self, y: torch.Tensor) -> float:
        p = y[:, self.tracked]
        return float((p[2:] - 2 * p[1:-1] + p[:-2]).norm(dim=-1).mean() * FPS**2)


def denoise(noisy: torch.Tensor, obj: Objective, w_acc: float, w_learned: float, sigma: float = 0.01,
            iters: int = 60) -> torch.Tensor:
    """argmin_y sum ||y - noisy||^2 / sigma^2 / U + w_acc * E_acc(y) + w_learned * E_learned(y) by L-BFGS."""
    y = noisy.clone().contiguous().requires_grad_(True)
    opt = torch.optim.LBFGS([y], lr=1.0, max_iter=iters, history_size=20, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-9, tolerance_change=1e-12)
    U = noisy.shape[1]

    def closure():
        opt.zero_grad()
        loss = (y - noisy).pow(2).sum() / sigma**2 / U
        if w_acc:
            loss = loss + w_acc * obj.acceleration(y)
        if w_learned:
            loss = loss + w_learned * obj.learned(y)
        loss.backward()
        return loss

    opt.step(closure)
    return y.detach()


def evaluate(cases, obj: Objective, w_acc: float, w_learned: float) -> tuple[float, float, float]:
    """Mean error (mm), mean jitter (m/s^2) and seconds per window over (clean, noisy) cases."""
    errs, jits, t0 = [], [], time.time()
    for clean, noisy in cases:
        y = noisy if (w_acc == 0 and w_learned == 0) else denoise(noisy, obj, w_acc, w_learned)
        errs.append(obj.error_mm(y, clean))
        jits.append(obj.jitter(y))
    return float(np.mean(errs)), float(np.mean(jits)), (time.time() - t0) / len(cases)


def tune(cases, obj: Objective, grid_acc, grid_learned) -> dict[str, tuple[float, float]]:
    """Best (w_acc, w_learned) per method on the tuning cases, by mean error."""
    def best(pairs):
        scores = [(evaluate(cases, obj, a, l)[0], (a, l)) for a, l in pairs]
        return min(scores)[1]

    acc = best([(a, 0.0) for a in grid_acc])
    learned = best([(0.0, l) for l in grid_learned])
    both = best([(acc[0] * fa, learned[1] * fl) for fa, fl in COMBINED])
    return {"acceleration": acc, "learned": learned, "learned + acceleration": both}


def separation(prior: mp.MotionPrior, obj: Objective, seqs: list[torch.Tensor], gen: torch.Generator) -> None:
    """Per-frame prior values clean vs jittered, learned and acceleration, and the spike response."""
    print(f"\n[{prior.kind}] separation on {len(seqs)} held-out windows: per-frame value, jittered / clean")
    with torch.no_grad():
        clean_l = sum(float(obj.learned(s)) for s in seqs)
        clean_a = sum(float(obj.acceleration(s)) for s in seqs)
        for sigma in (2.0, 5.0, 10.0):
            noisy = [s + torch.randn(s.shape, generator=gen) * sigma / 1000 for s in seqs]
            ratio_l = sum(float(obj.learned(s)) for s in noisy) / clean_l
            ratio_a = sum(float(obj.acceleration(s)) for s in noisy) / clean_a
            print(f"  +{sigma:4.1f} mm jitter: learned x{ratio_l:6.1f}   acceleration x{ratio_a:6.1f}")
        if prior.kind == "body":
            rises = []
            groups = limb_groups(seqs[0][0], prior.markers)
            for s in seqs:
                t = s.shape[0] // 2
                spiked = s.clone()
                spiked[t, groups[torch.randint(len(groups), (1,), generator=gen)]] += 0.05 * torch.nn.functional.normalize(
                    torch.randn(3, generator=gen), dim=0)
                dz = lambda x: (lambda z: (z[..., 1:] - z[..., :-1]).pow(2).sum(1)[0])(  # noqa: E731
                    prior.latent(x[None], FPS, UP))
                base, hit = dz(s), dz(spiked)
                rises.append(float(hit[t - 2:t + 2].max() / base.median()))
            print(f"  5 cm spike on one limb, one frame: latent change at the spike / median clean frame: "
                  f"median x{np.median(rises):.1f} (min x{np.min(rises):.1f})")


POSE_WINDOW = 60  # frames, 2 s at 30 fps
POSE_GRID_ACC = (1e-2, 3e-2, 0.1, 0.3, 1.0, 3.0, 10.0)
POSE_GRID_LEARNED = (1.0, 3.0, 10.0, 30.0, 100.0)
POSE_NOISE = dict(joint_deg=3.0, orient_deg=1.0, transl_mm=5.0)  # per frame, per axis


def pose_windows(data: Path, model, skinner, clips: tuple[str, ...], count: int) -> list[tuple[torch.Tensor, ...]]:
    """Up to `count` windows (body_pose (T, 65, 3), orient (T, 3), transl (T, 3)) at 30 fps, glitch-free."""
    from tools import cmu_mocap

    rest = cmu_mocap.AnnyRest.from_model(model)
    out = []
    for asf, amc in cmu_mocap.list_clips(data):
        if amc.stem not in clips:
            continue
        _, glitch, body, orient, transl = tm.read_clip(asf, amc, rest, skinner)
        for a, b in tm.good_stretches(glitch, 2 * POSE_WINDOW):
            for s in range(a, b - 2 * POSE_WINDOW + 1, 2 * POSE_WINDOW):
                keep = slice(s, s + 2 * POSE_WINDOW, 2)
                out.append(tuple(torch.from_numpy(np.ascontiguousarray(x[keep])).float() for x in (body, orient, transl)))
    pick = np.linspace(0, len(out) - 1, min(count, len(out))).round().astype(int)
    return [out[i] for i in sorted(set(pick))]


def pose_noise(pose: tuple[torch.Tensor, ...], gen: torch.Generator) -> tuple[torch.Tensor, ...]:
    """Per-frame fitting jitter in pose space: Gaussian on every joint's rotation vector, the root's and translation."""
    body, orient, transl = pose
    rad = math.radians
    return (body + torch.randn(body.shape, generator=gen) * rad(POSE_NOISE["joint_deg"]),
            orient + torch.randn(orient.shape, generator=gen) * rad(POSE_NOISE["orient_deg"]),
            transl + torch.randn(transl.shape, generator=gen) * POSE_NOISE["transl_mm"] / 1000)


def denoise_pose(observed: torch.Tensor, init: tuple[torch.Tensor, ...], skinner, obj: Objective, w_acc: float,
                 w_learned: float, sigma: float = 0.01, iters: int = 40) -> torch.Tensor:
    """Fit an anny pose sequence to observed points (T, U, 3) with a prior on its points; returns the points."""
    variables = [x.clone().contiguous().requires_grad_(True) for x in init]
    opt = torch.optim.LBFGS(variables, lr=1.0, max_iter=iters, history_size=20, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-9, tolerance_change=1e-12)
    U = observed.shape[1]

    def closure():
        opt.zero_grad()
        y = skinner.points(*variables)
        loss = (y - observed).pow(2).sum() / sigma**2 / U
        if w_acc:
            loss = loss + w_acc * obj.acceleration(y)
        if w_learned:
            loss = loss + w_learned * obj.learned(y)
        loss.backward()
        return loss

    if w_acc or w_learned:
        opt.step(closure)
    with torch.no_grad():
        return skinner.points(*variables)


def pose_experiment(args, model, prior: mp.MotionPrior, obj: Objective) -> None:
    """Denoising in pose space: the points can only move as an anny body moves them."""
    gen = torch.Generator().manual_seed(1)  # its own draws, whatever ran before
    skinner = tm.MarkerSkinner(model, prior.point_ids.numpy())
    t0 = time.time()
    held = pose_windows(args.data, model, skinner, tm.HELD_OUT, args.pose_windows)
    tune_set = pose_windows(args.data, model, skinner, TUNE_CLIPS, args.tune_windows // 2 or 1)
    print(f"\n[body, pose space] {len(held)} held-out windows of {POSE_WINDOW} frames, per-frame pose noise "
          f"{POSE_NOISE['joint_deg']} deg per joint axis, root {POSE_NOISE['orient_deg']} deg / "
          f"{POSE_NOISE['transl_mm']} mm; weights tuned on {len(tune_set)} windows ({time.time() - t0:.0f} s to read)")

    def cases_of(windows):
        out = []
        with torch.no_grad():
            for pose in windows:
                noisy = pose_noise(pose, gen)
                out.append((skinner.points(*pose), skinner.points(*noisy), noisy))
        return out

    def run(cases, wa, wl):
        errs, jits, t = [], [], time.time()
        for clean, observed, init in cases:
            y = denoise_pose(observed, init, skinner, obj, wa, wl)
            errs.append(obj.error_mm(y, clean))
            jits.append(obj.jitter(y))
        return float(np.mean(errs)), float(np.mean(jits)), (time.time() - t) / len(cases)

    tune_cases, cases = cases_of(tune_set), cases_of(held)
    best_a = min((run(tune_cases, a, 0.0)[0], a) for a in POSE_GRID_ACC)[1]
    best_l = min((run(tune_cases, 0.0, l)[0], l) for l in POSE_GRID_LEARNED)[1]
    both = min((run(tune_cases, best_a * fa, best_l * fl)[0], (best_a * fa, best_l * fl)) for fa, fl in COMBINED)[1]
    print(f"  {'method':24s} {'weights (acc, learned)':>24s} {'error mm':>9s} {'jitter m/s2':>12s} {'s/window':>9s}")
    for name, (wa, wl) in (("noisy input", (0.0, 0.0)), ("acceleration", (best_a, 0.0)), ("learned", (0.0, best_l)),
                           ("learned + acceleration", both)):
        err, jit, sec = run(cases, wa, wl)
        print(f"  {name:24s} {wa:11.1e} {wl:11.1e}  {err:9.2f} {jit:12.2f} {sec:9.2f}")
    gt = float(np.mean([obj.jitter(c) for c, _, _ in cases]))
    print(f"  {'(clean track)':24s} {'':24s} {0.0:9.2f} {gt:12.2f}")


def speed(prior_kind: str) -> None:
    """Forward + backward of the learned prior on full anny vertex tracks."""
    from intercap.body_models import load_body_model

    model = load_body_model("anny")
    for T in (90, 300):
        verts = (torch.randn(T, model.num_vertices, 3) * 0.3).requires_grad_(True)
        fn = (lambda v: mp.body_motion_smoothness(v, 30.0, UP)) if prior_kind == "body" else \
            (lambda v: mp.hand_motion_smoothness(v, 30.0, "L", UP) + mp.hand_motion_smoothness(v, 30.0, "R", UP))
        fn(verts).backward()
        t0, c0 = time.time(), time.process_time()
        for _ in range(5):
            fn(verts).backward()
        print(f"  [{prior_kind}] prior on {T} frames of anny vertices, forward + backward: "
              f"{(time.time() - t0) / 5 / T * 1000:.3f} ms/frame wall, {(time.process_time() - c0) / 5 / T * 1000:.3f} ms/frame CPU")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=tm.DEFAULT_DATA)
    parser.add_argument("--cache", type=Path, default=None, help="marker tracks written by train_motion_prior --cache")
    parser.add_argument("--windows", type=int, default=12, help="held-out windows per noise kind")
    parser.add_argument("--tune-windows", type=int, default=6)
    parser.add_argument("--kinds", nargs="+", default=["body", "hand"], choices=["body", "hand"])
    parser.add_argument("--noise", nargs="*", default=["jitter", "frames", "spikes"], help="marker-space noise kinds")
    parser.add_argument("--pose-windows", type=int, default=6, help="held-out windows of the pose-space test (0: skip)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads (1 keeps small convolutions from spinning on a shared machine)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    from intercap.body_models import load_body_model

    t0, c0 = time.time(), time.process_time()
    model = load_body_model("anny")
    layouts = {k: tm.compact_layout(v) for k, v in tm.marker_layout(model).items()}
    all_ids = np.unique(np.concatenate([l["point_ids"] for l in layouts.values()]))
    clips, _, _ = tm.load_sequences(args.data, model, all_ids, args.cache, only=tm.HELD_OUT + TUNE_CLIPS)
    col = {v: i for i, v in enumerate(all_ids)}
    print(f"marker tracks of {len(clips)} clips ready in {time.time() - t0:.1f} s")
    gen = torch.Generator().manual_seed(0)
    for kind in args.kinds:
        prior = mp.load_motion_prior(kind)
        take = np.array([col[v] for v in prior.point_ids.numpy()])
        held = windows([q[:, take] for c in tm.HELD_OUT for q in clips[c]], args.windows)
        tune_seqs = windows([q[:, take] for c in TUNE_CLIPS for q in clips[c]], args.tune_windows)
        obj = Objective(prior, kind)
        separation(prior, obj, held, gen)
        groups = limb_groups(held[0][0], prior.markers if kind == "body" else prior.markers_R)
        if kind == "hand":  # a spike moves the whole hand's markers of one side
            groups = torch.stack([prior.markers_L, prior.markers_R])
        print(f"\n[{kind}] denoising: {len(held)} held-out windows of {WINDOW} frames "
              f"(weights tuned on {len(tune_seqs)} windows of {', '.join(TUNE_CLIPS)})")
        print(f"  {'noise':8s} {'method':24s} {'weights (acc, learned)':>24s} {'error mm':>9s} {'jitter m/s2':>12s} "
              f"{'s/window':>9s}")
        for noise in args.noise:
            tune_cases = [(s, corrupt(s, noise, gen, groups)) for s in tune_seqs]
            cases = [(s, corrupt(s, noise, gen, groups)) for s in held]
            gt_jitter = float(np.mean([obj.jitter(s) for s, _ in cases]))
            chosen = tune(tune_cases, obj, grid_acc=GRID_ACC, grid_learned=GRID_LEARNED)
            rows = [("noisy input", (0.0, 0.0))] + list(chosen.items())
            for name, (wa, wl) in rows:
                err, jit, sec = evaluate(cases, obj, wa, wl)
                print(f"  {noise:8s} {name:24s} {wa:11.1e} {wl:11.1e}  {err:9.2f} {jit:12.2f} {sec:9.2f}")
            print(f"  {noise:8s} {'(clean track)':24s} {'':24s} {0.0:9.2f} {gt_jitter:12.2f}")
        if kind == "body" and args.pose_windows:
            pose_experiment(args, model, prior, obj)
        speed(kind)
    print(f"\ntotal {time.time() - t0:.1f} s wall, {time.process_time() - c0:.1f} s CPU (2 cores shared with other work)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
