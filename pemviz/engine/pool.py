"""The ``local`` executor: a batch's rollouts simulated by a pool of worker processes on this machine, the same
rollouts, bit for bit, as one process gives.

A batch is cut into the blocks of :data:`pemviz.core.rng.RQMC_BLOCK` rollouts, each simulated from its slice of the
serial uniform stream (:class:`pemviz.engine.executors.ChunkUniforms`). The first block is simulated here and timed;
the pool starts when the blocks left would take at least :data:`pemviz.engine.resources.POOL_PAYS_S` seconds more,
and then takes every batch of two blocks or more, a streamed stage's at most two per worker ahead, handed back in
order through shared-memory files (:mod:`pemviz.engine.handoff`). The pool is joblib's loky executor (fork + exec:
safe in a parent with threads; broken workers replaced; idle ones exit after :data:`IDLE_S` seconds).

Ctrl-C and SIGTERM reach the run only: the workers ignore SIGINT, and the run's end shuts the pool down
(:func:`pemviz.engine.executors.close_executors`, also at exit)."""

from __future__ import annotations

import atexit
import collections
import hashlib
import signal
import sys
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

from pemviz.core.detectors import Detector
from pemviz.core.rng import block_bounds
from pemviz.engine import handoff, resources
from pemviz.engine.executors import Block, Executor, simulate_blocks, simulate_chunk, splittable, stream_block
from pemviz.engine.resources import ONE_THREAD_ENV, usable_cpus

IDLE_S = 120
"""Seconds an idle worker waits for work before it exits (a new one starts when work comes)."""


_PROBLEMS: collections.OrderedDict[str, Any] = collections.OrderedDict()
"""In a worker: the problems of the last batches, by the digest of their pickle (unpickled once per batch kind)."""


def _problem(digest: str, blob: bytes) -> Any:
    import cloudpickle

    problem = _PROBLEMS.get(digest)
    if problem is None:
        problem = _PROBLEMS[digest] = cloudpickle.loads(blob)
        while len(_PROBLEMS) > 2:
            _PROBLEMS.popitem(last=False)
    return problem


def _task(
    digest: str,
    blob: bytes,
    n: int,
    blocks: list[tuple[int, int]],
    sampler: Detector,
    target: Detector,
    state: Any,
    stream: bool,
    keep_rows: Any,
    folder: str | None,
) -> handoff.Packed:
    """One worker's task: the blocks' rollouts, pickled by cloudpickle (a chunk's row replay is a closure), their
    arrays handed over in a file of ``folder`` (:func:`pemviz.engine.handoff.pack`)."""
    from threadpoolctl import threadpool_limits

    problem = _problem(digest, blob)
    with threadpool_limits(1):
        out = simulate_blocks(problem, n, blocks, sampler, target, state, stream, keep_rows)
    return handoff.pack(out, folder)


def _call(digest: str, blob: bytes, fn: Any, args: tuple[Any, ...]) -> Any:
    """One worker's call ``fn(problem, *args)`` on one BLAS thread (:meth:`LocalExecutor.submit`)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        return fn(_problem(digest, blob), *args)


def _worker_start(path: tuple[str, ...]) -> None:
    """A worker's start: the parent's import path (a scenario or method of one's own imported from a folder the
    parent put on ``sys.path`` is found), and Ctrl-C is the run's to handle (it shuts the pool down)."""
    sys.path[:] = list(path)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


class LocalExecutor(Executor):
    """Simulates the blocks of a large batch on ``workers`` processes where they pay for their start (module
    docstring), the others in this process; the rollouts do not depend on the workers.

    Args:
        workers: worker processes (None: :func:`pemviz.engine.resources.usable_cpus`); 1 never starts a pool (the
            serial executor).
    Raises:
        ValueError: ``workers`` below 1."""

    name = "local"

    def __init__(self, workers: int | None = None) -> None:
        if workers is not None and workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.workers = usable_cpus() if workers is None else int(workers)
        self.started = False
        """Whether a batch was big enough to start the pool."""
        self._pool: Any = None
        self._folder: str | None = None
        """The pool's hand-off folder (:mod:`pemviz.engine.handoff`), made with the pool."""

    def eligible(self, n: int, rng: np.random.Generator, problem: Any = None) -> bool:
        """Whether a batch of ``n`` rollouts of ``problem`` drawn from ``rng`` may go to the pool: more than one worker
        and a batch that can be split into blocks (:func:`pemviz.engine.executors.splittable`); else this process, as
        ``problem.simulate``."""
        return self.workers > 1 and splittable(n, rng, problem)

    def _pays(self, blocks_left: int, block_s: float) -> bool:
        """Whether to hand the blocks left to the pool: it is started, or they take at least
        :data:`pemviz.engine.resources.POOL_PAYS_S` CPU seconds at ``block_s`` a block."""
        return self._pool is not None or blocks_left * block_s >= resources.POOL_PAYS_S

    def _executor(self) -> Any:
        from joblib.externals.loky import get_reusable_executor

        if self._pool is None:
            atexit.register(self.close)
            self._folder = handoff.make_folder()
        self._pool = get_reusable_executor(  # a changed import path starts new workers (loky compares the arguments)
            max_workers=self.workers,
            timeout=IDLE_S,
            initializer=_worker_start,
            initargs=(tuple(sys.path),),
            env=dict(ONE_THREAD_ENV),
        )
        self.started = True
        return self._pool

    @staticmethod
    def _pickled(problem: Any) -> tuple[str, bytes]:
        import cloudpickle

        blob = cloudpickle.dumps(problem)
        return hashlib.blake2b(blob, digest_size=16).hexdigest(), blob

    def submit(self, fn: Any, problem: Any, *args: Any) -> Any:
        """``fn(problem, *args)`` in a worker process, a ``concurrent.futures.Future`` of its result: ``fn`` a
        module-level function, ``problem`` pickled by cloudpickle (unpickled once per worker), ``args`` and the result
        picklable (e.g. whole splitting runs: :mod:`pemviz.estimators.ams`)."""
        digest, blob = self._pickled(problem)
        return self._executor().submit(_call, digest, blob, fn, args)

    def _simulated(self, problem: Any, n: int, sampler: Detector, target: Detector, state: Any) -> list[Block]:
        """The blocks' results in order: the first block here, timed, and the others in the pool where they pay for it
        (:meth:`_pays`)."""
        blocks = block_bounds(n)
        if self._pool is None:
            t0 = time.thread_time()
            first = [simulate_chunk(problem, n, *blocks[0], sampler, target, state)]
            block_s, blocks = time.thread_time() - t0, blocks[1:]
        else:
            first, block_s = [], 0.0
        if not self._pays(len(blocks), block_s):
            rest = [simulate_chunk(problem, n, a, b, sampler, target, state) for a, b in blocks]
            return first + rest
        digest, blob = self._pickled(problem)
        pool = self._executor()
        k = -(-len(blocks) // self.workers)
        tasks = [blocks[i : i + k] for i in range(0, len(blocks), k)]
        args = (sampler, target, state, False, None, self._folder)
        futures = [pool.submit(_task, digest, blob, n, part, *args) for part in tasks]
        try:
            parts = [r for f in futures for r in handoff.unpack(f.result())]
        finally:
            for f in futures:
                f.cancel()
        return first + parts

    def _streamed(
        self, problem: Any, n: int, sampler: Detector, target: Detector, state: Any, keep_rows: bool | None
    ) -> Iterator[Block]:
        """The streamed blocks' results ``(batch, draws, uniforms per rollout)`` in order: the first here, timed; the
        others here too, or in the pool, at most two per worker ahead, where they pay for it (:meth:`_pays`); closing
        this cancels the blocks not handed back."""
        todo = collections.deque(block_bounds(n))
        pending: collections.deque[Any] = collections.deque()
        pool, block_s, digest, blob = None, 0.0, "", b""
        try:
            while todo or pending:
                if pool is None and todo and self._pays(len(todo), block_s):
                    digest, blob = self._pickled(problem)
                    pool = self._executor()
                while pool is not None and todo and len(pending) < 2 * self.workers:
                    block = [todo.popleft()]
                    args = (sampler, target, state, True, keep_rows, self._folder)
                    pending.append(pool.submit(_task, digest, blob, n, block, *args))
                if pending:
                    (result,) = handoff.unpack(pending.popleft().result())
                else:  # in this process, timed: what the blocks left would cost
                    t0 = time.thread_time()
                    result = stream_block(problem, n, *todo.popleft(), sampler, target, state, keep_rows)
                    block_s = time.thread_time() - t0
                yield result
                del result
        finally:
            for f in pending:
                f.cancel()

    def close(self) -> None:
        """Shut the pool down, killing its workers (idempotent)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, kill_workers=True)
            self._pool = None
        handoff.remove_folder(self._folder)  # with the blocks cancelled before they were read
        self._folder = None
