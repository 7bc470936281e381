"""Tensor operations per frame, per stage: what a GPU run's time follows, counted on the CPU.

On a GPU the fitting stages run small tensors (one body batch, one object, a few
views), so each operation costs its launch and the Python around it, not its
arithmetic: on one H100 the sample's object, body and global stages took 25, 27
and 25 us per counted kernel operation, the 150-frame 640x576 bench 35-39 us
(its image decoding and k-d trees are CPU work besides; BENCHMARKS.md,
2026-11-27). So the count of operations per frame predicts a GPU's seconds per
frame (25 us per kernel: a floor), and a change that cuts it can be measured
without a GPU.

Runs the pipeline in one process (`run.workers=1`, as a GPU runs it; each stage
redone; the renderer cuts its work in a GPU's chunks) and counts every aten operation the selected stages dispatch
(`TorchDispatchMode`): all of them, the kernels among them (views, reshapes
and selections launch nothing) and the kernels of the backward passes, per
frame; then the intercap functions that issue most forward kernels (an
operation inside a library, e.g. the body model, counts at its intercap
caller). Counting slows the run several times: its timings mean nothing.

    python -m tools.count_ops --session data_samples/sample [--stages object,body,global] [--alone]
                              [--out DIR] [--sites 15] [--graphs] [--lines] [--set SECTION.KEY=VALUE ...]

`--alone` runs only the counted stages (for one that needs no earlier stage's results: object).
`--graphs` counts what the fits record on a GPU (`optim.recorded`: the body's, the global stage's
and the object's evaluations, the L-BFGS's direction, verdict and step) after each one's first call
apart, as the CUDA-graph replays a GPU runs them as: one launch each; the stages run as they do
where graphs are recorded (`optim.records_graphs`: the object renders in fixed shapes, the depth
pairs keep theirs).

`--lines` names each site down to its line, and looks into our body models, anny and roma too
(anny's phenotype weights and kinematics were found so).

`--set body.batch_frames=32 --set body.side_by_side=8 --set global.window_frames=300 --set
object.side_by_side=8 --set body.line_search=armijo --set global.line_search=armijo` runs the GPU's
settings (`body.batch_frames_gpu`, `body.side_by_side_gpu`, `global.window_frames_gpu`,
`object.side_by_side_gpu`, and the line search "auto" picks on CUDA).
"""
from __future__ import annotations

import argparse
import collections
import dataclasses
import logging
import sys
import tempfile
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from intercap.energies.optim import HOST_WAITS

# aten operations that only describe a tensor's view of memory: no kernel on a GPU
VIEW_OPS = {"view", "_unsafe_view", "reshape", "select", "slice", "unsqueeze", "squeeze", "expand", "t", "transpose",
            "permute", "as_strided", "alias", "detach", "unbind", "split", "split_with_sizes", "chunk", "narrow",
            "diagonal", "lift_fresh", "view_as_real", "view_as_complex", "_reshape_alias"}
US_PER_KERNEL_H100 = 25.0  # the sample's stages on one H100 (2026-11-26): seconds per frame / kernels per frame


class OperationCount(TorchDispatchMode):
    """Counts the aten operations dispatched while active; kernels by the intercap function issuing
    them. Kernels of evaluations a GPU replays from a recorded CUDA graph (`replaying`) count apart
    (`in_graphs`, and one launch per replay in `replays`); those by issuing function too, or for the
    backward passes by autograd node (`graph_sites`): what a fused evaluation would have to cut."""

    def __init__(self, lines: bool = False):
        super().__init__()
        self.lines = lines
        self.all = self.kernels = self.backward = self.in_graphs = self.replays = self.waits = 0
        self.replaying = False
        self.sites = collections.Counter()
        self.wait_sites = collections.Counter()
        self.graph_sites = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.all += 1
        name = func.overloadpacket.__name__
        if name in HOST_WAITS:
            self.waits += 1
            self.wait_sites[issuing_function(sys._getframe(1), self.lines)] += 1
        if name in VIEW_OPS:
            pass
        elif self.replaying:
            self.in_graphs += 1
            node = torch._C._current_autograd_node()
            self.graph_sites[f"backward {node.name()}" if node is not None
                             else issuing_function(sys._getframe(1), self.lines)] += 1
        else:
            self.kernels += 1
            if torch._C._current_autograd_node() is not None:
                self.backward += 1
            else:
                self.sites[issuing_function(sys._getframe(1), self.lines)] += 1
        return func(*args, **(kwargs or {}))


LINE_PACKAGES = ("body_models", "anny", "roma")  # `--lines` looks into these too, not only intercap


def issuing_function(frame, lines: bool = False) -> str:
    """module:function of the innermost intercap frame on the stack ("-" when none). `lines`: the
    innermost frame of intercap, our body models, anny or roma, as package:module:function:line
    (which line of the body model's forward, or of a library, issues the most)."""
    while frame is not None:
        path = frame.f_code.co_filename.replace("\\", "/")
        if "/intercap/" in path and "site-packages" not in path:
            where = f"{path.rsplit('/intercap/', 1)[1][:-3].replace('/', '.')}:{frame.f_code.co_name}"
            return f"intercap:{where}:{frame.f_lineno}" if lines else where
        if lines:
            package = next((p for p in LINE_PACKAGES if f"/{p}/" in path), None)
            if package is not None:
                module = path.rsplit(f"/{package}/", 1)[1][:-3].replace("/", ".")
                return f"{package}:{module}:{frame.f_code.co_name}:{frame.f_lineno}"
        frame = frame.f_back
    return "-"


def count_stages(session: Path, out: Path, stages: list[str], overrides: list[str],
                 alone: bool = False, graphs: bool = False, lines: bool = False) -> tuple[dict, int]:
    """Run the pipeline (or, `alone`, only `stages`) on `session` into `out`, counting inside `stages`
    (`lines`: sites by line, `issuing_function`): ({stage: OperationCount}, frames)."""
    from intercap import pipeline
    from intercap.config import load_config
    from intercap.session import Session

    from intercap.energies import optim

    counts, running = {}, {}
    originals = dict(pipeline.STAGES)
    record, records_graphs = optim.recorded, optim.records_graphs

    def counted(name, run):
        def run_counting(session, cfg, out_dir, progress):
            counts[name] = running["stage"] = OperationCount(lines)
            try:
                with counts[name]:
                    return run(session, cfg, out_dir, progress)
            finally:
                running.clear()
        return run_counting

    def as_on_a_gpu(fn, enabled, device):
        """`optim.recorded` as on a GPU: calls after the first count as graph replays (the fits record
        where `cuda_graphs` is on; the global stage's windows with a free flight stay eager)."""
        if not enabled:
            return fn
        calls = []

        def counted():
            calls.append(1)
            counter = running.get("stage")
            if len(calls) == 1 or counter is None:
                return fn()
            counter.replaying, counter.replays = True, counter.replays + 1
            try:
                return fn()
            finally:
                counter.replaying = False
        return counted

    from intercap.geometry import rendering

    cpu_pairs = rendering.MAX_PAIRS["cpu"]
    rendering.MAX_PAIRS["cpu"] = rendering.MAX_PAIRS["cuda"]  # the renderer's work in a GPU's chunks
    if graphs:  # the stages record (depth pairs and renders in fixed shapes), counted as replays
        optim.recorded, optim.records_graphs = as_on_a_gpu, lambda device: True
    try:
        for name in stages:
            pipeline.STAGES[name] = dataclasses.replace(originals[name], run=counted(name, originals[name].run))
        cfg = load_config(overrides=["run.force=true", "run.workers=1", "report.enabled=false", *overrides])
        pipeline.run_pipeline(session, out, cfg, stages=stages if alone else None, progress=False)
    finally:
        pipeline.STAGES.update(originals)
        rendering.MAX_PAIRS["cpu"] = cpu_pairs
        optim.recorded, optim.records_graphs = record, records_graphs
    return counts, Session.load(session).num_frames


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--session", type=Path, required=True)
    parser.add_argument("--stages", default="object,body,global", help="the stages to count (all stages run)")
    parser.add_argument("--alone", action="store_true", help="run only the counted stages, not the whole pipeline")
    parser.add_argument("--out", type=Path, help="results folder (default: a temporary one)")
    parser.add_argument("--sites", type=int, default=15, help="issuing functions listed per stage")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="config override")
    parser.add_argument("--graphs", action="store_true",
                        help="count the fits' evaluations after each fit's first as CUDA-graph replays")
    parser.add_argument("--lines", action="store_true",
                        help="sites by line, looking into the body models, anny and roma too")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    from intercap.pipeline import STAGES

    stages = [s.strip() for s in args.stages.split(",") if s.strip()]
    unknown = [s for s in stages if s not in STAGES]
    if unknown:
        parser.error(f"unknown stage(s) {', '.join(unknown)}; available: {', '.join(STAGES)}")
    with tempfile.TemporaryDirectory(prefix="count_ops_") as scratch:
        counts, T = count_stages(args.session, args.out or Path(scratch), stages, args.set, args.alone, args.graphs,
                                 args.lines)

    print(f"\noperations per frame on {args.session} ({T} frames; {' '.join(args.set) or 'default settings'})")
    print(f"{'stage':8s} {'all':>9s} {'kernels':>9s} {'backward':>9s} {'in graphs':>10s} {'replays':>8s} "
          f"{'waits':>7s} {'H100 s/frame >= (25 us a launch)':>33s}")
    for name, c in counts.items():
        launches = (c.kernels + c.replays) / T
        print(f"{name:8s} {c.all / T:9.0f} {c.kernels / T:9.0f} {c.backward / T:9.0f} {c.in_graphs / T:10.0f} "
              f"{c.replays / T:8.1f} {c.waits / T:7.1f} {launches * US_PER_KERNEL_H100 * 1e-6:33.3f}")
    total = sum(c.kernels + c.replays for c in counts.values()) / T
    print(f"{'total':8s} {'':9s} {'':9s} {'':9s} {'':10s} {'':8s} {'':7s} {total * US_PER_KERNEL_H100 * 1e-6:33.3f}")
    if args.graphs:
        print("(kernels: launched one by one; in graphs: run by the replays, whose GPU time this does not count)")
    print("(waits: operations the host waits on, `optim.HOST_WAITS`, on a GPU each drains its queue; also counted "
          "where a GPU run keeps the tensors on the CPU)")
    for name, c in counts.items():
        print(f"\n{name}: forward kernels per frame by issuing function")
        for site, n in c.sites.most_common(args.sites):
            print(f"  {n / T:8.0f}  {site}")
        print(f"{name}: host waits per frame by issuing function")
        for site, n in c.wait_sites.most_common(args.sites):
            print(f"  {n / T:8.1f}  {site}")
        if c.graph_sites:
            print(f"{name}: kernels inside the graphs per frame by issuing function (backward: by autograd node)")
            for site, n in c.graph_sites.most_common(args.sites):
                print(f"  {n / T:8.0f}  {site}")


if __name__ == "__main__":
    main()
