"""Executors: where a stage's rollouts are simulated: worker processes on this machine (``local``, the default:
:mod:`pemviz.engine.pool`), this process (``serial``) or Ray tasks (``ray``).

The engine asks its executor for every batch (``executor.simulate(problem, n, sampler, target, rng)``) and, for a
stage streamed in chunks, the ``local`` and ``serial`` ones for its chunks (``executor.stream(...)``). All give the
same rollouts, bit for bit, for the same seed, whatever the number of workers or tasks:

- ``serial`` calls ``problem.simulate(n, sampler, target, rng)`` (``problem.stream`` for chunks); so does ``local``
  with one worker, or for a batch too small to pay for its pool.
- ``local`` simulates the blocks (below) of a large batch, or of a streamed stage, in a pool of worker processes.
- ``ray`` cuts the N rollouts into the fixed blocks of :data:`pemviz.core.rng.RQMC_BLOCK` rollouts
  (:func:`pemviz.core.rng.block_bounds`), which every simulator also works by: an Array-RQMC sampler couples the
  rollouts of a block, and detectors are asked about one block at a time. Each Ray task simulates a run of whole blocks
  (:func:`task_blocks`: as many tasks as the cluster has CPUs by default), one block after another. Every pemviz
  simulator draws one ``rng.random(n K)`` per step, K uniforms per rollout
  (:func:`pemviz.core.rollouts.draws_per_rollout`: 1 for a single-object scenario; u for rollout i at step t is then
  the ``(t * n + i)``-th uniform of the stream),
  so the block ``a..b-1`` gets a stand-in for ``rng`` (:class:`ChunkUniforms`) whose k-th ``random((b - a) K)``
  returns slice ``[a, b)`` of the serial run's k-th draw, found by jumping a copy of the PCG64 stream
  (``bit_generator.advance``). Nothing but the generator's state (a few integers) travels with the task, and
  ``rng`` ends where the serial run leaves it. A batch of one block (at most 8,192 rollouts, e.g. every batch of the
  default sampler) is simulated in the driver: there is nothing to split without changing the rollouts.

Requirements for ``ray``: Ray installed (``pip install ray``; pemviz's ``test`` extra installs it),
pemviz importable on every worker, the problem picklable by cloudpickle (pemviz's problems are),
a PCG64 / PCG64DXSM generator (``np.random.default_rng`` gives one; any other runs serially, with the
same result), and a ``problem.simulate`` that draws one ``rng.random(n)`` per step (pemviz's simulators
and :func:`pemviz.core.lockstep.simulate` do; anything else raises a RuntimeError naming the problem).

:func:`chunk_uniforms` gives the u's of rollouts ``a..b-1`` as a [T, b - a] array for
:func:`pemviz.core.lockstep.simulate` (``uniforms=``), to run blocks on any other infrastructure.
"""

from __future__ import annotations

import socket
from collections.abc import Iterator, Mapping
from typing import Any, Protocol

import numpy as np

from pemviz.core.detectors import Detector
from pemviz.core.rng import JUMPABLE, RQMC_BLOCK, advance, bit_generator_at, block_bounds
from pemviz.core.rollouts import RolloutBatch
from pemviz.settings import EXECUTORS


class Executor(Protocol):
    """Simulates a stage's rollouts: ``simulate(problem, n, sampler, target, rng) -> RolloutBatch``."""

    def simulate(
        self, problem: Any, n: int, sampler: Detector, target: Detector, rng: np.random.Generator
    ) -> RolloutBatch: ...

    def close(self) -> None: ...


class SerialExecutor:
    """Runs ``problem.simulate`` in this process (``--workers 1``)."""

    name = "serial"
    workers = 1

    def simulate(
        self, problem: Any, n: int, sampler: Detector, target: Detector, rng: np.random.Generator
    ) -> RolloutBatch:
        """``problem.simulate(n, sampler, target, rng)``: N rollouts [N, T] (see
        :class:`pemviz.core.problems.Problem`)."""
        return problem.simulate(n, sampler, target, rng)

    def stream(
        self, problem: Any, n: int, sampler: Detector, target: Detector, rng: np.random.Generator, **size: Any
    ) -> Iterator[RolloutBatch]:
        """``problem.stream(n, sampler, target, rng, **size)``: its chunks in order."""
        return problem.stream(n, sampler, target, rng, **size)

    def close(self) -> None:
        pass


def task_blocks(n: int, n_tasks: int, block: int = RQMC_BLOCK) -> list[list[tuple[int, int]]]:
    """The fixed blocks of ``n`` rollouts (:func:`pemviz.core.rng.block_bounds`) dealt into at most ``n_tasks`` runs of
    consecutive blocks, in order, their counts differing by at most one.

    Raises:
        ValueError: ``n``, ``n_tasks`` or ``block`` below 1.
    """
    if n < 1 or n_tasks < 1 or block < 1:
        raise ValueError(f"task_blocks: n, n_tasks, block must be >= 1, got {n}, {n_tasks}, {block}")
    blocks = block_bounds(n, block)
    k = min(len(blocks), n_tasks)
    edges = [(i * len(blocks)) // k for i in range(k + 1)]
    return [blocks[a:b] for a, b in zip(edges[:-1], edges[1:], strict=False)]


class ChunkUniforms:
    """Stands in for the run's ``np.random.Generator`` inside one chunk of rollouts ``start..stop-1``.

    Its k-th call ``random((stop - start) K)`` returns the slice of rollouts ``start..stop-1`` of the k-th
    ``rng.random(n K)`` the serial run draws from ``state`` (a PCG64 / PCG64DXSM state dict): K uniforms per rollout
    and step (:func:`pemviz.core.rollouts.draws_per_rollout`; 1 for a single-object scenario), the positions ``k n K +
    start K .. k n K + stop K - 1`` of the stream. ``calls`` counts the draws.

    Raises (from :meth:`random`):
        RuntimeError: a draw of another size or kind (the simulator does not draw one ``random(n K)`` per step).
    """

    bit_generator = None
    """Not a real generator: simulators that inspect it (the batched one) then draw plainly."""

    def __init__(self, state: Mapping[str, Any], n: int, start: int, stop: int) -> None:
        self.state, self.n, self.start, self.stop = state, int(n), int(start), int(stop)
        self.calls, self._position, self.per_rollout = 0, 0, 1

    def random(self, size: Any = None, dtype: Any = np.float64, out: np.ndarray | None = None) -> np.ndarray:
        m = self.stop - self.start
        shape = (size,) if isinstance(size, (int, np.integer)) else tuple(size) if size is not None else None
        if shape is None or len(shape) != 1 or shape[0] < m or shape[0] % m or np.dtype(dtype) != np.float64:
            raise RuntimeError(
                f"ChunkUniforms: the simulator drew random({size!r}, dtype={np.dtype(dtype)}) in a chunk of {m} "
                f"rollouts; an executor needs exactly one rng.random(n K) float64 draw per step"
            )
        k = self.per_rollout = shape[0] // m
        gen = np.random.Generator(bit_generator_at(self.state, self._position + self.start * k))
        self.calls += 1
        self._position += self.n * k
        return gen.random(shape[0], out=out)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        raise AttributeError(
            f"ChunkUniforms has no {name!r}: the simulator used rng.{name}; an executor needs exactly one "
            f"rng.random(n) per step"
        )


def chunk_uniforms(rng_state: Mapping[str, Any], n: int, n_steps: int, start: int, stop: int) -> np.ndarray:
    """The u's of rollouts ``start..stop-1`` of an n-rollout serial run, float64 [T, stop - start].

    Equal to ``np.random.Generator(bg).random((T, n))[:, start:stop]`` for the bit generator ``bg`` in
    ``rng_state`` (``rng.bit_generator.state``, PCG64 or PCG64DXSM), without drawing the other columns;
    pass it to :func:`pemviz.core.lockstep.simulate` as ``uniforms``.

    Raises:
        ValueError: a bit generator that cannot jump, or ``0 <= start < stop <= n`` violated.
    """
    if rng_state.get("bit_generator") not in ("PCG64", "PCG64DXSM"):
        raise ValueError(f"chunk_uniforms: needs a PCG64 or PCG64DXSM state, got {rng_state.get('bit_generator')}")
    if not 0 <= start < stop <= n:
        raise ValueError(f"chunk_uniforms: need 0 <= start < stop <= n, got start={start}, stop={stop}, n={n}")
    stream = ChunkUniforms(rng_state, n, start, stop)
    return np.stack([stream.random(stop - start) for _ in range(n_steps)]) if n_steps else np.empty((0, stop - start))


def simulate_chunk(
    problem: Any, n: int, start: int, stop: int, sampler: Detector, target: Detector, rng_state: Mapping[str, Any]
) -> tuple[RolloutBatch, int, int]:
    """Rollouts ``start..stop-1`` of the serial run ``problem.simulate(n, sampler, target, rng)`` from
    ``rng_state``; returns the batch [stop - start, T], the number of per-step draws it made (T) and the uniforms
    per rollout of each (:func:`pemviz.core.rollouts.draws_per_rollout`). The rollouts
    are the serial run's when ``start..stop-1`` is one block (:func:`pemviz.core.rng.block_bounds`) or, without
    Array-RQMC and with detectors that give the same bits at any batch size, any range."""
    stream = ChunkUniforms(rng_state, n, start, stop)
    batch = problem.simulate(stop - start, sampler, target, stream)
    return batch, stream.calls, stream.per_rollout


def simulate_blocks(
    problem: Any,
    n: int,
    blocks: list[tuple[int, int]],
    sampler: Detector,
    target: Detector,
    rng_state: Mapping[str, Any],
) -> list[tuple[RolloutBatch, int, int]]:
    """:func:`simulate_chunk` of each block ``(start, stop)`` in turn (one Ray task's work)."""
    return [simulate_chunk(problem, n, a, b, sampler, target, rng_state) for a, b in blocks]


def check_draws(problem: Any, results: list[tuple[RolloutBatch, int, int]]) -> tuple[int, int]:
    """Check that every chunk result ``(batch, draws, uniforms per rollout)`` drew once per step; returns (T, K).

    Raises:
        RuntimeError: a chunk drew another number of times than its rollouts have steps.
    """
    n_steps, per_rollout = results[0][0].n_steps, results[0][2]
    for batch, calls, _ in results:
        if calls != n_steps or batch.n_steps != n_steps:
            raise RuntimeError(
                f"executor: problem {getattr(problem, 'name', problem)!r} drew rng.random {calls} times for "
                f"{batch.n_steps} steps; an executor needs exactly one rng.random(n K) per step"
            )
    return n_steps, per_rollout


def gather_chunks(
    problem: Any, n: int, rng: np.random.Generator, results: list[tuple[RolloutBatch, int, int]]
) -> RolloutBatch:
    """Concatenate chunk results in rollout order, check each drew T times (:func:`check_draws`), and advance ``rng``
    by n K T.

    Raises:
        RuntimeError: a chunk drew another number of times than its rollouts have steps.
    """
    n_steps, per_rollout = check_draws(problem, results)
    batches = [b for b, _, _ in results]
    advance(rng, n * per_rollout * n_steps)
    return batches[0] if len(batches) == 1 else RolloutBatch.concatenate(batches)


RAY_PROBE_TIMEOUT_S = 5.0
"""Seconds to wait for a TCP connection to a ``--ray-address`` before giving up (Ray itself retries for minutes)."""


def probe_ray_address(address: str | None, timeout_s: float = RAY_PROBE_TIMEOUT_S) -> None:
    """Check that a Ray cluster address accepts TCP connections, within ``timeout_s`` seconds.

    ``host:port`` (the GCS) and ``ray://host:port`` (Ray client) are probed; None, ``auto`` and ``local`` are
    left to Ray (they name no socket).

    Raises:
        ValueError: a malformed address, or nothing answers at it (the message names it and the timeout).
    """
    if address is None or address in ("auto", "local"):
        return

    hostport = address.removeprefix("ray://")
    host, sep, port = hostport.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--ray-address {address!r}: use HOST:PORT or ray://HOST:PORT (or auto)")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except TimeoutError:
        raise ValueError(f"--ray-address {address}: no answer within {timeout_s:g} s; is the Ray cluster up?") from None
    except OSError as exc:
        raise ValueError(
            f"--ray-address {address}: cannot connect ({exc.strerror or exc}); is the Ray cluster "
            "up (ray start --head)?"
        ) from None


class RayExecutor:
    """Simulates each batch as Ray tasks, one per chunk of rollouts (module docstring).

    Args:
        address: Ray cluster address (``ray.init(address=...)``); None starts a local cluster. If Ray is
            already initialised in this process, that cluster is used and ``address`` is ignored.
        n_chunks: the most tasks per batch, each simulating a run of whole blocks (default: the cluster's CPU
            count). The rollouts do not depend on it.
        init_kwargs: more keyword arguments for ``ray.init``.
    Raises:
        ImportError: Ray is not installed (the message says how to install it).
        ValueError: ``address`` does not answer (:func:`probe_ray_address`).
    """

    name = "ray"

    def __init__(self, address: str | None = None, *, n_chunks: int | None = None, **init_kwargs: Any) -> None:
        try:
            import ray
        except ImportError:
            raise ImportError("--executor ray needs Ray: pip install ray (or pip install 'pemviz[test]')") from None
        self._ray = ray
        self._started = False
        if not ray.is_initialized():
            probe_ray_address(address)
            ray.init(address=address, include_dashboard=False, **init_kwargs)
            self._started = True
        self.n_chunks = int(n_chunks) if n_chunks else max(1, int(ray.cluster_resources().get("CPU", 1)))
        self._task = ray.remote(simulate_blocks)

    def simulate(
        self, problem: Any, n: int, sampler: Detector, target: Detector, rng: np.random.Generator
    ) -> RolloutBatch:
        """The rollouts of ``problem.simulate(n, sampler, target, rng)``, simulated as Ray tasks of whole blocks
        [N, T] (in the driver when N is one block)."""
        tasks = task_blocks(n, self.n_chunks)
        if len(block_bounds(n)) == 1 or not isinstance(rng.bit_generator, JUMPABLE):
            return problem.simulate(n, sampler, target, rng)
        state = rng.bit_generator.state
        ray = self._ray
        problem_ref = ray.put(problem)
        futures = [self._task.remote(problem_ref, n, blocks, sampler, target, state) for blocks in tasks]
        return gather_chunks(problem, n, rng, [r for part in ray.get(futures) for r in part])

    def close(self) -> None:
        """Shut Ray down if this executor started it."""
        if self._started and self._ray.is_initialized():
            self._ray.shutdown()
        self._started = False


_EXECUTORS: dict[tuple[str, str | int | None], Executor] = {}


def get_executor(name: str = "local", address: str | None = None, workers: int | None = None) -> Executor:
    """The executor called ``name`` (:data:`EXECUTORS`), made once per process and (name, address or workers):
    ``local`` with ``workers`` processes (None: :func:`pemviz.engine.resources.usable_cpus`; one: the ``serial``
    executor).

    Raises:
        ValueError: an unknown name, or ``workers`` below 1.
        ImportError: ``ray`` without Ray installed.
    """
    if name not in EXECUTORS:
        raise ValueError(f"unknown executor {name!r}; use one of {', '.join(EXECUTORS)}")
    if name == "local":
        from pemviz.engine.resources import usable_cpus
        from pemviz.plugins import resolve

        # named by text: the pool is built on this module's blocks (pool -> executors, never back at import)
        local_executor = resolve("pemviz.engine.pool:LocalExecutor")

        if workers is not None and workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        workers = usable_cpus() if workers is None else workers
        name = "serial" if workers == 1 else name
    key = (name, address if name == "ray" else workers if name == "local" else None)
    ex = _EXECUTORS.get(key)
    if ex is None or (name == "ray" and not ex._ray.is_initialized()):  # type: ignore[attr-defined]
        if name == "local":
            ex = local_executor(workers)
        else:
            ex = SerialExecutor() if name == "serial" else RayExecutor(address)
        _EXECUTORS[key] = ex
    return ex


def close_executors() -> None:
    """Close every executor :func:`get_executor` made (kills a local pool's workers, shuts down a Ray cluster it
    started)."""
    for ex in _EXECUTORS.values():
        ex.close()
    _EXECUTORS.clear()
