"""Benchmark the differentiable renderer (`intercap.geometry.rendering.render`).

For a 12-face box, a 512-face cylinder and the synthetic objects (box 2048,
cup 1664, chair 2400 faces), in 640x576 views with Azure-Kinect-like rational
distortion, object about 2 m away: median time of one forward pass (autograd
on) and of forward + backward of an E_O-like loss, for 1 view and for 4 views
in one call, at each crop size; plus peak extra memory of a 4-view forward +
backward (CPU: growth of the peak resident set, /proc; CUDA: peak allocated).

On CPU the times are thread CPU time with `--threads 1` (robust when other
processes share the machine), wall-clock time otherwise; CUDA: wall clock.

    PYTHONPATH=. python tools/bench_rendering.py [--sizes 64,96] [--sigma 0.6] [--device cpu] [--threads 1]
"""
from __future__ import annotations

import argparse
import re
import time

import numpy as np
import torch
import trimesh

from intercap.body_models import axis_angle_to_matrix
from intercap.geometry.cameras import Cameras
from intercap.geometry.rendering import MeshTopology, object_crops, render

IMAGE_W, IMAGE_H = 640, 576
KINECT_DIST = [0.55, -0.05, 1e-4, -2e-4, 0.002, 0.9, 0.05, 0.01]  # k1 k2 p1 p2 k3 k4 k5 k6, mild net distortion


def bench_meshes() -> dict:
    """name -> trimesh, in object coordinates (metres)."""
    from intercap.synth.objects import box_mesh, chair_mesh, cup_mesh

    return {
        "box12": trimesh.creation.box(extents=(0.30, 0.20, 0.15)),
        "cylinder512": trimesh.creation.cylinder(radius=0.04, height=0.10, sections=128),
        "box2048": box_mesh(),
        "cup1664": cup_mesh(),
        "chair2400": chair_mesh(),
    }


def bench_cameras(n: int = 4, distance: float = 2.0, dtype=torch.float32, device="cpu") -> Cameras:
    """n cameras on a circle around (0, 0, 0.8), z up, looking at it from 1.4 m height."""

    class Info:
        pass

    infos = []
    target = np.array([0.0, 0.0, 0.8])
    for i in range(n):
        a = 2 * np.pi * i / n + 0.3
        centre = np.array([distance * np.cos(a), distance * np.sin(a), 1.4])
        z = target - centre
        z /= np.linalg.norm(z)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        T = np.eye(4)
        T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
        T[:3, 3] = centre
        info = Info()
        info.name, info.width, info.height = f"cam{i}", IMAGE_W, IMAGE_H
        info.K = np.array([[504.0, 0, 321.3], [0, 504.5, 287.6], [0, 0, 1]])
        info.dist = KINECT_DIST
        info.T_world_from_cam = T
        infos.append(info)
    return Cameras.from_infos(infos, device=device, dtype=dtype)


def _peak_rss_kb() -> tuple[int, int]:
    s = open("/proc/self/status").read()
    return int(re.search(r"VmHWM:\s+(\d+)", s).group(1)), int(re.search(r"VmRSS:\s+(\d+)", s).group(1))


def _sync(device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def bench_one(mesh, cameras, size, sigma, repeats, device, dtype, clock=time.perf_counter) -> dict:
    """Timings (ms, median) for one mesh; each call renders all of `cameras`."""
    topo = MeshTopology.from_faces(torch.as_tensor(mesh.faces)).to(device)
    v_obj = torch.as_tensor(np.asarray(mesh.vertices), dtype=dtype, device=device)
    rot = torch.tensor([0.3, -0.2, 0.5], dtype=dtype, device=device)
    trans = torch.tensor([0.0, 0.0, 0.8], dtype=dtype, device=device)
    verts0 = (v_obj @ axis_angle_to_matrix(rot).T + trans)[None]
    crops = object_crops(verts0, cameras, size, margin=0.15)
    with torch.no_grad():  # target: the object moved by 1 cm
        moved = verts0 + torch.tensor([0.01, 0.0, 0.0], dtype=dtype, device=device)
        target = render(moved, topo, cameras, crops, size, sigma)
    r = rot.clone().requires_grad_(True)
    t = trans.clone().requires_grad_(True)

    def forward():
        verts = (v_obj @ axis_angle_to_matrix(r).T + t)[None]
        out = render(verts, topo, cameras, crops, size, sigma)
        mask = target.coverage & out.coverage
        e_s = ((out.silhouette - target.silhouette) ** 2).sum()
        return e_s + 100 * (((out.depth - target.depth) * mask) ** 2).sum()

    def timed(fn) -> float:
        for _ in range(3):
            fn()
        times = []
        for _ in range(repeats):
            _sync(device)
            t0 = clock()
            fn()
            _sync(device)
            times.append(clock() - t0)
        return 1000 * float(np.median(times))

    def fwd_bwd():
        r.grad = t.grad = None
        forward().backward()

    fwd = timed(forward)
    fb = timed(fwd_bwd)
    return dict(fwd=fwd, fwd_bwd=fb, covered=int(target.coverage.sum()), run=fwd_bwd)


def peak_memory_mb(run, device) -> float:
    """Peak extra memory (MB) of one call of `run`. CUDA: peak allocated. CPU: growth of
    the peak resident set, with glibc told to serve every block over 64 KB by mmap
    (returned to the system when freed), so the peak reflects live tensors rather
    than what the allocator had cached from earlier calls."""
    if device.type == "cuda":
        torch.cuda.synchronize()
        base = torch.cuda.memory_allocated()
        torch.cuda.reset_peak_memory_stats()
        run()
        torch.cuda.synchronize()
        return (torch.cuda.max_memory_allocated() - base) / 2**20
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 65536)  # M_MMAP_THRESHOLD (also stops glibc raising it dynamically)
        run()  # settle with this allocation policy
        libc.malloc_trim(0)
        base = _peak_rss_kb()[1]
        open("/proc/self/clear_refs", "w").write("5")  # reset the peak (VmHWM) to the current RSS
    except (OSError, AttributeError):
        return float("nan")
    run()
    return (_peak_rss_kb()[0] - base) / 1024


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="64,96", help="output crop sizes (square), pixels, comma separated")
    ap.add_argument("--sigma", type=float, default=0.6)
    ap.add_argument("--device", default=None, help="cpu or cuda (default: both if CUDA exists)")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (0: leave torch's default)")
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--float64", action="store_true")
    args = ap.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    dtype = torch.float64 if args.float64 else torch.float32
    devices = [args.device] if args.device else (["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"])
    meshes = bench_meshes()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} CPU thread(s), sigma {args.sigma}, "
          f"{IMAGE_W}x{IMAGE_H} views, {dtype}")
    for dev_name in devices:
        device = torch.device(dev_name)
        cpu_time = device.type == "cpu" and torch.get_num_threads() == 1
        clock = time.thread_time if cpu_time else time.perf_counter
        cams4 = bench_cameras(4, dtype=dtype, device=device)
        cams1 = cams4.select([0])
        runs = {}
        for crop in (int(x) for x in args.sizes.split(",")):
            size = (crop, crop)
            print(f"\n[{dev_name}] crop {crop}x{crop}: ms ({'thread CPU time' if cpu_time else 'wall clock'}, "
                  f"median of {args.repeats})")
            print(f"{'mesh':<13}{'faces':>6}{'fwd 1v':>9}{'f+b 1v':>9}{'fwd 4v':>9}{'f+b 4v':>9}"
                  f"{'f+b/view':>10}{'px/view':>9}")
            for name, mesh in meshes.items():
                one = bench_one(mesh, cams1, size, args.sigma, args.repeats, device, dtype, clock)
                four = bench_one(mesh, cams4, size, args.sigma, args.repeats, device, dtype, clock)
                runs[(crop, name)] = four["run"]
                print(f"{name:<13}{len(mesh.faces):>6}{one['fwd']:>9.2f}{one['fwd_bwd']:>9.2f}{four['fwd']:>9.2f}"
                      f"{four['fwd_bwd']:>9.2f}{four['fwd_bwd'] / 4:>10.2f}{four['covered'] / 4:>9.0f}")
        # memory last: on CPU it changes the allocator's policy for the rest of the process
        print(f"\n[{dev_name}] peak extra memory of one 4-view forward + backward, MB")
        for (crop, name), run in runs.items():
            print(f"crop {crop:<4} {name:<13}{peak_memory_mb(run, device):8.1f}")


if __name__ == "__main__":
    main()
