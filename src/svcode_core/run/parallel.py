"""Frame-parallel reconstruction: in process, or on a dask.distributed cluster.

Frames of a recording are independent, so they scale out over workers with no
communication except the frames themselves. Every backend here takes a *factory*, a
picklable zero-argument callable returning a reconstructor of any method (normally a
:class:`~svcode_core.methods.build.MethodSpec`), and yields ``(index, reconstruction,
views, counters)`` as frames finish, in completion order.

On dask, the factory is scattered to every worker once, and each worker process builds
its reconstructor (loads the model) on its first frame and keeps it in a worker-side cache
for the rest of the run, so a model is loaded once per worker. Frames are read by the
client and sent to the workers; at most ``2 × workers`` frames are in flight, so memory
stays bounded on both sides.

Running on a cluster with GPUs
    Start a scheduler (``dask scheduler``) and one worker per GPU, each with one thread and
    its GPU pinned, e.g. on every node and for every GPU ``i``::

        CUDA_VISIBLE_DEVICES=i dask worker tcp://SCHEDULER:8786 --nthreads 1 --nworkers 1

    (or ``dask-cuda-worker``, or a ``dask_jobqueue`` cluster on SLURM/PBS). Then run
    ``svcode reconstruct MEAS.tif --out OUT.tif --weights MODEL --device cuda
    --scheduler tcp://SCHEDULER:8786``. The weights file must be readable by the workers at
    the same path (a shared file system); the input is read and the output written only by
    the client. Each worker loads the model once on its GPU; frames are spread over the
    workers as they become free, and an interrupted run resumes from the frames already
    written (see :mod:`svcode_core.run.stream`).
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import signal
import threading
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from typing import Any

import numpy as np
import torch

from ..methods.base import BaseReconstructor

__all__ = ["dask_client", "dask_frames", "local_frames"]

#: ``(index, reconstruction, views or None, counters)``: the counters are the frame's
#: tiles (``tiles_run``, ``tiles_skipped``, ``tiles_total``) and its ``exposure_gain``
#: (``None`` for a method that does not normalise)
FrameResult = tuple[int, np.ndarray, "np.ndarray | None", dict[str, Any]]
Factory = Callable[[], BaseReconstructor]


def _counters(result: Any) -> dict[str, Any]:
    gains = result.exposure_gains
    return {
        "tiles_run": result.tiles_run,
        "tiles_skipped": result.tiles_skipped,
        "tiles_total": result.tiles_total,
        "exposure_gain": None if gains is None else float(np.ravel(gains)[0]),
    }


def local_frames(
    factory: Factory,
    frames: Sequence[np.ndarray],
    indices: Iterable[int],
    return_views: bool,
    threads: int | None = None,
) -> Iterator[FrameResult]:
    """Reconstruct ``frames[i]`` for every ``i`` in ``indices`` in this process.

    A reconstructor that allows it
    (:attr:`~svcode_core.methods.base.BaseReconstructor.frames_side_by_side`) runs the
    first frame alone (it fills the mask cache), then the others ``threads`` at a time
    side by side, and yields them in completion order; at most ``2 × threads`` frames
    are in flight. Every frame, the first too, runs on one torch thread: measured on the
    bundled ``cm2-mini`` model, a frame takes as long on two threads as on one (0.86 s for
    the first, whose masks are computed, 0.42-0.56 s for the others) at up to twice the
    CPU time. Otherwise the frames run one after another, in order, on every thread.

    Parameters
    ----------
    factory : callable
        Builds the reconstructor.
    frames : sequence of numpy.ndarray
    indices : iterable of int
    return_views : bool
    threads : int, optional
        Frames side by side; default :func:`torch.get_num_threads`.
    """
    reconstructor = factory()
    pending = list(indices)
    threads = torch.get_num_threads() if threads is None else threads

    def run(index: int, frame: np.ndarray) -> FrameResult:
        result = reconstructor.reconstruct(frame, return_views)
        return index, result.reconstruction, result.views, _counters(result)

    if not (reconstructor.frames_side_by_side and threads > 1 and len(pending) > 2):
        yield from (run(index, frames[index]) for index in pending)
        return
    rest = iter(pending[1:])
    with _torch_threads(1), ThreadPoolExecutor(threads, "svcode-frame") as pool:
        yield run(pending[0], frames[pending[0]])

        def submit(index: int) -> Future:  # the frame is read here, in this thread
            return pool.submit(run, index, np.asarray(frames[index]))

        running = {submit(index) for index in itertools.islice(rest, 2 * threads)}
        try:
            while running:
                done, running = wait(running, return_when=FIRST_COMPLETED)
                for future in done:
                    yield future.result()
                    following = next(rest, None)
                    if following is not None:
                        running.add(submit(following))
        finally:  # stopped early (an error, an interrupt): drop the frames not started
            for future in running:
                future.cancel()


@contextlib.contextmanager
def _torch_threads(count: int) -> Iterator[None]:
    """Torch's intra-op threads set to ``count`` meanwhile."""
    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)


_WORKER_CACHE: dict[str, BaseReconstructor] = {}
_WORKER_LOCK = threading.Lock()


def _reconstruct_on_worker(
    token: str, factory: Factory, frame: np.ndarray, return_views: bool
) -> tuple[np.ndarray, np.ndarray | None, dict[str, Any]]:
    """Dask task: reconstruct one frame with this worker's cached reconstructor."""
    with _WORKER_LOCK:
        reconstructor = _WORKER_CACHE.get(token)
        if reconstructor is None:
            _WORKER_CACHE.clear()  # one model per worker: drop the previous run's
            reconstructor = _WORKER_CACHE[token] = factory()
    result = reconstructor.reconstruct(frame, return_views)
    return result.reconstruction, result.views, _counters(result)


def dask_frames(
    factory: Factory,
    frames: Sequence[np.ndarray],
    indices: Iterable[int],
    return_views: bool,
    client: Any,
) -> Iterator[FrameResult]:
    """Reconstruct frames on the workers of a :class:`distributed.Client`.

    Parameters
    ----------
    factory : callable
        Picklable; builds the reconstructor once per worker.
    frames : sequence of numpy.ndarray
        Raw frames, read here (on the client) one at a time.
    indices : iterable of int
        Frames to reconstruct.
    return_views : bool
    client : distributed.Client

    Yields
    ------
    tuple
        ``(index, reconstruction, views or None, counters)`` in completion order.
    """
    from distributed import as_completed

    token = uuid.uuid4().hex
    [shared] = client.scatter([factory], broadcast=True, hash=False)
    window = 2 * max(len(client.scheduler_info().get("workers", {})), 1)
    pending = iter(indices)
    index_of: dict[Any, int] = {}

    def submit() -> Any:
        index = next(pending, None)
        if index is None:
            return None
        frame = np.array(frames[index], dtype=np.float32)
        future = client.submit(
            _reconstruct_on_worker, token, shared, frame, return_views, pure=False
        )
        index_of[future] = index
        return future

    running = as_completed([f for f in (submit() for _ in range(window)) if f is not None])
    for future in running:
        recon, views, counters = future.result()
        yield index_of.pop(future), recon, views, counters
        following = submit()
        if following is not None:
            running.add(following)


@contextlib.contextmanager
def dask_client(workers: int = 0, scheduler: str | None = None) -> Iterator[Any]:
    """A client of the cluster at ``scheduler``, or of a new local cluster of ``workers``.

    The local cluster runs ``workers`` processes with one thread each (and one OpenMP
    thread each, so that they do not compete for cores); it is shut down on exit.

    Raises
    ------
    svcode_core.extras.NotInstalled
        Without ``distributed`` (the ``dask`` extra).
    """
    from ..extras import require

    distributed = require("distributed", "dask", "frames on a dask cluster (--workers, "
                          "--scheduler)")  # fmt: skip
    Client, LocalCluster = distributed.Client, distributed.LocalCluster

    if scheduler:
        with Client(scheduler) as client:
            yield client
        return
    if workers < 1:
        raise ValueError(f"workers must be >= 1 for a local dask cluster, got {workers}")
    threads = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    with _sigint_ignored():
        cluster = LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            env=threads,
            silence_logs=logging.ERROR,  # no warnings of tasks cancelled by an interruption
        )
    with cluster, Client(cluster) as client:
        yield client


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """SIGINT ignored meanwhile, so that processes started meanwhile ignore it for good.

    A Ctrl-C in the terminal goes to the whole process group: without this, each worker
    process would print its own traceback (starting up, it is still importing); this
    process alone handles it. A Ctrl-C while the workers start (seconds) is lost.
    """
    if threading.current_thread() is not threading.main_thread():
        yield  # only the main thread may change signal handlers
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.SIG_DFL if previous is None else previous)
