"""Resource guards: memory a run will need, estimated from N, K, T before anything is allocated, the CPUs worker pools
may use, and the threads a run's torch and BLAS take (:func:`torch_threads`). A run that cannot fit is refused with
the number instead of failing hours in."""

from __future__ import annotations

import contextlib
import math
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

from pemviz.config import ExperimentConfig

if TYPE_CHECKING:
    from pemviz.core.plan import RunPlan

ONE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
"""The environment that gives a process started with it one OpenMP and one BLAS thread (OpenBLAS, MKL): for processes
that run beside another busy one on few cores, where idle BLAS threads spin against it."""
BYTES_PER_ROLLOUT_STEP = 100
"""Peak bytes per (rollout, step) of a batch: observations [N, T, 3], detected, log p, log q, robustness under
three metrics and the masks (measured: 79 B from the peak RSS of ``mc`` runs of N = 2,000 and 8,000, T = 100)."""
BYTES_PER_STREAMED_ROLLOUT = 70
"""Bytes kept per rollout of a stage streamed in chunks (failure flag, log-weight, log p total, robustness)."""
BASE_BYTES = 400 * 2**20
"""The process before any batch: Python, numpy, rerun, the PEM, torch where a fit needs it (measured ~100 MB resident
without torch, ~250 MB with it; with margin)."""


def available_memory() -> int | None:
    """Bytes the system can still give (``MemAvailable`` of /proc/meminfo, else free physical pages); None if
    unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):
        return None


def run_memory(
    plan: RunPlan, n_steps: int, quantile_level: float = 0.0, *, stream_above: int | None = None, chunk: int = 8192
) -> int:
    """Peak bytes a run of ``plan`` (:class:`~pemviz.core.plan.RunPlan`) needs for batches of ``n_steps`` steps.

    The largest stage held at once, each [N, T] whole or, above ``stream_above`` rollouts, one chunk plus
    :data:`BYTES_PER_STREAMED_ROLLOUT` a rollout and, for a CE stage, its elites ((1 - sigma) N rollouts,
    ``quantile_level`` = sigma).
    """
    cell = BYTES_PER_ROLLOUT_STEP * n_steps
    peaks = [0]
    for stage in plan.stages:
        n = stage.n_rollouts
        if stream_above is not None and n > stream_above:
            elites = (1.0 - quantile_level) * n if stage.kind == "ce" else 0.0
            peaks.append(int((min(n, chunk) + elites) * cell + n * BYTES_PER_STREAMED_ROLLOUT))
        else:
            peaks.append(n * cell)
    return BASE_BYTES + max(peaks)


def format_bytes(n: float) -> str:
    """``1.2 GB``-style text (powers of 1024: KiB .. EiB)."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if n < 1024 or unit == "PiB":
            return f"{n:.3g} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.3g} EiB"


def check_run_memory(cfg: ExperimentConfig, n_steps: int, *, stream_above: int | None = None) -> int:
    """Refuse a run whose batches cannot fit in the memory available now.

    Returns:
        the estimate in bytes (:func:`run_memory`).
    Raises:
        ValueError: the estimate exceeds the available memory; the message gives both numbers and the knobs.
    """
    from pemviz.estimators import run_plan  # imports torch: only when a run is checked

    need = run_memory(run_plan(cfg), n_steps, cfg.adaptive.quantile_level, stream_above=stream_above)
    have = available_memory()
    if have is not None and need > have:
        raise ValueError(
            f"this run needs about {format_bytes(need)} of memory (N = {cfg.n_per_stage}, "
            f"N_e = {cfg.adaptive.n_final}, T = {n_steps} steps, {BYTES_PER_ROLLOUT_STEP} B per rollout step) but "
            f"{format_bytes(have)} is available: lower --n / --n-final"
        )
    return need


def usable_cpus(cpu_max: Path = Path("/sys/fs/cgroup/cpu.max")) -> int:
    """CPUs this process may use: those of its affinity mask (``os.sched_getaffinity``, else ``os.cpu_count()``), at
    most the cgroup v2 CPU quota ``ceil(quota / period)`` that ``cpu_max`` sets, if any; at least 1."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count() or 1
    try:
        quota, period = cpu_max.read_text().split()[:2]
        if quota != "max" and int(period) > 0:
            cpus = min(cpus, math.ceil(int(quota) / int(period)))
    except (OSError, ValueError):
        pass
    return max(1, cpus)


POOL_BLOCK = 8192
"""The rollouts of a block the local executor hands a worker: :data:`pemviz.core.rng.RQMC_BLOCK` (a test keeps the two
equal; this module imports no numpy)."""
POOL_PAYS_S = 20.0
"""CPU seconds of simulation left in a batch from which the local executor starts its pool: the pool costs CPU, a
worker's start (about 1.5 s) and each block's own stream and transfer (measured on 2 cores: 100,000 crossing rollouts
took 16.1 s of CPU in one process and 24.0 s with 2 workers started for them). Once started, the pool takes every
batch of two blocks or more."""


def pool_workers(config: ExperimentConfig, n: int, seconds: float) -> int:
    """The processes that simulate a batch of ``n`` rollouts of a run of ``config`` that takes ``seconds`` in one
    process: its ``workers`` (None: every :func:`usable_cpus`) with executor ``local``, at least two blocks of
    :data:`POOL_BLOCK` and at least :data:`POOL_PAYS_S` seconds, else 1 (this process; a Ray cluster's size is not
    known before it starts)."""
    run = config.execution
    if run.executor != "local" or n <= POOL_BLOCK or seconds < POOL_PAYS_S:
        return 1
    return run.workers if run.workers is not None else usable_cpus()


LOAD_SAMPLES = 5
"""How many times :func:`runnable_now` reads the runnable tasks (:func:`competing_now`, :data:`LOAD_GAP_S` apart)."""
LOAD_GAP_S = 0.005
"""Seconds between two of those readings."""


NICE_WEIGHT = 1.25
"""How many times the CPU share of a task grows per step of niceness below another's: the Linux scheduler weighs nice
n as 1024 / 1.25^n (``sched_prio_to_weight``, kernel/sched/core.c)."""


def _autogroup(pid: str) -> tuple[str, int] | None:
    """The autogroup of process ``pid`` (``self``: this one) and its nice value, from ``/proc/<pid>/autogroup``
    (``/autogroup-408 nice 0``); None where it cannot be read (autogroups off, not Linux, the process gone)."""
    try:
        with open(f"/proc/{pid}/autogroup", encoding="ascii") as f:
            name, _, nice = f.read().split()[:3]
        return name, int(nice)
    except (OSError, ValueError):
        return None


def competing_now() -> float | None:
    """What the other tasks running or waiting for a CPU now claim of the CPUs, in this task's shares: one reading of
    ``/proc/<pid>/stat`` (state R, field 19 the nice value) of every other process. With Linux's autogroups (each
    session one group, ``/proc/sys/kernel/sched_autogroup_enabled``) the scheduler shares the CPUs alike among the
    groups with a runnable task, each weighed by its group's nice, and within a group among its tasks by their nice:
    another group counts :data:`NICE_WEIGHT` ^ (this group's nice - its), however many tasks it runs; a task of this
    group :data:`NICE_WEIGHT` ^ (this task's nice - its). Without autogroups every task counts as in this group.
    None where ``/proc`` cannot be read."""
    own, me, mine = os.getpriority(os.PRIO_PROCESS, 0), os.getpid(), _autogroup("self")
    try:
        names = os.listdir("/proc")
    except OSError:
        return None
    groups: dict[str, float] = {}
    inside = 0.0
    for name in names:
        if not name.isdigit() or int(name) == me:
            continue
        try:
            with open(f"/proc/{name}/stat", encoding="ascii", errors="replace") as f:
                fields = f.read().rsplit(")", 1)[1].split()  # from field 3 (the state) on: the name may hold spaces
            if fields[0] != "R":
                continue
            nice = int(fields[16])
        except (OSError, IndexError, ValueError):
            continue
        group = _autogroup(name) if mine is not None else None
        if group is None or mine is None or group[0] == mine[0]:
            inside += NICE_WEIGHT ** (own - nice)
        else:
            groups[group[0]] = NICE_WEIGHT ** (mine[1] - group[1])
    return sum(groups.values()) + inside


def runnable_now(samples: int = LOAD_SAMPLES, gap_s: float = LOAD_GAP_S) -> float | None:
    """The other tasks' claim on the CPUs now, in this task's shares (:func:`competing_now`): the mean of ``samples``
    readings ``gap_s`` apart; None where they cannot be read (not Linux). Unlike the load averages it does not lag: a
    machine busy a minute ago and idle now reads 0. On 2 cores shared by a few sessions (load average 9-12) it gave the
    share of a CPU a run under ``nice -n 5`` then had (its wall over its CPU seconds, mostly 2.4-2.9) within 20 % in 25
    of 29 readings, where counting every runnable task by its nice said 2.4-19 (2026-11-29)."""
    readings = []
    for i in range(samples):
        now = competing_now()
        if now is None:
            return None
        readings.append(now)
        if i + 1 < samples:
            time.sleep(gap_s)
    return sum(readings) / len(readings)


PROBE_PIECES = 400
"""Pieces of arithmetic :func:`cpu_speed` times (each a few array operations on 1,000 x 100 floats in place, as a
simulation step of a batch does)."""
PROBE_REFERENCE_CPU_S = 0.0236
"""The CPU seconds of :data:`PROBE_PIECES` pieces at the speed the cost model's constants hold
(:data:`pemviz.engine.cost.COST`): 200 pieces' CPU seconds beside default braking and plain cut-in runs, divided by
those runs' CPU seconds over the model's (32-48 ms at 3.0-3.9 times the model's on 2 loaded cores, 2026-11-29:
10.4-13.5 ms, the median 11.8 ms per 200)."""


def cpu_speed(pieces: int = PROBE_PIECES) -> float:
    """How many times the CPU seconds the cost model gives a run's arithmetic takes now: the CPU seconds of ``pieces``
    pieces of array arithmetic over :data:`PROBE_REFERENCE_CPU_S` (per :data:`PROBE_PIECES`). A CPU second does less
    where many tasks share a CPU (each time slice starts with caches others filled): on 2 cores with 9-11 runnable
    tasks a run's CPU seconds were 3.0-3.9 times the model's, with 5 of them 1.5-2.6 times; no count of tasks says by
    how much, so it is measured. About 25 ms of CPU on an idle machine."""
    import numpy as np

    a = np.random.default_rng(0).random((1000, 100))
    buf, row = np.empty_like(a), np.empty(1000)
    start = time.process_time()
    for _ in range(max(1, int(pieces))):
        np.multiply(a, 1.0001, out=buf)
        np.add(buf, 0.5, out=buf)
        np.minimum(buf, 0.9, out=buf)
        np.log1p(buf.sum(axis=1, out=row), out=row)
    return (time.process_time() - start) / (PROBE_REFERENCE_CPU_S * max(1, int(pieces)) / PROBE_PIECES)


def load_slowdown(threads: int = 1) -> float:
    """How many times longer than the cost model says a run of ``threads`` busy threads will take now, from the
    machine's load: ``max(1, (L + threads) / C x S)``, L the other tasks' claim on the CPUs now
    (:func:`runnable_now`; the 1-minute load average where that cannot be read), shared by the scheduler among the C
    usable CPUs (:func:`usable_cpus`), and S the CPU seconds its arithmetic takes now over the model's
    (:func:`cpu_speed`). On an idle machine 1; with two other sessions busy on two CPUs a one-thread run gets two
    thirds of a CPU, 1.5 (times S). 1 where neither L nor the load average can be read."""
    load = runnable_now()
    if load is None:
        try:
            load = os.getloadavg()[0]
        except (AttributeError, OSError):
            return 1.0
    return max(1.0, (float(load) + threads) / usable_cpus() * cpu_speed())


def cap_jobs(jobs: int, say=None) -> int:
    """``jobs`` worker processes, at most :func:`usable_cpus`; ``say(message)`` is told when capped."""
    cpus = usable_cpus()
    if jobs > cpus:
        if say is not None:
            say(f"--jobs {jobs}: this machine gives {cpus} CPU{'s' * (cpus != 1)}; using {cpus} worker processes")
        return cpus
    return jobs


@contextlib.contextmanager
def torch_threads(n: int = 1, blas: int | None = None) -> Iterator[None]:
    """Run the block with torch on ``n`` threads, and with ``blas`` given the BLAS libraries too (numpy's OpenBLAS,
    MKL, OpenMP: ``threadpoolctl``), then restore the process's settings (process-wide: for the command layer, around
    a whole run). The proposal is tiny, and on 2 cores a second torch thread only adds synchronisation (measured
    7.7 ms vs 74 ms per Adam epoch under load). The exact fits' products (:func:`pemviz.core.exact_fit.fit_exact`)
    run in numpy's BLAS, whose idle threads spin: ``blas=1`` where runs go side by side (``pemviz validate --jobs 2``:
    10-25 s a run otherwise) and for ``pemviz run``, whose recording process needs the second core (a default run
    without a recording: 2.0 s wall and 1.9 s of CPU on one BLAS thread, 2.15 s wall and 3.7 s of CPU on two, on 2
    cores). The thread count changes no number: a seed gives the same run either way. torch is
    not imported for this: a run that never needs it never imports it (:mod:`pemviz.core.torch_use`)."""
    from threadpoolctl import threadpool_limits

    from pemviz.core import torch_use

    if torch_use.imported():
        torch = torch_use.torch_module()
        before: int | None = torch.get_num_threads()
        torch.set_num_threads(n)
    else:  # torch is imported only if a fit needs it (pemviz.core.torch_use): n is applied then
        before = None
        torch_use.want_threads(n)
    try:
        if blas is None:
            yield
        else:
            with threadpool_limits(blas):
                yield
    finally:
        if before is None:
            before = torch_use.settle()
        if before is not None:
            torch_use.torch_module().set_num_threads(before)
