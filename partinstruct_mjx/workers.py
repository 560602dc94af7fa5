"""Objects simulated at once in threads: demo synthesis and evaluation run one object's env per worker thread;
evaluation can use worker processes instead (`process_pool`), which also draw large episode selections.

JAX and C MuJoCo release the GIL, so one thread's physics runs while another's JAX oracle, IK or policy does; on a
GPU several small batches keep the device busier than one. Results do not depend on the number of workers: every
random draw derives from the seed and the episode, never from the thread that ran it.
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_EXCEPTION, Executor, ProcessPoolExecutor, ThreadPoolExecutor, wait
from contextlib import contextmanager

PREALLOCATE = "XLA_PYTHON_CLIENT_PREALLOCATE"


def default_workers(backend: str) -> int:
    """Objects simulated at once by default: 2 on the mujoco backend with 2 or more cores (one thread's physics runs
    while the other's JAX work does), 1 on the mjx backend (one device)."""
    return 1 if backend == "mjx" else min(2, os.cpu_count() or 1)


def threads_per_worker(num_threads: int | None, workers: int) -> int:
    """Physics threads each worker's env gets: its share of `num_threads` (None: the cores), at least 1."""
    return max(1, (num_threads or os.cpu_count() or 1) // workers)


def run_in_threads(items: Iterable, workers: int, work: Callable[[int, object, threading.Event], None],
                   name: str) -> None:
    """Call `work(slot, item, stop)` for every item, `workers` threads taking items off one queue (`slot`, the
    thread's index, picks per-thread resources such as a policy of its own). The first exception in a thread, or a
    KeyboardInterrupt while waiting, sets `stop`, waits for the threads (`work` should return soon once `stop` is
    set) and is raised."""
    todo = queue.SimpleQueue()
    for item in items:
        todo.put(item)
    stop = threading.Event()

    def drain(slot: int) -> None:
        while not stop.is_set():
            try:
                item = todo.get_nowait()
            except queue.Empty:
                return
            work(slot, item, stop)

    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix=name) as pool:
        runs = [pool.submit(drain, slot) for slot in range(workers)]
        try:
            wait(runs, return_when=FIRST_EXCEPTION)
            for run in runs:
                if run.done() and run.exception() is not None:
                    raise run.exception()
        except BaseException:
            stop.set()
            wait(runs)
            raise


@contextmanager
def gpu_shared() -> Iterator[None]:
    """Within it, JAX initialised in this process or in processes it spawns does not preallocate GPU memory
    (PREALLOCATE=false unless set; JAX takes 75 % of the GPU by default), so that several processes share one GPU."""
    before = os.environ.get(PREALLOCATE)
    os.environ.setdefault(PREALLOCATE, "false")
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(PREALLOCATE, None)


@contextmanager
def process_pool(processes: int) -> Iterator[Executor | None]:
    """`processes` spawned worker processes (None for 1), each with the persistent compilation cache on; they start
    when the first job is submitted. They share the GPU (`gpu_shared`)."""
    if processes == 1:
        yield None
        return
    from partinstruct_mjx.jax_setup import enable_compilation_cache

    with gpu_shared():
        pool = ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=enable_compilation_cache)
        try:
            yield pool
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
