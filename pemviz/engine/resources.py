"""Resource guards: memory a run will need, estimated from N, K, T before anything is allocated, the CPUs worker pools
may use, and the threads a run's torch and BLAS take (:func:`torch_threads`). A run that cannot fit is refused with
the number instead of failing hours in."""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from pemviz.config import Execution, ExperimentConfig

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
    ``quantile_level`` = sigma)."""
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
        ValueError: the estimate exceeds the available memory; the message gives both numbers and the knobs."""
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
worker's start (about 1 s: its imports and the problem's unpickling) and each block's hand-off (about 2 % of its
simulation through shared memory). Once started, the pool takes every batch of two blocks or more."""


def pool_workers(run: Execution, n: int, seconds: float) -> int:
    """The processes that simulate a batch of ``n`` rollouts of a run whose execution settings are ``run`` (a config's
    :attr:`~pemviz.config.ExperimentConfig.execution`) that takes ``seconds`` in one process: its ``workers`` (None:
    every :func:`usable_cpus`) with executor ``local``, at least two blocks of :data:`POOL_BLOCK` and at least
    :data:`POOL_PAYS_S` seconds, else 1 (this process; a Ray cluster's size is not known before it starts)."""
    if run.executor != "local" or n <= POOL_BLOCK or seconds < POOL_PAYS_S:
        return 1
    return run.workers if run.workers is not None else usable_cpus()


LOAD_WINDOW_S = 0.25
"""The shortest window over which :func:`load_slowdown` averages the other tasks' runnable time: where the reading
that opens it (:func:`tasks_now`) is taken earlier (``pemviz run`` takes it before the run's problem is built),
the run waits for no more than what is left of it."""
LOAD_WINDOW_MAX_S = 30.0
"""The longest: a reading older than this is not the load the run starts in, and a new window opens."""


NICE_WEIGHT = 1.25
"""How many times the CPU share of a task grows per step of niceness below another's: the Linux scheduler weighs nice
n as 1024 / 1.25^n (``sched_prio_to_weight``, kernel/sched/core.c)."""


@dataclasses.dataclass(frozen=True)
class TaskTimes:
    """One reading of every other task's time on a CPU or waiting for one (:func:`tasks_now`).

    Attributes:
        at: when it was read (``time.perf_counter`` seconds).
        tasks: thread id -> (its process's autogroup, that group's nice, its process's nice, nanoseconds it has run
            or waited on a run queue since it started: ``/proc/<pid>/task/<tid>/schedstat`` fields 1 + 2); every
            thread but this process's. The group is ``""`` where it cannot be read (a kernel thread: the root group).
        group: this process's autogroup (None without autogroups: then every task counts as in this group).
        group_nice: that group's nice.
        nice: this process's nice."""

    at: float
    tasks: dict[str, tuple[str, int, int, int]]
    group: str | None
    group_nice: int
    nice: int


@dataclasses.dataclass(frozen=True)
class Competition:
    """What the other tasks claimed of the CPUs over a window (:func:`competition`), as Linux's autogroups share them.

    Attributes:
        groups: each other autogroup (session) that had a runnable task: (its weight against this one's,
            :data:`NICE_WEIGHT` ^ (this group's nice - its), its runnable tasks: the mean over the window, >= 0).
        inside: this session's other runnable tasks, each weighed :data:`NICE_WEIGHT` ^ (this task's nice - its).
        inside_tasks: the same tasks, counted (what they can use: one CPU each)."""

    groups: tuple[tuple[float, float], ...] = ()
    inside: float = 0.0
    inside_tasks: float = 0.0


def _autogroup(pid: str) -> tuple[str, int] | None:
    """The autogroup of process ``pid`` (``self``: this one) and its nice value, from ``/proc/<pid>/autogroup``
    (``/autogroup-408 nice 0``); None where it cannot be read (autogroups off, a kernel thread, not Linux, the process
    gone)."""
    try:
        with open(f"/proc/{pid}/autogroup", encoding="ascii") as f:
            name, _, nice = f.read().split()[:3]
        return name, int(nice)
    except (OSError, ValueError):
        return None


def tasks_now() -> TaskTimes | None:
    """Every other thread's nanoseconds on a CPU or waiting for one so far, with its session's autogroup and its
    process's nice (fields 1 and 2 of ``/proc/<pid>/task/<tid>/schedstat``, field 19 of ``/proc/<pid>/stat``): two
    readings give each thread's runnable share of the time between them (:func:`competition`). None where ``/proc``
    or this process's own ``schedstat`` cannot be read (not Linux, a kernel without schedstats). About 5-20 ms of CPU
    for a few hundred threads."""
    me, mine = os.getpid(), _autogroup("self")
    try:
        names = os.listdir("/proc")
        with open(f"/proc/{me}/schedstat", encoding="ascii") as f:
            int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return None
    tasks: dict[str, tuple[str, int, int, int]] = {}
    for pid in names:
        if not pid.isdigit() or int(pid) == me:
            continue
        try:
            with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as f:
                nice = int(f.read().rsplit(")", 1)[1].split()[16])  # from field 3 on: the name may hold spaces
            tids = os.listdir(f"/proc/{pid}/task")
        except (OSError, IndexError, ValueError):
            continue
        group = _autogroup(pid) if mine is not None else None
        name, group_nice = group if group is not None else ("", 0)
        for tid in tids:
            try:
                with open(f"/proc/{pid}/task/{tid}/schedstat", encoding="ascii") as f:
                    ran, waited = f.read().split()[:2]
                tasks[tid] = (name, group_nice, nice, int(ran) + int(waited))
            except (OSError, ValueError):
                continue
    own, own_nice = mine if mine is not None else (None, 0)
    return TaskTimes(time.perf_counter(), tasks, own, own_nice, os.getpriority(os.PRIO_PROCESS, 0))


def competition(before: TaskTimes, after: TaskTimes) -> Competition:
    """The other tasks' claim on the CPUs between two readings (:func:`tasks_now`): each thread's runnable share of the
    time between them (its nanoseconds run or waiting, at most all of them; a thread present in both), summed per
    autogroup; a thread of this process's group by its nice against this process's, another group by its group's nice
    against this one's (Linux's autogroups: the scheduler shares the CPUs among the sessions with a runnable task
    first, each weighed by its group's nice, then among a session's tasks by their nice). The root group (kernel
    threads) is one group. Without autogroups (``after.group`` None) every thread counts as in this group. Unlike the
    load averages it does not lag, and unlike a count of the tasks runnable at one instant it does not depend on the
    instant: a session whose task runs half the time counts half."""
    span_ns = max(1.0, (after.at - before.at) * 1e9)
    groups: dict[str, list[float]] = {}
    inside = inside_tasks = 0.0
    for tid, (name, group_nice, nice, ns) in after.tasks.items():
        then = before.tasks.get(tid)
        if then is None or then[:3] != (name, group_nice, nice):
            continue
        share = min(1.0, max(0.0, (ns - then[3]) / span_ns))
        if share <= 0.0:
            continue
        if after.group is None or name == after.group:
            inside += share * NICE_WEIGHT ** (after.nice - nice)
            inside_tasks += share
        else:
            groups.setdefault(name, [NICE_WEIGHT ** (after.group_nice - group_nice), 0.0])[1] += share
    return Competition(tuple((w, n) for w, n in groups.values()), inside, inside_tasks)


def crowding(c: Competition, cpus: int, threads: int = 1) -> float:
    """How many times its CPU seconds a run of ``threads`` busy threads takes in wall time beside the competition
    ``c`` on ``cpus`` CPUs, as Linux's autogroups share them: the CPUs go to the sessions with a runnable task by their
    weight, none more than its runnable tasks can use (one CPU each; what it cannot use goes to the others), and a
    session's CPUs to its tasks by their nice. With every session able to use its share this is
    (G + 1)(threads + inside) / C (G the other sessions, weighed; inside this session's other tasks): a session's tasks
    split its share, they do not add to the others'. At least 1. On 2 cores beside two other sessions a CPU-bound
    loop's wall over its CPU seconds was 1.45-1.51 alone (this: 1.5), 2.97-3.12 beside one more loop of its session
    (3.0), 4.37-4.49 beside two (4.5), where adding the tasks said 2.0 and 2.5 (the loop of
    ``benchmarks/load_share.py``, 2026-11-29)."""
    weight = [1.0] + [w for w, n in c.groups if n > 0.0]
    need = [threads + c.inside_tasks] + [n for _, n in c.groups if n > 0.0]
    free, active = float(cpus), set(range(len(need)))
    while True:  # water-filling: a group that cannot use its share takes what it can, the rest is shared again
        per = free / sum(weight[i] for i in active)
        full = {i for i in active if need[i] <= weight[i] * per}
        if not full or 0 in full:
            break
        active -= full
        free -= sum(need[i] for i in full)
    got = need[0] if 0 in full else per
    return max(1.0, (threads + c.inside) / max(got, 1e-12))


@dataclasses.dataclass(frozen=True)
class LoadReading:
    """The machine's load, read once (:func:`read_load`): what the other tasks claimed of ``cpus`` CPUs over a window
    (:func:`competition`), or where their times cannot be read the 1-minute load average; neither: an idle machine.

    Attributes:
        cpus: the CPUs the run may use (:func:`usable_cpus`).
        competition: the other tasks' claim (None: not read).
        average: the 1-minute load average, runnable tasks (None: not read; used only without ``competition``)."""

    cpus: int
    competition: Competition | None = Competition()
    average: float | None = None

    def crowding(self, threads: int = 1) -> float:
        """Wall over CPU seconds of a run of ``threads`` busy threads (:func:`crowding`); from the load average
        ``max(1, (L + threads) / C)``."""
        if self.competition is None and self.average is not None:
            return max(1.0, (self.average + threads) / self.cpus)
        return crowding(self.competition or Competition(), self.cpus, threads)

    def pool_speedup(self, workers: int) -> float:
        """How many times as fast ``workers`` busy processes get through the same CPU seconds as one, at this load:
        ``workers x crowding(1) / crowding(workers)`` (the same sharing of the CPUs among the sessions, the run's
        session holding ``workers`` runnable tasks instead of one). Idle on 2 CPUs, 2 workers: 2; 4 workers: 2;
        beside two other busy sessions on 2 CPUs: 1.0 (the run's session gets two thirds of a CPU either way)."""
        return workers * self.crowding(1) / self.crowding(workers)


def read_load(since: TaskTimes | None = None) -> LoadReading:
    """The machine's load now (:class:`LoadReading`): the other tasks' runnable time from ``since``, a
    :func:`tasks_now` reading at most :data:`LOAD_WINDOW_MAX_S` old, else now, over at least :data:`LOAD_WINDOW_S`
    (the rest of the window is slept): a time average, where a count of the tasks runnable at five instants in 20 ms
    priced a tilted multi-car run at 5.2-9.8 times the model's while it took 6.3-7.8 times. The 1-minute load average
    is read only where the tasks' times cannot be: it counts tasks, not the sessions the scheduler shares the CPUs
    among, and lags by a minute."""
    fresh = since is not None and time.perf_counter() - since.at <= LOAD_WINDOW_MAX_S
    opening = since if fresh else tasks_now()
    cpus = usable_cpus()
    if opening is not None:
        time.sleep(max(0.0, LOAD_WINDOW_S - (time.perf_counter() - opening.at)))
        last = tasks_now()
        if last is not None:
            return LoadReading(cpus, competition(opening, last))
    try:
        return LoadReading(cpus, None, float(os.getloadavg()[0]))
    except (AttributeError, OSError):
        return LoadReading(cpus)


def load_slowdown(threads: int = 1, since: TaskTimes | None = None, speed: float = 1.0) -> float:
    """How many times longer than the cost model says a run of ``threads`` busy threads will take now: the crowding
    of :func:`read_load` (from ``since``) times ``speed``, how many times the model's CPU seconds the run's work takes
    now, e.g. a pilot of the scene's own rollouts (:func:`pemviz.engine.cost.pilot_speed`). On an idle machine
    ``speed``; beside two other busy sessions on two CPUs a one-thread run gets two thirds of a CPU, 1.5 times it."""
    return read_load(since).crowding(threads) * speed


def cap_jobs(jobs: int, say: Callable[[str], object] | None = None) -> int:
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
    a whole run). The proposal is tiny, and on 2 cores a second torch thread only adds synchronisation. The exact
    fits' products (:func:`pemviz.core.exact_fit.fit_exact`) run in numpy's BLAS, whose idle threads spin: ``blas=1``
    where runs go side by side (``pemviz validate --jobs 2``) and for ``pemviz run``, whose recording process needs
    the second core. The thread count changes no number: a seed gives the same run either way. torch is not imported
    for this: a run that never needs it never imports it (:mod:`pemviz.core.torch_use`)."""
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
