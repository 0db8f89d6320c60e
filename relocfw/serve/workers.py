"""Where queries run, off the event loop: one Relocalizer per worker, one query at a
time each (a Relocalizer is not thread-safe: relocfw.core.pipeline.Relocalizer).

serve.workers=1: one thread of the server process, holding the model the server
loaded. serve.workers=N > 1: N spawned processes, each loading the model once when it
starts and running torch on its share of the cores.
"""

from __future__ import annotations

import concurrent.futures as futures
import functools
import multiprocessing
import os
import signal
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from relocfw.core.camera import PinholeCamera
from relocfw.core.pipeline import Relocalizer
from relocfw.core.values import Localization

# Builds a worker's Relocalizer; picklable (a module-level function or a partial of
# one) where worker processes call it.
Loader = Callable[[], Relocalizer]

# A worker process's own model, set once by `start_worker` as the process starts. A
# process pool gives its workers no other place to keep what they load; the server
# process never sets it (its one worker thread is given the Relocalizer directly).
THIS_PROCESS: dict[str, Relocalizer] = {}


@dataclass(frozen=True, eq=False)
class Query:
    """One decoded image to localize, with its camera and frame name."""

    image: np.ndarray
    camera: PinholeCamera | None = None
    name: str | None = None


def answer(relocalizer: Relocalizer, query: Query) -> Localization:
    return relocalizer.localize(query.image, camera=query.camera, name=query.name)


def start_worker(loader: Loader, threads: int) -> None:
    """A worker process's initializer: deaf to the stop signals, its share of the
    cores, then its model.

    A terminal's Ctrl-C and systemd's stop signal the whole process group, workers
    included; a worker that died of them would fail the queries the server is still
    draining. The server owns the workers' lifetime: its executor's shutdown ends them
    once their queries are answered."""
    for stop in (signal.SIGINT, signal.SIGTERM):
        signal.signal(stop, signal.SIG_IGN)
    torch.set_num_threads(threads)
    THIS_PROCESS["relocalizer"] = loader()


def answer_here(query: Query) -> Localization:
    return answer(THIS_PROCESS["relocalizer"], query)


def process_id() -> int:
    return os.getpid()


def threads_per_worker(workers: int) -> int:
    """Each worker process's torch threads: the cores this process may use, shared."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, (cores or 1) // workers)


class Workers:
    """The executor that runs queries, and how a query is handed to it."""

    def __init__(self, relocalizer: Relocalizer, loader: Loader, count: int) -> None:
        self.count = count
        if count == 1:
            self.executor: futures.Executor = futures.ThreadPoolExecutor(
                max_workers=1, thread_name_prefix="relocfw-query"
            )
            self.run: Callable[[Query], Localization] = functools.partial(answer, relocalizer)
        else:
            self.executor = futures.ProcessPoolExecutor(
                max_workers=count,
                # spawn, not fork: a forked copy of a process running torch's and
                # uvicorn's threads may hold their locks forever.
                mp_context=multiprocessing.get_context("spawn"),
                initializer=start_worker,
                initargs=(loader, threads_per_worker(count)),
            )
            self.run = answer_here

    def warm(self) -> None:
        """Start every worker process (each loads the model) before serving. One call
        per worker: a pool starts a process for each call that finds none idle."""
        if self.count == 1:
            return
        started = [self.executor.submit(process_id) for _ in range(self.count)]
        for future in started:
            future.result()

    def submit(self, query: Query) -> futures.Future[Localization]:
        return self.executor.submit(self.run, query)

    def shutdown(self) -> None:
        """Wait for the queries handed over, then stop the workers."""
        self.executor.shutdown(wait=True)
