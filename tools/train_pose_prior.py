"""Build the shipped body-pose prior files from anny and the CMU mocap in ../shared/data.

    python tools/train_pose_prior.py                      # anatomy + learned prior + report
    python tools/train_pose_prior.py --anatomy-only       # only intercap/data/anny_anatomy.npz

Steps: measure the anatomical joint frames on anny's rest skeleton
(`intercap.energies.priors.anatomy_from_model`); read every CMU clip, drop capture
glitches, retarget every `--step`-th frame to anny (tools/cmu_mocap.py); report
how often real poses leave the joint limits; fit a Gaussian mixture on the
learned features of the training clips (mirrored copies added, so the prior is
left-right symmetric); compare held-out real poses with random poses; write
intercap/data/body_pose_prior.npz.

Data credit: "The data used in this project was obtained from mocap.cs.cmu.edu.
The database was created with funding from NSF EIA-0196217."
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from intercap.energies import priors  # noqa: E402
from tools import cmu_mocap  # noqa: E402

DEFAULT_DATA = ROOT.parent / "shared" / "data" / "cmu_mocap"
HELD_OUT = ("01_09", "02_01", "03_04")  # one clip per subject: playground, walk, uneven terrain
MAJOR_JOINTS = ("head", "clavicle", "shoulder", "elbow", "wrist", "hip", "knee", "ankle")  # + each spine/neck bone


def write_anatomy(model, path: Path = priors.ANATOMY_FILE) -> dict:
    """Measure the joint frames on anny's rest skeleton and save them."""
    if list(model.body_joint_names) != list(priors.ANNY_BODY_BONES):
        raise ValueError("anny's body bones differ from intercap.energies.priors.ANNY_BODY_BONES; update the table")
    if list(model.hand_joint_names) != list(priors.HAND_BONES):
        raise ValueError("anny's hand bones differ from intercap.energies.priors.HAND_BONES; update the table")
    anatomy = priors.anatomy_from_model(model)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **anatomy)
    priors._shipped_anatomy.cache_clear()
    priors.load_anatomy.cache_clear()
    priors._learned_table.cache_clear()
    return anatomy


def retarget_clips(root: Path, model, step: int) -> tuple[dict[str, np.ndarray], dict[str, tuple[int, int]]]:
    """clip name -> body_pose (T, 65, 3) float32 of every `step`-th frame without glitches; and
    clip -> (frames kept, frames dropped as glitches)."""
    rest = cmu_mocap.AnnyRest.from_model(model)
    poses, counts = {}, {}
    for asf, amc in cmu_mocap.list_clips(root):
        skeleton, motion = cmu_mocap.load_clip(asf, amc, step=step)
        bad = cmu_mocap.glitch_frames(skeleton, motion)
        motion = {k: v[~bad] for k, v in motion.items()}
        body, _ = cmu_mocap.retarget_to_anny(skeleton, cmu_mocap.world_rotations(skeleton, motion), rest)
        poses[amc.stem] = body
        counts[amc.stem] = (int((~bad).sum()), int(bad.sum()))
    return poses, counts


def limit_violation_table(body_pose: torch.Tensor, threshold_deg: float = 5.0) -> dict[str, list[float]]:
    """Joint (left and right pooled) -> % of frames beyond its (flexion, abduction, twist) range by more
    than `threshold_deg`; toe bones pooled as 'toe_mtp' / 'toe_ip'; and 'second bones' swing."""
    excess = torch.rad2deg(priors.joint_limit_excess(body_pose)) > threshold_deg  # (N, R, 3)
    joints = priors.load_anatomy().row_joints
    table = {}
    for joint in dict.fromkeys(joints):
        rows = [r for r, j in enumerate(joints) if j == joint]
        table[joint] = (excess[:, rows].float().mean((0, 1)) * 100).tolist()
    swing = torch.rad2deg(priors.second_bone_swing(body_pose)).abs() > priors.SECOND_BONE_SWING + threshold_deg
    table["second bones (swing)"] = [float(swing.float().mean() * 100)] * 2 + [0.0]
    table["any joint"] = [float(excess.any(2).any(1).float().mean() * 100)] * 3
    return table


def kmeans_plus_plus(x: torch.Tensor, k: int, generator: torch.Generator) -> torch.Tensor:
    """(k, D) initial centres, each drawn with probability proportional to squared distance."""
    centres = [x[torch.randint(len(x), (1,), generator=generator)][0]]
    for _ in range(1, k):
        d2 = torch.cdist(x, torch.stack(centres)).min(1).values ** 2
        centres.append(x[torch.multinomial(d2 / d2.sum(), 1, generator=generator)][0])
    return torch.stack(centres)


def gaussian_log_densities(x: torch.Tensor, means: torch.Tensor, covs: torch.Tensor) -> torch.Tensor:
    """(N, D), (K, D), (K, D, D) -> (N, K) log N(x | mu_k, Sigma_k)."""
    chol = torch.linalg.cholesky(covs)  # (K, D, D)
    diff = (x[None] - means[:, None]).transpose(1, 2)  # (K, D, N)
    z = torch.linalg.solve_triangular(chol, diff, upper=False)  # (K, D, N)
    log_det = 2 * torch.log(torch.diagonal(chol, dim1=1, dim2=2)).sum(1)  # (K,)
    d = x.shape[1]
    return (-0.5 * (z * z).sum(1) - 0.5 * (log_det[:, None] + d * math.log(2 * math.pi))).T


def fit_gmm(
    x: np.ndarray, k: int, floor_deg: float = 3.0, iterations: int = 300, tol: float = 1e-4, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[float]]:
    """EM for a full-covariance Gaussian mixture: (weights (K,), means (K, D), covs (K, D, D), log-lik trace).

    Covariances get `floor_deg`^2 (radians^2) added on the diagonal: a floor for directions the
    retargeted mocap makes (nearly) deterministic (knee and elbow abduction)."""
    gen = torch.Generator().manual_seed(seed)
    X = torch.as_tensor(x, dtype=torch.float64)
    n, d = X.shape
    floor = math.radians(floor_deg) ** 2 * torch.eye(d, dtype=torch.float64)
    means = kmeans_plus_plus(X, k, gen)
    for _ in range(10):  # a few Lloyd steps
        assign = torch.cdist(X, means).argmin(1)
        means = torch.stack([X[assign == j].mean(0) if (assign == j).any() else means[j] for j in range(k)])
    covs = torch.cov(X.T).expand(k, d, d).clone() / k + floor
    weights = torch.full((k,), 1.0 / k, dtype=torch.float64)
    trace = []
    for _ in range(iterations):
        log_p = gaussian_log_densities(X, means, covs) + torch.log(weights)  # (N, K)
        log_norm = torch.logsumexp(log_p, 1, keepdim=True)
        trace.append(float(log_norm.mean()))
        resp = torch.exp(log_p - log_norm)  # (N, K)
        nk = resp.sum(0) + 1e-9
        weights = nk / n
        means = (resp.T @ X) / nk[:, None]
        covs = torch.stack([
            ((X - means[j]) * resp[:, j : j + 1]).T @ (X - means[j]) for j in range(k)
        ]) / nk[:, None, None] + floor
        if len(trace) > 1 and abs(trace[-1] - trace[-2]) < tol:
            break
    return weights.numpy(), means.numpy(), covs.numpy(), trace


def precision_cholesky(covs: np.ndarray) -> np.ndarray:
    """(K, D, D) covariances -> L with L L^T = Sigma^-1 (what intercap.energies.priors.learned_pose_prior reads)."""
    return np.linalg.cholesky(np.linalg.inv(covs))


def random_poses_within_limits(n: int, seed: int = 0) -> torch.Tensor:
    """(<= n, 65, 3): every major joint drawn uniformly inside its limit box - plausible joint by joint,
    incoherent as a whole (the hard negatives for a learned prior)."""
    gen = torch.Generator().manual_seed(seed)
    a = priors.load_anatomy()
    angles = {}
    for r, (name, joint) in enumerate(zip(a.row_names, a.row_joints)):
        if joint in MAJOR_JOINTS or joint.rstrip("0123456789") in ("spine", "neck") and joint[-1].isdigit():
            u = torch.rand(n, 3, generator=gen, dtype=torch.float64)
            low, high = a.low[r].double(), a.high[r].double()
            angles[name] = torch.rad2deg(low + u * (high - low)).float()
    body = priors.body_pose_from_joint_angles(angles, batch_size=n, anatomical=False)
    # Drop the draws that leave a limit after all: a swing-box corner past 180 deg, a spine total.
    return body[priors.joint_limit_penalty(body) == 0]


def score(body_pose: torch.Tensor, chunk: int = 4096) -> np.ndarray:
    with torch.no_grad():
        return torch.cat([priors.learned_pose_prior(p) for p in body_pose.split(chunk)]).numpy()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="CMU folder (subjects/NN/*.asf, *.amc)")
    parser.add_argument("--step", type=int, default=4, help="keep every step-th frame (120 fps in the files)")
    parser.add_argument("--components", type=int, default=8)
    parser.add_argument("--floor-deg", type=float, default=3.0, help="covariance floor, degrees")
    parser.add_argument("--examples", type=int, default=12, help="held-out poses stored in the npz (tests use them)")
    parser.add_argument("--anatomy-only", action="store_true")
    parser.add_argument("--report", type=Path, default=None, help="also write the figures as JSON here")
    args = parser.parse_args(argv)

    from intercap.body_models import load_body_model

    t0 = time.time()
    model = load_body_model("anny")
    write_anatomy(model)
    print(f"wrote {priors.ANATOMY_FILE} ({priors.ANATOMY_FILE.stat().st_size / 1024:.1f} KiB)")
    if args.anatomy_only:
        return 0
    if not args.data.exists():
        raise SystemExit(f"CMU mocap folder {args.data} not found (expected ../shared/data/cmu_mocap)")

    t1 = time.time()
    poses, counts = retarget_clips(args.data, model, args.step)
    kept, dropped = sum(c[0] for c in counts.values()), sum(c[1] for c in counts.values())
    print(f"retargeted {kept} frames of {len(poses)} clips (every {args.step}th; {dropped} glitch frames dropped) "
          f"in {time.time() - t1:.1f} s")
    missing = [c for c in HELD_OUT if c not in poses]
    if missing:
        raise SystemExit(f"held-out clips {missing} not found under {args.data}")

    everything = torch.from_numpy(np.concatenate(list(poses.values())))
    table = limit_violation_table(everything)
    print("\n% of CMU frames beyond a joint limit by more than 5 deg (flexion, abduction, twist):")
    for joint, values in table.items():
        print(f"  {joint:22s} " + "  ".join(f"{v:5.2f}" for v in values))

    train = torch.from_numpy(np.concatenate([p for c, p in poses.items() if c not in HELD_OUT]))
    held = torch.from_numpy(np.concatenate([poses[c] for c in HELD_OUT]))
    features = priors.learned_features(train)
    features = torch.cat([features, priors.mirror_features(features)]).double().numpy()
    t2 = time.time()
    weights, means, covs, trace = fit_gmm(features, args.components, floor_deg=args.floor_deg)
    train_s = time.time() - t2
    print(f"\nGMM: {args.components} components, {features.shape[1]} features, {len(features)} training vectors "
          f"(mirrored included), {len(trace)} EM iterations, {train_s:.1f} s; mean log-lik {trace[-1]:.2f}")

    pick = np.linspace(0, len(poses[HELD_OUT[1]]) - 1, args.examples // 2).astype(int)
    pick3 = np.linspace(0, len(poses[HELD_OUT[2]]) - 1, args.examples - len(pick)).astype(int)
    examples = np.concatenate([poses[HELD_OUT[1]][pick], poses[HELD_OUT[2]][pick3]]).astype(np.float32)
    np.savez_compressed(
        priors.POSE_PRIOR_FILE,
        log_weights=np.log(weights).astype(np.float32),
        means=means.astype(np.float32),
        precision_chol=precision_cholesky(covs).astype(np.float32),
        feature_names=np.array(priors.learned_feature_names()),
        example_poses=examples,
        held_out_clips=np.array(HELD_OUT),
        source=np.array("CMU Graphics Lab Motion Capture Database, subjects 01-03 (mocap.cs.cmu.edu); "
                        "created with funding from NSF EIA-0196217"),
    )
    priors.load_pose_prior.cache_clear()

    noise = torch.randn(held.shape, generator=torch.Generator().manual_seed(2)) * math.radians(20.0) / math.sqrt(3)
    scores = {
        "train (real)": score(train),
        "held-out (real)": score(held),
        "held-out mirrored (real)": score(priors.mirror_body_pose(held)),
        "random within joint limits": score(random_poses_within_limits(5000, seed=1)),
        "held-out + 20 deg noise per joint": score(held + noise),
    }
    p99 = float(np.percentile(scores["held-out (real)"], 99))
    print("\nlearned_pose_prior (min-component NLL, 0 = densest mode): median [p5, p95]; "
          "% above the held-out 99th percentile")
    report = {"frames": kept, "glitch_frames": dropped, "clips": len(poses), "held_out": HELD_OUT,
              "train_seconds": train_s, "violations_pct_over_5deg": table, "scores": {}}
    for name, s in scores.items():
        above = float((s > p99).mean() * 100)
        p5, p95 = np.percentile(s, [5, 95])
        print(f"  {name:36s} {np.median(s):8.1f} [{p5:7.1f}, {p95:8.1f}]  {above:5.1f}%")
        report["scores"][name] = {"median": float(np.median(s)), "p5": float(np.percentile(s, 5)),
                                  "p95": float(np.percentile(s, 95)), "pct_above_heldout_p99": above}
    size = priors.POSE_PRIOR_FILE.stat().st_size
    print(f"\nwrote {priors.POSE_PRIOR_FILE} ({size / 1024:.1f} KiB); total {time.time() - t0:.1f} s")
    report["prior_file_kib"] = size / 1024
    if args.report:
        args.report.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
