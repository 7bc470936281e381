"""The worker processes of the frame-parallel stages (the chunks they fit: `intercap.stages.chunks`).

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
`run_pipeline` shuts them down at its end (`shutdown`). Their warnings go to their stderr and,
with their INFO lines, to the run's OUT/run.log (`logging_to`).
"""
from __future__ import annotations

import logging
import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager

log = logging.getLogger(__name__)


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


LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"  # OUT/run.log's lines
_run_log: dict = {"path": None}


@contextmanager
def logging_to(path):
    """Worker processes started while the block runs also write their log records (INFO and up) to
    `path` (OUT/run.log: `pipeline.run_log`), appending, as the parent does; their warnings still
    reach their stderr."""
    before, _run_log["path"] = _run_log["path"], os.path.abspath(path)
    try:
        yield
    finally:
        _run_log["path"] = before


def _init_worker(threads: int, deterministic: bool, log_path: str | None = None) -> None:
    import torch

    torch.set_num_threads(threads)
    torch.use_deterministic_algorithms(deterministic)
    init_worker_logging(log_path)


def init_worker_logging(log_path: str | None) -> None:
    """A worker's logging: WARNING and up on stderr and, with `log_path`, INFO and up appended to
    that file (one write per line, so the lines of several processes do not mix)."""
    logging.basicConfig(level=logging.WARNING)
    if log_path is None:
        return
    root = logging.getLogger()
    for handler in root.handlers:
        handler.setLevel(max(handler.level, logging.WARNING))
    to_file = logging.FileHandler(log_path, mode="a", encoding="utf-8")
    to_file.setLevel(logging.INFO)
    to_file.setFormatter(logging.Formatter(LOG_FORMAT))
    root.addHandler(to_file)
    root.setLevel(logging.INFO)


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
    in this process: `repeatable`, logging to the run's log: `logging_to`), started on first use and
    kept for the next stage; started anew when these change or a worker died."""
    import torch

    key = (workers, threads, torch.are_deterministic_algorithms_enabled(), _run_log["path"])
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
