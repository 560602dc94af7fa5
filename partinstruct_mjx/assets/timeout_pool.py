"""A process pool whose jobs each have a time limit: a job over it is killed and reported, its worker replaced.

concurrent.futures cannot stop a running task; CoACD can run for many minutes on a bad mesh, so each worker is a
plain process that can be terminated.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class JobResult:
    key: Any
    value: Any = None
    error: str | None = None


def _serve(function: Callable, connection) -> None:
    while True:
        job = connection.recv()
        if job is None:
            return
        key, args = job
        try:
            connection.send(JobResult(key, value=function(*args)))
        except Exception as err:  # reported to the parent, which names the job
            connection.send(JobResult(key, error=f"{type(err).__name__}: {err}"))


class _Worker:
    def __init__(self, context, function):
        self.connection, child = context.Pipe()
        self.process = context.Process(target=_serve, args=(function, child), daemon=True)
        self.process.start()
        self.job = None
        self.started = 0.0

    def stop(self, kill: bool = False) -> None:
        if kill:
            self.process.kill()
        else:
            try:
                self.connection.send(None)
            except OSError:
                pass
        self.process.join(timeout=5)


def _poll(worker: _Worker, timeout: float) -> tuple[JobResult | None, bool]:
    """(the job's result or None while it runs, whether the worker can take another job)."""
    key = worker.job[0]
    try:
        if worker.connection.poll():
            return worker.connection.recv(), True
    except (EOFError, OSError):
        return JobResult(key, error=f"worker died (exit code {worker.process.exitcode})"), False
    if not worker.process.is_alive():
        return JobResult(key, error=f"worker died (exit code {worker.process.exitcode})"), False
    if time.monotonic() - worker.started > timeout:
        return JobResult(key, error=f"timed out after {timeout:g} s"), False
    return None, True


def run_jobs(function: Callable, jobs: list[tuple[Any, tuple]], workers: int, timeout: float,
             poll_interval: float = 0.02) -> Iterator[JobResult]:
    """Run `function(*args)` for each (key, args) in `jobs` on `workers` processes; yield results as they finish.

    A job running longer than `timeout` seconds is killed and yields an error naming the limit.
    `function` must be importable by the spawned workers (a module-level function).
    """
    context = mp.get_context("spawn")
    pending = list(reversed(jobs))
    pool = [_Worker(context, function) for _ in range(max(1, min(workers, len(jobs))))]
    try:
        while pending or any(w.job is not None for w in pool):
            for index, worker in enumerate(pool):
                if worker.job is None and pending:
                    worker.job = pending.pop()
                    worker.started = time.monotonic()
                    worker.connection.send(worker.job)
                elif worker.job is not None:
                    result, healthy = _poll(worker, timeout)
                    if result is None:
                        continue
                    yield result
                    worker.job = None
                    if not healthy:
                        worker.stop(kill=True)
                        pool[index] = _Worker(context, function)
            time.sleep(poll_interval)
    finally:
        for worker in pool:
            worker.stop(kill=worker.job is not None)
