"""Worker processes of the frame-parallel stages (`intercap.parallel`)."""
import multiprocessing as mp

from intercap.config import load_config
from intercap.parallel import cpu_count, shutdown, worker_count
from intercap.stages.chunks import frame_chunks, run_chunks


def test_processes_share_a_gpu_only_when_asked():
    """One process per core on the CPU; one on a GPU unless run.workers asks for more."""
    assert worker_count(load_config()) == cpu_count()
    assert worker_count(load_config(overrides=["run.device=cuda"])) == 1
    assert worker_count(load_config(overrides=["run.device=cuda", "run.workers=6"])) == 6
    assert worker_count(load_config(overrides=["run.workers=3"])) == 3


def test_worker_processes_serve_one_stage_after_another_until_shut_down():
    """Starting a worker costs seconds of imports and model loading: the next stage of a run finds
    the same processes; `shutdown` (end of `run_pipeline`) stops them."""
    chunks = frame_chunks(4, workers=2, min_frames=1)
    shutdown()
    before = {p.pid for p in mp.active_children()}
    try:
        # `print(chunk, queue)` stands in for a stage's chunk function: picklable, harmless
        assert run_chunks(print, chunks, (), 4, "first", False) == [None, None]
        workers = {p.pid for p in mp.active_children()} - before
        assert len(workers) == 2
        run_chunks(print, chunks, (), 4, "second", False)
        assert {p.pid for p in mp.active_children()} - before == workers
    finally:
        shutdown()
    assert not ({p.pid for p in mp.active_children()} - before)
