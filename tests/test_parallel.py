"""Worker processes of the frame-parallel stages (`intercap.parallel`)."""
import logging
import multiprocessing as mp
import re
from concurrent.futures import ProcessPoolExecutor

from intercap.config import load_config
from intercap.parallel import cpu_count, init_worker_logging, shutdown, worker_count
from intercap.pipeline import run_log
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


def test_worker_log_records_reach_the_run_log(tmp_path, capfd):
    """Inside `run_log` (OUT/run.log of a run) the workers append their INFO and WARNING lines to the
    file, whole and timestamped as the parent's; their stderr still shows the warnings only."""
    path = tmp_path / "run.log"
    chunks = frame_chunks(4, workers=2, min_frames=1)
    shutdown()
    try:
        with run_log(path):
            logging.getLogger("intercap.test").info("the parent's line")
            # logging.warning(msg, chunk, queue) stands in for a stage's chunk function that warns
            run_chunks(logging.warning, chunks, ("worker warns on %s (%s)",), 4, "warn", False)
            run_chunks(logging.info, chunks, ("worker informs on %s (%s)",), 4, "info", False)
    finally:
        shutdown()
    lines = path.read_text().splitlines()
    stamp = r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+ "
    assert any(re.fullmatch(stamp + "INFO intercap.test: the parent's line", line) for line in lines)
    for level, verb in (("WARNING", "warns"), ("INFO", "informs")):
        for chunk in chunks:
            line_of_chunk = stamp + f"{level} root: worker {verb} on {re.escape(str(chunk))} \\(.*\\)"
            assert sum(bool(re.fullmatch(line_of_chunk, line)) for line in lines) == 1, (level, chunk, lines)
    err = capfd.readouterr().err
    assert "worker warns on" in err and "worker informs on" not in err


def test_worker_logging_appends_info_and_up_to_the_file_it_is_given(tmp_path):
    """The pool initializer's logging on its own, in a pool of one: the worker's lines land in the file."""
    path = tmp_path / "worker.log"
    path.write_text("before\n")
    with ProcessPoolExecutor(1, mp_context=mp.get_context("spawn"), initializer=init_worker_logging,
                             initargs=(str(path),)) as pool:
        for log in (logging.warning, logging.info, logging.debug):
            pool.submit(log, "a %s line", log.__name__).result()
    lines = path.read_text().splitlines()
    assert lines[0] == "before" and len(lines) == 3, lines
    assert lines[1].endswith(" WARNING root: a warning line") and lines[2].endswith(" INFO root: a info line")
