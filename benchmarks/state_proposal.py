"""The state-dependent proposal (``--method state``, :mod:`pemviz.estimators.state`) against each scene's default
command and plain Monte Carlo, one row per scene and sampler: the study behind the Validation page's section "A
proposal that reads the tracker's state".

Each run is ``pemviz run SCENE-FLAGS SAMPLER-FLAGS --seed S`` (the command's own parser and engine, no recording;
:func:`benchmarks.scene_neutral.one_run`), against the scene's exact answer or plain Monte Carlo reference. A row
gives the median relative error, the runs within x2, the printed 95 % intervals holding p, the lower bounds holding p,
``reliable`` verdicts outside x2, nan, the verdicts, the answers that are plain Monte Carlo's (the fallback), the mean
cost in rollout-equivalents and plain Monte Carlo's cost for the same median error, ``(0.674 / m)^2 (1 - p) / p``,
and their ratio. For the state method the cost counts, besides the run's simulations, one rollout-equivalent for every
rollout whose state features were replayed for the fits and weights (an upper bound: a replay steps the scene without
the perception), and the row says how many and how many seconds they took.

Samplers: ``default`` (the scene's default command: on the crossing the cross-entropy stages, their retry, then plain
Monte Carlo), ``state`` (``--method state``: the same stages and fallback with the state-dependent proposal, by default
the PEM's logit plus a linear function of the row and its features, the errors drawn from the PEM), ``state-only``
(``--plain-fallback 0``: the proposal's own answer), ``state-only-400`` (the same at N = 400 a stage, the default's
retry's N), and the proposal's variants, each alone: ``network-only`` (``--state-model network``: the paper's
network over the row and its features), ``spline-only`` (``--state-model spline``: the PEM's logit plus an additive
function of the row and its features, hats at their quantiles), ``fit-errors-only`` (``--state-fit-errors``: the
errors' location and log-scale shifts fitted too), ``network-fit-errors-only`` (both) and
``network-fit-errors-only-400`` (both, N = 400).

Usage::

    nice -n 10 python benchmarks/state_proposal.py --scenes crossing --seeds 5
    python benchmarks/state_proposal.py --scenes toy --samplers state-only --seeds 8
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import scene_neutral  # noqa: E402  (the runs and the table's row)

STATE = ("--method", "state")
SAMPLERS: dict[str, tuple[str, ...]] = {
    "default": (),
    "state": STATE,
    "state-only": (*STATE, "--plain-fallback", "0"),
    "state-only-400": (*STATE, "--plain-fallback", "0", "--n", "400"),
    "network-only": (*STATE, "--state-model", "network", "--plain-fallback", "0"),
    "spline-only": (*STATE, "--state-model", "spline", "--plain-fallback", "0"),
    "fit-errors-only": (*STATE, "--state-fit-errors", "--plain-fallback", "0"),
    "network-fit-errors-only": (*STATE, "--state-model", "network", "--state-fit-errors", "--plain-fallback", "0"),
    "network-fit-errors-only-400": (
        *STATE,
        "--state-model",
        "network",
        "--state-fit-errors",
        "--plain-fallback",
        "0",
        "--n",
        "400",
    ),
}
"""Each sampler's flags (module docstring)."""

SCENES = {"crossing": ("--scenario", "crossing"), "toy": ("--scenario", "toy"), "cut-in": ("--scenario", "cut-in")}
"""The scenes that report state features: the crossing (reference 2.98e-4), the toy (exact 1e-21 at its defaults) and
the cut-in (reference 7.95e-5)."""


@dataclasses.dataclass(frozen=True)
class Run:
    """One run (:class:`scene_neutral.Outcome`) and its state features' replays: rollouts and seconds."""

    outcome: scene_neutral.Outcome
    replayed: int
    replay_s: float


def one_run(scene: str, sampler: str, seed: int) -> Run:
    """The run of ``scene`` and ``sampler`` at ``seed``, the state method's replays counted."""
    from pemviz.estimators.state import StateCrossEntropy

    counted = {"n": 0, "s": 0.0}
    replay = StateCrossEntropy._with_state

    def counting(self, batch):  # noqa: ANN001, ANN202
        t0 = time.perf_counter()
        out = replay(self, batch)
        counted["n"] += batch.n
        counted["s"] += time.perf_counter() - t0
        return out

    StateCrossEntropy._with_state = counting  # type: ignore[method-assign]
    scene_neutral.SCENES.update(SCENES)
    scene_neutral.SAMPLERS.update(SAMPLERS)
    outcome = scene_neutral.one_run(scene, sampler, seed)
    return Run(dataclasses.replace(outcome, sims=outcome.sims + counted["n"]), counted["n"], counted["s"])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["crossing"], choices=list(SCENES))
    ap.add_argument("--samplers", nargs="+", default=list(SAMPLERS), choices=list(SAMPLERS))
    ap.add_argument("--seeds", type=int, default=5, help="seeds a scene and sampler")
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args(argv)
    seeds = range(a.first_seed, a.first_seed + a.seeds)
    jobs = [(s, v, k) for s in a.scenes for v in a.samplers for k in seeds]
    runs: list[Run] = []
    with ProcessPoolExecutor(a.jobs) as pool:
        for r in pool.map(one_run, *zip(*jobs, strict=False)):
            runs.append(r)
            o = r.outcome
            print(
                f"# {o.scene} {o.variant} seed {o.seed}: x{o.ratio:.3g} of p, {o.verdict}, interval "
                f"{'holds' if o.interval_holds else ('misses' if o.interval else 'none')}, {o.sims:,} "
                f"rollout-equivalents ({r.replayed:,} replayed, {r.replay_s:.1f} s), {o.wall_s:.0f} s",
                file=sys.stderr,
                flush=True,
            )
    print(
        "| scene | sampler | runs | median rel. error | within x2 | intervals holding p | bounds holding p | "
        "reliable outside x2 | nan | verdicts | answered by plain MC | cost (rollout-eq.) | plain MC for that error | "
        "ratio | s a run | replayed a run (s) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for s in a.scenes:
        for v in a.samplers:
            mine = [r for r in runs if r.outcome.scene == s and r.outcome.variant == v]
            if mine:
                replayed = statistics.mean(r.replayed for r in mine)
                replay_s = statistics.mean(r.replay_s for r in mine)
                row = scene_neutral.summary([r.outcome for r in mine])
                print(f"{row} {replayed:,.0f} ({replay_s:.1f} s) |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
