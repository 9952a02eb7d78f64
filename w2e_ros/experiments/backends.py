"""Where independent jobs run: this machine's processes, or a Ray cluster.

``w2e collect`` and ``w2e benchmark`` cut their work into jobs that share nothing (a shard of
observations; one method on one seed) and only need the results back, in any order. A
:class:`Backend` maps a picklable top-level function over such jobs and yields
``(index, result)`` as each finishes, so the caller writes its files and counts progress
the same way whatever runs the jobs:

- :class:`LocalBackend`: in this process (``workers <= 1``) or a pool of spawned processes;
- :class:`RayBackend`: one Ray task per job on a local Ray instance or an existing cluster
  (``address="auto"`` or ``HOST:PORT``); results come back through Ray's object store,
  so worker hosts need the same venv but no shared directory for the outputs.

Both run the same function on the same job, so a job that seeds itself from its own
description gives the same result on either (tested in ``test_ray_backend.py``).
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import os
import signal
import threading
from collections.abc import Callable, Iterator, Sequence
from functools import partial
from typing import Any, TypeVar

from w2e_ros.core.infra.allocator import keep_freed_memory

log = logging.getLogger("w2e.backends")

T = TypeVar("T")
R = TypeVar("R")

BACKENDS = ("local", "ray")


class Backend:
    """Maps a function over independent jobs, yielding results as they finish."""

    name = "backend"

    def map(self, fn: Callable[[T], R], jobs: Sequence[T]) -> Iterator[tuple[int, R]]:
        """``(index into jobs, fn(job))`` in order of completion."""
        raise NotImplementedError

    def put(self, value: Any) -> Any:
        """A handle to a large input shared by many jobs; :func:`resolve` turns it back into
        the value inside a job. Locally the value itself."""
        return value

    @property
    def parallelism(self) -> int:
        """How many jobs run at once (for the log)."""
        return 1

    def close(self) -> None:
        """Release what the backend started (``contextlib.closing`` calls it)."""


def resolve(handle: Any) -> Any:
    """The value behind a :meth:`Backend.put` handle (a Ray object reference or the value)."""
    if type(handle).__name__ == "ObjectRef":
        import ray

        return ray.get(handle)
    return handle


class LocalBackend(Backend):
    """This process for ``workers <= 1``, else ``workers`` spawned processes (one thread
    each: the workers already use every core). SIGTERM unwinds like Ctrl-C so the pool's
    workers are terminated with it instead of being orphaned."""

    name = "local"

    def __init__(self, workers: int = 1) -> None:
        self.workers = workers

    @property
    def parallelism(self) -> int:
        return max(1, self.workers)

    def map(self, fn: Callable[[T], R], jobs: Sequence[T]) -> Iterator[tuple[int, R]]:
        if self.workers <= 1 or len(jobs) <= 1:
            for i, job in enumerate(jobs):
                yield i, fn(job)
            return
        ctx = mp.get_context("spawn")
        with _term_as_interrupt(), ctx.Pool(self.workers, initializer=_worker_init) as pool:
            yield from pool.imap_unordered(partial(_call_indexed, fn), list(enumerate(jobs)))


def _call_indexed(fn: Callable[[Any], Any], item: tuple[int, Any]) -> tuple[int, Any]:
    """``(i, job) -> (i, fn(job))``: results finishing out of order keep their place. A
    top-level function: picklable for the pool, and ``ray.remote`` takes only functions."""
    return item[0], fn(item[1])


class RayBackend(Backend):
    """One Ray task per job (1 CPU each). Joins the cluster at ``address`` (``"auto"``: the
    one started on this host with ``ray start``); without one, starts a private local
    instance on first use and stops it in :meth:`close`. A Ray session already initialised
    by the caller (a test, a notebook) is used as is and left running.

    Ctrl-C or SIGTERM cancels the tasks not yet finished (force: a trial in the simulator
    cannot be interrupted politely); shards already written stay, so a re-run resumes.
    """

    name = "ray"

    def __init__(self, address: str | None = None, num_cpus: int | None = None) -> None:
        self.address, self.num_cpus = address, num_cpus
        self._owned = False

    def _connect(self) -> Any:
        import ray

        if not ray.is_initialized():
            kw: dict[str, Any] = {"include_dashboard": False, "log_to_driver": True}
            if self.address:
                try:
                    ray.init(address=self.address, **kw)
                except ConnectionError as exc:  # a clear message instead of a trace
                    raise ValueError(f"no Ray cluster at --address {self.address} ({exc}); "
                                     "start one with `ray start --head`") from exc
            else:
                ray.init(num_cpus=self.num_cpus, **kw)
            self._owned = True
        return ray

    @property
    def parallelism(self) -> int:
        ray = self._connect()
        return int(ray.cluster_resources().get("CPU", 1))

    def put(self, value: Any) -> Any:
        return self._connect().put(value)

    def close(self) -> None:
        """Leave the Ray session if this backend started it (a local instance stops)."""
        if self._owned:
            import ray

            ray.shutdown()
            self._owned = False

    def map(self, fn: Callable[[T], R], jobs: Sequence[T]) -> Iterator[tuple[int, R]]:
        ray = self._connect()
        # a worker that dies (killed under memory pressure, a crash in native code) is
        # retried twice: jobs are deterministic and return their results to this process
        # (which writes the shards), so a retry gives the same result; an exception raised
        # by the job itself is not retried
        task = ray.remote(num_cpus=1, max_retries=2, retry_exceptions=False)(_call_indexed)
        pending = [task.remote(fn, (i, job)) for i, job in enumerate(jobs)]
        try:
            with _term_as_interrupt():
                while pending:
                    done, pending = ray.wait(pending, num_returns=1)
                    yield ray.get(done[0])
        finally:
            for ref in pending:  # interrupted, or a task failed: nothing left behind
                with contextlib.suppress(Exception):
                    ray.cancel(ref, force=True)


def make_backend(name: str, workers: int = 1, address: str | None = None) -> Backend:
    """The backend a command line asks for (``--backend``, ``--workers``, ``--address``)."""
    if name == "local":
        if address:
            raise ValueError("--address needs --backend ray")
        return LocalBackend(workers)
    if name == "ray":
        try:
            import ray  # noqa: F401
        except ImportError as exc:
            raise ValueError("--backend ray needs the ray package: pip install ray") from exc
        return RayBackend(address)
    raise ValueError(f"unknown backend {name!r}; known: {', '.join(BACKENDS)}")


@contextlib.contextmanager
def _term_as_interrupt() -> Iterator[None]:
    """SIGTERM (``kill``, a supervisor stopping the job) unwinds like Ctrl-C, so the ``with``
    blocks and ``finally`` clauses around the jobs stop the workers instead of leaving them
    orphaned; finished shards stay on disk and a re-run resumes from them."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def _raise(signum: int, frame: object) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    previous = signal.signal(signal.SIGTERM, _raise)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _worker_init() -> None:
    # one thread per worker process: the workers already use every core
    os.environ["OMP_NUM_THREADS"] = "1"
    keep_freed_memory()  # spawned: the parent's allocator setting does not carry over
