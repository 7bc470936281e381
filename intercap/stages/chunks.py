"""The one chunk runner of the fitting stages (object, body, global_fit).

A take is cut into contiguous chunks (`frame_chunks`, `chunk_groups`), each fitted in a worker
process (`intercap.parallel`: their tensors are too small for torch's threads to help, two
single-threaded processes fit a take nearly twice as fast), the chunks of one process side by
side (`lockstep`). A chunk starts cold, as the first frames of a take do; stages that smooth over
time give it frames of context beyond its ends (`Chunk.lo_context`, `hi_context`) and keep only
its own rows. Each chunk saves its progress in one checkpoint format (`Checkpoint`:
OUT/<stage>/progress_LO_HI.npz, written atomically) and a killed run resumes from it.
`fit_in_chunks` is what a stage calls: its fit function per group of chunks, its stitch
function over the chunks' results.
"""
from __future__ import annotations

import logging
import multiprocessing as mp
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from tqdm import tqdm

from intercap import parallel
from intercap.io.files import save_npz

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Chunk:
    """Frames [lo, hi) are this chunk's results; [lo_context, hi_context) is what it may look at."""

    lo: int
    hi: int
    lo_context: int
    hi_context: int


@dataclass(frozen=True)
class Checkpoint:
    """A chunk's saved progress: OUT/<stage>/progress_LO_HI.npz (or another file a stage resumes from,
    as the object stage's seam tracks), arrays by name, written atomically (a run killed while it
    writes keeps the previous one)."""

    path: Path

    @classmethod
    def of_chunk(cls, out_dir: Path, stage: str, chunk: Chunk) -> "Checkpoint":
        return cls(Path(out_dir) / stage / f"progress_{chunk.lo:06d}_{chunk.hi:06d}.npz")

    def exists(self) -> bool:
        return self.path.exists()

    def load(self) -> dict[str, np.ndarray] | None:
        """The saved arrays, or None when nothing is saved."""
        if not self.path.exists():
            return None
        with np.load(self.path) as saved:
            return {name: saved[name] for name in saved.files}

    def save(self, **arrays) -> None:
        save_npz(self.path, **arrays)


def fit_in_chunks(fit: Callable, stitch: Callable, session, cfg, out_dir: Path, groups: list, desc: str,
                  progress: bool, extra: tuple = ()):
    """A fitting stage's take in chunks: `fit(where, cfg, out_dir, *extra, group, queue)` for each group
    of chunks (in worker processes when there are several groups: they load the session from its
    folder themselves), then `stitch(results)` with the groups' results in order (a list per group).
    One progress bar counts the frames every chunk reports."""
    where = session if len(groups) == 1 else session.root
    results = run_chunks(fit, groups, (where, cfg, Path(out_dir), *extra), session.num_frames, desc, progress)
    return stitch(results)


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


def chunk_groups(T: int, cfg, section, align: int = 1) -> list[tuple[Chunk, ...]]:
    """The take's chunks (`run.workers` x the section's `side_by_side`), dealt to the processes: each process runs
    a run of consecutive chunks side by side."""
    workers = parallel.worker_count(cfg)
    chunks = frame_chunks(T, workers * max(1, section.side_by_side), cfg.run.min_frames_per_worker, align)
    n = min(workers, len(chunks))
    bounds = [round(k * len(chunks) / n) for k in range(n + 1)]
    return [tuple(chunks[a:b]) for a, b in zip(bounds[:-1], bounds[1:])]


def run_chunks(fn: Callable, chunks: list[Chunk], args: tuple, total: int, desc: str, progress: bool,
               initial: int = 0) -> list:
    """`fn(*args, chunk, queue)` for every chunk, in worker processes when there are several
    (in this process otherwise, with queue None); returns the results in chunk order. `fn`
    puts the number of frames it finishes on `queue` (or nothing); one bar shows them all."""
    bar = tqdm(total=total, desc=desc, unit="frame", disable=not progress, initial=initial)
    if len(chunks) == 1:
        result = fn(*args, chunks[0], InProcessBar(bar))
        bar.close()
        return [result]
    pool = parallel.worker_pool(len(chunks), max(1, parallel.cpu_count() // len(chunks)))
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
            parallel.shutdown()
            raise
    bar.close()
    return results


class InProcessBar:
    """The queue interface over an in-process progress bar."""

    def __init__(self, bar):
        self.bar = bar

    def put(self, n: int) -> None:
        self.bar.update(n)
