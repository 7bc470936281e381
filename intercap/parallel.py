"""Frame-parallel stages: a take cut into contiguous chunks, one worker process per chunk.

The fitting stages run small tensors (8-48 frames of a 2,000-vertex body) whose
operations are too short to gain from torch's intra-op threads: on two cores
two threads run a body batch barely faster than one (BENCHMARKS.md). Two
single-threaded processes, each fitting half the take, run it nearly twice as
fast. A chunk starts cold, as the first frames of a take do, so the chunks'
results are those of a take cut in two; stages that smooth over time give each
chunk some frames of context beyond its ends (`Chunk.lo_context`, `hi_context`).

Workers are spawned (not forked: torch's OpenMP pool does not survive a fork),
load the session and the model themselves, and report finished frames through
a queue so the parent shows one progress bar. The worker processes outlive a
stage: the next stage of the run finds torch, the libraries and the body model
already loaded there (starting a worker cost ~5 s of imports, per stage), and
`run_pipeline` shuts them down at its end (`shutdown`).
"""
from __future__ import annotations

import logging
import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable

from tqdm import tqdm

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Chunk:
    """Frames [lo, hi) are this chunk's results; [lo_context, hi_context) is what it may look at."""

    lo: int
    hi: int
    lo_context: int
    hi_context: int


def cpu_count() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def on_gpu(cfg) -> bool:
    """Whether the run's fitting stages run on a CUDA device (`run.device`)."""
    return str(cfg.run.device).startswith("cuda")


def worker_count(cfg) -> int:
    """`run.workers`, 0 meaning one per CPU core on the CPU and one process on a GPU.

    Several processes may share one GPU (`run.workers` > 1 with `run.device=cuda`): a
    stage's GPU work is a chain of small kernels, so one process leaves the GPU waiting
    on Python and kernel launches, which processes side by side overlap."""
    if on_gpu(cfg):
        return max(1, cfg.run.workers or 1)
    return max(1, cfg.run.workers or cpu_count())


def frame_chunks(T: int, workers: int, min_frames: int, align: int = 1, context: int = 0) -> list[Chunk]:
    """Contiguous chunks covering [0, T), at most `workers`, none shorter than `min_frames`,
    boundaries on multiples of `align` (a stage's batch size), each with `context` frames
    either side where the take has them."""
    n = max(1, min(workers, T // max(min_frames, 1)))
    bounds = [0]
    for k in range(1, n):
        cut = round(k * T / n / align) * align
        if bounds[-1] < cut < T:
            bounds.append(cut)
    bounds.append(T)
    return [Chunk(a, b, max(0, a - context), min(T, b + context)) for a, b in zip(bounds[:-1], bounds[1:])]


def lockstep(runs: list, serve: Callable[[list], list]) -> list:
    """Runs generators side by side: each round, `serve` gets the pending request of every unfinished
    run (in run order) and returns one reply per request, each sent back to its run (so one
    evaluation serves them all). Returns the runs' results in order."""
    results, pending = [None] * len(runs), {}

    def advance(k: int, reply) -> None:
        try:
            pending[k] = runs[k].send(reply)
        except StopIteration as finished:
            pending.pop(k, None)
            results[k] = finished.value

    for k in range(len(runs)):
        advance(k, None)
    while pending:
        order = sorted(pending)
        for k, reply in zip(order, serve([pending[k] for k in order])):
            advance(k, reply)
    return results


def side_by_side(cfg, section) -> int:
    """Chunks one process runs side by side in a stage: its config `section`'s `side_by_side`, or
    `side_by_side_gpu` on CUDA (a GPU's step costs its kernel launches, whatever the chunks)."""
    return max(1, section.side_by_side_gpu if on_gpu(cfg) else section.side_by_side)


def chunk_groups(T: int, cfg, section, align: int = 1) -> list[tuple[Chunk, ...]]:
    """The take's chunks (`run.workers` x `side_by_side`), dealt to the processes: each process runs
    a run of consecutive chunks side by side."""
    workers = worker_count(cfg)
    chunks = frame_chunks(T, workers * side_by_side(cfg, section), cfg.run.min_frames_per_worker, align)
    n = min(workers, len(chunks))
    bounds = [round(k * len(chunks) / n) for k in range(n + 1)]
    return [tuple(chunks[a:b]) for a, b in zip(bounds[:-1], bounds[1:])]


def _init_worker(threads: int, deterministic: bool) -> None:
    import torch

    torch.set_num_threads(threads)
    torch.use_deterministic_algorithms(deterministic)
    logging.basicConfig(level=logging.WARNING)


@contextmanager
def repeatable(cfg):
    """torch's deterministic algorithms while the stages run on the CPU (`run.deterministic`), so a
    rerun gives the same numbers: with two or more threads, the backward of indexing (an
    index_put with accumulation) otherwise adds in thread order, and the sample's body poses
    differed by up to 0.05 rad between runs. Measured no slower on the CPU. The worker processes
    take the setting of the process that starts them. CUDA keeps its atomics (not measured)."""
    import torch

    before = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(bool(cfg.run.deterministic) and not on_gpu(cfg))
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(before)


_pool: dict = {"executor": None, "key": None}


def worker_pool(workers: int, threads: int) -> ProcessPoolExecutor:
    """The run's worker processes (`workers`, `threads` torch threads each, deterministic algorithms as
    in this process: `repeatable`), started on first use and kept for the next stage; started anew
    when these change or a worker died."""
    import torch

    key = (workers, threads, torch.are_deterministic_algorithms_enabled())
    executor = _pool["executor"]
    if executor is not None and (_pool["key"] != key or getattr(executor, "_broken", False)):
        shutdown()
        executor = None
    if executor is None:
        executor = ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_init_worker,
                                       initargs=key[1:])
        _pool.update(executor=executor, key=key)
    return executor


def shutdown() -> None:
    """Stop the worker processes (the next `run_chunks` starts new ones)."""
    executor, _pool["executor"], _pool["key"] = _pool["executor"], None, None
    if executor is not None:
        executor.shutdown(wait=True, cancel_futures=True)


def run_chunks(fn: Callable, chunks: list[Chunk], args: tuple, total: int, desc: str, progress: bool,
               initial: int = 0) -> list:
    """`fn(*args, chunk, queue)` for every chunk, in worker processes when there are several
    (in this process otherwise, with queue None); returns the results in chunk order. `fn`
    puts the number of frames it finishes on `queue` (or nothing); one bar shows them all."""
    bar = tqdm(total=total, desc=desc, unit="frame", disable=not progress, initial=initial)
    if len(chunks) == 1:
        result = fn(*args, chunks[0], _Bar(bar))
        bar.close()
        return [result]
    pool = worker_pool(len(chunks), max(1, cpu_count() // len(chunks)))
    with mp.get_context("spawn").Manager() as manager:
        queue = manager.Queue()
        futures = [pool.submit(fn, *args, chunk, queue) for chunk in chunks]
        while not all(f.done() for f in futures):
            try:
                bar.update(queue.get(timeout=0.5))
            except Exception:  # noqa: BLE001 - queue.Empty through the manager proxy
                pass
        while not queue.empty():
            bar.update(queue.get())
        try:
            results = [f.result() for f in futures]  # re-raises a worker's error here
        except BrokenProcessPool:  # a worker died (killed, out of memory): the next stage starts new ones
            shutdown()
            raise
    bar.close()
    return results


class _Bar:
    """The queue interface over an in-process progress bar."""

    def __init__(self, bar):
        self.bar = bar

    def put(self, n: int) -> None:
        self.bar.update(n)
