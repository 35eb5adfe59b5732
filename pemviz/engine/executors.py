"""Executors: where a stage's rollouts are simulated: worker processes on this machine (``local``, the default:
:mod:`pemviz.engine.pool`), this process (``serial``) or Ray tasks (``ray``).

All give the same rollouts, bit for bit, for the same seed, whatever the number of workers or tasks. ``local`` and
``ray`` cut the N rollouts into the fixed blocks of :data:`pemviz.core.rng.RQMC_BLOCK` rollouts; since every
simulator draws one ``rng.random(n K)`` per step (:func:`pemviz.core.rollouts.draws_per_rollout`), a block gets a
stand-in for ``rng`` (:class:`ChunkUniforms`) that jumps a copy of the PCG64 stream to its slice, and ``rng`` ends
where the serial run leaves it.

Requirements for ``ray``: Ray installed (``pip install ray``), pemviz importable on every worker, the problem
picklable by cloudpickle, a PCG64 / PCG64DXSM generator (any other runs serially, with the same result), and a
``problem.simulate`` that draws one ``rng.random(n)`` per step (else a RuntimeError naming the problem).
:func:`chunk_uniforms` gives a block's u's to run blocks on any other infrastructure."""

from __future__ import annotations

import collections
import contextlib
import signal
import socket
import threading
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import numpy as np

from pemviz.core.detectors import Detector
from pemviz.core.rng import JUMPABLE, RQMC_BLOCK, advance, bit_generator_at, block_bounds
from pemviz.core.rollouts import RolloutBatch
from pemviz.settings import EXECUTORS


def stream_size(chunk_size: int | None, keep_rows: bool | None) -> dict[str, Any]:
    """The keyword arguments of ``problem.stream`` for ``chunk_size`` and ``keep_rows``, those that are not None."""
    size: dict[str, Any] = {} if chunk_size is None else {"chunk_size": chunk_size}
    if keep_rows is not None:
        size["keep_rows"] = keep_rows
    return size


Block = tuple[RolloutBatch, int, int]
"""A block's result: its rollouts [stop - start, T], the draws made (T) and the uniforms per rollout (K)."""


class Executor:
    """Simulates a stage's rollouts: ``simulate(problem, n, sampler, target, rng) -> RolloutBatch``, and
    ``stream(problem, n, sampler, target, rng, chunk_size=None, keep_rows=None)``: the chunks of
    ``problem.stream``, in order. A batch it cannot split (:meth:`eligible`) is the problem's own ``simulate`` /
    ``stream`` in this process; the others are cut into blocks, the results of a subclass's :meth:`_simulated` and
    :meth:`_streamed` (module docstring)."""

    name = "serial"
    _simulated: Callable[[Any, int, Detector, Detector, Mapping[str, Any]], list[Block]]
    """A subclass's results of the blocks of ``(problem, n, sampler, target, rng state)``, in rollout order."""
    _streamed: Callable[[Any, int, Detector, Detector, Mapping[str, Any], bool | None], Iterator[Block]]
    """A subclass's results of the streamed blocks of ``(..., keep_rows)`` in order; closing it cancels those not
    taken."""

    def eligible(self, n: int, rng: np.random.Generator, problem: Any = None) -> bool:
        """Whether a batch of ``n`` rollouts of ``problem`` drawn from ``rng`` is simulated block by block
        (:func:`splittable`)."""
        return splittable(n, rng, problem)

    def simulate(
        self, problem: Any, n: int, sampler: Detector, target: Detector, rng: np.random.Generator
    ) -> RolloutBatch:
        """The rollouts of ``problem.simulate(n, sampler, target, rng)`` [N, T], bit for bit, ``rng`` left where that
        leaves it."""
        if not self.eligible(n, rng, problem):
            return problem.simulate(n, sampler, target, rng)
        return gather_chunks(problem, n, rng, self._simulated(problem, n, sampler, target, rng.bit_generator.state))

    def stream(
        self,
        problem: Any,
        n: int,
        sampler: Detector,
        target: Detector,
        rng: np.random.Generator,
        chunk_size: int | None = None,
        keep_rows: bool | None = None,
    ) -> Iterator[RolloutBatch]:
        """The chunks of ``problem.stream(n, sampler, target, rng, ...)`` in order, each at most ``chunk_size`` rollouts
        (None: one block): the same rollouts, bit for bit; ``rng`` is left where the serial stream leaves it once the
        last chunk is handed out."""
        if not self.eligible(n, rng, problem):
            return problem.stream(n, sampler, target, rng, **stream_size(chunk_size, keep_rows))
        blocks = self._streamed(problem, n, sampler, target, rng.bit_generator.state, keep_rows)
        return stream_chunks(problem, n, rng, blocks, chunk_size)

    def close(self) -> None:
        """Free what the executor holds (idempotent)."""


class SerialExecutor(Executor):
    """Runs ``problem.simulate`` / ``problem.stream`` in this process (``--workers 1``)."""

    workers = 1

    def eligible(self, n: int, rng: np.random.Generator, problem: Any = None) -> bool:
        """Never: every batch is simulated in this process."""
        return False


class ChunkUniforms:
    """Stands in for the run's ``np.random.Generator`` inside one chunk of rollouts ``start..stop-1``: its k-th call
    ``random((stop - start) K)`` returns that chunk's slice of the k-th ``rng.random(n K)`` the serial run draws
    from ``state`` (a PCG64 / PCG64DXSM state dict). ``calls`` counts the draws.

    Raises (from :meth:`random`):
        RuntimeError: a draw of another size or kind (the simulator does not draw one ``random(n K)`` per step)."""

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
    """The u's of rollouts ``start..stop-1`` of an n-rollout serial run, float64 [T, stop - start]:
    ``np.random.Generator(bg).random((T, n))[:, start:stop]`` for the bit generator in ``rng_state``, without
    drawing the other columns.

    Raises:
        ValueError: a bit generator that cannot jump, or ``0 <= start < stop <= n`` violated."""
    if rng_state.get("bit_generator") not in ("PCG64", "PCG64DXSM"):
        raise ValueError(f"chunk_uniforms: needs a PCG64 or PCG64DXSM state, got {rng_state.get('bit_generator')}")
    if not 0 <= start < stop <= n:
        raise ValueError(f"chunk_uniforms: need 0 <= start < stop <= n, got start={start}, stop={stop}, n={n}")
    stream = ChunkUniforms(rng_state, n, start, stop)
    return np.stack([stream.random(stop - start) for _ in range(n_steps)]) if n_steps else np.empty((0, stop - start))


def simulate_chunk(
    problem: Any, n: int, start: int, stop: int, sampler: Detector, target: Detector, rng_state: Mapping[str, Any]
) -> Block:
    """Rollouts ``start..stop-1`` of the serial run ``problem.simulate(n, sampler, target, rng)`` from
    ``rng_state``: the batch [stop - start, T], its per-step draws (T) and uniforms per rollout; the serial run's
    when the range is one block (:func:`pemviz.core.rng.block_bounds`), or any range without Array-RQMC and with
    batch-size-independent detectors."""
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
    stream: bool = False,
    keep_rows: bool | None = None,
) -> list[Block]:
    """:func:`stream_block` (``stream``) or :func:`simulate_chunk` of each block ``(start, stop)`` in turn (one task's
    work)."""
    if stream:
        return [stream_block(problem, n, a, b, sampler, target, rng_state, keep_rows) for a, b in blocks]
    return [simulate_chunk(problem, n, a, b, sampler, target, rng_state) for a, b in blocks]


def stream_block(
    problem: Any,
    n: int,
    start: int,
    stop: int,
    sampler: Detector,
    target: Detector,
    rng_state: Mapping[str, Any],
    keep_rows: bool | None = None,
) -> Block:
    """Rollouts ``start..stop-1`` (one block) of the serial ``problem.stream(n, sampler, target, rng, ...)`` from
    ``rng_state``, streamed as one chunk (its object rows elided when ``keep_rows`` is False): the batch
    [stop - start, T], the draws made and the uniforms per rollout (as :func:`simulate_chunk`)."""
    uniforms = ChunkUniforms(rng_state, n, start, stop)
    batches = list(problem.stream(stop - start, sampler, target, uniforms, **stream_size(stop - start, keep_rows)))
    batch = batches[0] if len(batches) == 1 else RolloutBatch.concatenate(batches)
    return batch, uniforms.calls, uniforms.per_rollout


def splittable(n: int, rng: np.random.Generator, problem: Any = None) -> bool:
    """Whether a batch of ``n`` rollouts of ``problem`` drawn from ``rng`` can be simulated block by block elsewhere:
    two blocks or more, a generator that can jump, and a problem whose rollouts draw only their steps' uniforms (not
    one over an operating design domain, which draws every rollout's parameters first); else it is simulated in this
    process, as ``problem.simulate`` (``problem.stream``)."""
    return n > RQMC_BLOCK and isinstance(rng.bit_generator, JUMPABLE) and getattr(problem, "odd", None) is None


def stream_chunks(
    problem: Any,
    n: int,
    rng: np.random.Generator,
    blocks: Iterator[Block],
    chunk_size: int | None = None,
) -> Iterator[RolloutBatch]:
    """The chunks of a streamed batch of ``n`` rollouts from its blocks' results in rollout order, each block cut into
    chunks of at most ``chunk_size`` (None: the block), checked (:func:`check_draws`) and dropped once handed out;
    ``rng`` is advanced to where the serial stream leaves it.

    Raises:
        RuntimeError: a block drew another number of times than its rollouts have steps."""
    drawn = (0, 0)
    try:
        for result in blocks:
            drawn = check_draws(problem, [result])
            batch = result[0]
            del result
            step = chunk_size or batch.n
            for a in range(0, batch.n, step):
                yield batch if batch.n <= step else batch.select(slice(a, a + step))
            del batch
    finally:
        close = getattr(blocks, "close", None)
        if close is not None:
            close()
    advance(rng, n * drawn[0] * drawn[1])


def check_draws(problem: Any, results: list[Block]) -> tuple[int, int]:
    """Check that every chunk result ``(batch, draws, uniforms per rollout)`` drew once per step; returns (T, K).

    Raises:
        RuntimeError: a chunk drew another number of times than its rollouts have steps."""
    n_steps, per_rollout = results[0][0].n_steps, results[0][2]
    for batch, calls, _ in results:
        if calls != n_steps or batch.n_steps != n_steps:
            raise RuntimeError(
                f"executor: problem {getattr(problem, 'name', problem)!r} drew rng.random {calls} times for "
                f"{batch.n_steps} steps; an executor needs exactly one rng.random(n K) per step"
            )
    return n_steps, per_rollout


def gather_chunks(problem: Any, n: int, rng: np.random.Generator, results: list[Block]) -> RolloutBatch:
    """Concatenate chunk results in rollout order, check each drew T times (:func:`check_draws`), and advance ``rng``
    by n K T.

    Raises:
        RuntimeError: a chunk drew another number of times than its rollouts have steps."""
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
        ValueError: a malformed address, or nothing answers at it (the message names it and the timeout)."""
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


_RAY_SHARED: collections.OrderedDict[str, Any] = collections.OrderedDict()
"""In a Ray worker: the (problem, sampler, target) of the last batches, by their object's id (fetched once each)."""


def ray_block(
    shared: list[Any], n: int, start: int, stop: int, rng_state: Mapping[str, Any], stream: bool, keep_rows: Any
) -> Block:
    """One Ray task: block ``start..stop-1`` of the batch whose (problem, sampler, target) is the object
    ``shared[0]`` (an ``ObjectRef`` in a list, so that Ray does not fetch it for every task: a worker fetches and
    unpickles it once, :data:`_RAY_SHARED`): :func:`simulate_blocks` of that block."""
    import ray

    key = shared[0].hex()
    parts = _RAY_SHARED.get(key)
    if parts is None:
        parts = _RAY_SHARED[key] = ray.get(shared[0])
        while len(_RAY_SHARED) > 2:
            _RAY_SHARED.popitem(last=False)
    problem, sampler, target = parts
    return simulate_blocks(problem, n, [(start, stop)], sampler, target, rng_state, stream, keep_rows)[0]


@contextlib.contextmanager
def kept_signal_handlers(signals: tuple[int, ...] = (signal.SIGTERM, signal.SIGINT)) -> Iterator[None]:
    """Put back the Python handlers of ``signals`` that the block replaced (``ray.init`` installs its own for SIGTERM,
    and its C++ core a failure handler that prints a stack dump and kills the process), so that the run's own
    handling holds: SIGTERM like Ctrl-C, what was finished kept. Outside the main thread nothing is changed."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = {sig: signal.getsignal(sig) for sig in signals}
    try:
        yield
    finally:
        for sig, handler in before.items():
            if handler is not None:
                signal.signal(sig, handler)


class RayExecutor(Executor):
    """Simulates each batch as Ray tasks, one per block of rollouts, a bounded number in flight (module docstring).

    Args:
        address: Ray cluster address (``ray.init(address=...)``); None starts a local cluster (an initialised one is
            used as it is).
        in_flight: the most tasks submitted and not yet taken back (default: twice the cluster's CPUs).
        init_kwargs: more keyword arguments for ``ray.init``.
    Raises:
        ImportError: Ray is not installed (the message says how to install it).
        ValueError: ``address`` does not answer (:func:`probe_ray_address`), or ``in_flight`` below 1."""

    name = "ray"

    def __init__(self, address: str | None = None, *, in_flight: int | None = None, **init_kwargs: Any) -> None:
        try:
            import ray
        except ImportError:
            raise ImportError("--executor ray needs Ray: pip install ray (or pip install 'pemviz[test]')") from None
        if in_flight is not None and in_flight < 1:
            raise ValueError(f"in_flight must be >= 1, got {in_flight}")
        self._ray = ray
        self._started = False
        if not ray.is_initialized():
            probe_ray_address(address)
            with kept_signal_handlers():  # Ray's driver would take SIGTERM and SIGINT from the run (a C stack dump)
                ray.init(address=address, include_dashboard=False, **init_kwargs)
            self._started = True
        self.cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
        """The cluster's CPUs when this executor was made."""
        self.in_flight = int(in_flight) if in_flight else 2 * self.cpus
        self._task = ray.remote(ray_block)

    def _streamed(
        self,
        problem: Any,
        n: int,
        sampler: Detector,
        target: Detector,
        state: Mapping[str, Any],
        keep_rows: bool | None,
        stream: bool = True,
    ) -> Iterator[Block]:
        """The results ``(batch, draws, uniforms per rollout)`` of the blocks of ``n`` rollouts in order, each a Ray
        task (:func:`ray_block`), at most :attr:`in_flight` not yet taken; a result is freed in the object store
        once dropped, and closing this cancels the tasks not taken."""
        ray = self._ray
        shared = [ray.put((problem, sampler, target))]
        todo = collections.deque(block_bounds(n))
        pending: collections.deque[Any] = collections.deque()
        try:
            while todo or pending:
                while todo and len(pending) < self.in_flight:
                    start, stop = todo.popleft()
                    pending.append(self._task.remote(shared, n, start, stop, state, stream, keep_rows))
                result = ray.get(pending.popleft())
                yield result
                del result
        finally:
            for ref in pending:
                with contextlib.suppress(Exception):
                    ray.cancel(ref)

    def _simulated(
        self, problem: Any, n: int, sampler: Detector, target: Detector, state: Mapping[str, Any]
    ) -> list[Block]:
        """The blocks' results, a Ray task a block (:meth:`_streamed` of :func:`simulate_chunk`)."""
        return list(self._streamed(problem, n, sampler, target, state, None, stream=False))

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
        ImportError: ``ray`` without Ray installed."""
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
