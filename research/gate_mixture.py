"""Splitting's failures choose a mixture of state gates; importance sampling from it, mixed with the PEM, estimates p
(a study outside the product, on the crossing). Its figures are on the Validation page, "A proposal that reads the
tracker's state".

The pipeline, one run per seed:

1. **Pilot**: adaptive multilevel splitting ranked by the nominal look-ahead (``pemviz run --method ams --ams-score
   lookahead``; :func:`pemviz.estimators.ams.run_ams`), N particles, k killed an iteration. Its failing particles
   at the end are (approximately, and correlated through their genealogy) draws of the failures' law; their state
   features are replayed (one rollout-equivalent each).
2. **Fit**: K state gates (``research/state_gate.py``: the PEM outside an intersection of up to ``--depth``
   intervals of a column of the rows with their state features; inside it the detection's logit shifted by c and
   the errors' scale widened by exp(b)), each fitted by the cross-entropy objective to the failures the ones before
   cover least (:func:`state_gate.mixture_of_gates`, every failing particle alike).
3. **Estimate**: N_e rollouts from the defensive mixture ``s p + (1 - s) / K sum_j q_j`` over whole rollouts (s
   ``--state-share``: every weight at most 1 / s; Hesterberg 1995, Owen & Zhou 2000), each weighted by the exact
   likelihood ratio ``p(x) / (s p(x) + (1 - s) / K sum_j q_j(x))`` in float64 log space (the state method's own
   mixture weights: ``pemviz run --method state``), with the state method's interval, ESS and verdict. The pilot
   only chooses the q_j, drawn from streams of its own, so the estimate is unbiased whatever the pilot found
   (Owen, "Monte Carlo theory, methods and examples", 2013, ch. 9-10).

The estimate stage is ``pemviz run --scenario crossing --method state --plain-fallback 0 --k 1 --n N1 --n-final
N_e`` with the state proposal replaced by the fixed mixture (:func:`state_gate.install`; its one CE stage of N1 and
its pretraining of 100 rollouts fit nothing and weigh nothing into the estimate, but they are counted). Its verdict
is the scene's, not capped at ``doubtful`` for "no stage's threshold reached the failure level": the q_j were fitted
to the pilot's failures.

Cost, in rollout-equivalents: the pilot's simulated steps over T (look-ahead included), the replays of its failures'
features, every rollout of the estimate stage (pretraining, CE stage, final), and the replays of their features
(``pemviz run --method state`` replays each batch it weighs; shown apart, as ``sim`` and ``+ replays``).

Commands whose figures were recorded (one process, ``nice -n 10``, seeds 1-5; 1-3.5 min a seed on the loaded
2-core machine)::

    python research/gate_mixture.py --seeds 1 2 3 4 5    # one pilot of 200 particles, k = 20
    python research/gate_mixture.py --seeds 1 2 3 4 5 --pilots 3 --particles 100 --killed 10
    python research/gate_mixture.py --seeds 1 2 3 4 5 --pilots 3 --particles 100 --killed 10 \\
        --refit 4000 --refit-gates 2
    python research/gate_mixture.py --seeds 1 2 3 4 5 --pilots 3 --particles 100 --killed 10 \\
        --param brake_ttc_s=1.5 --reference 1.294e-4
    python research/gate_mixture.py --seeds 1 2 3 4 5 --pilots 3 --particles 100 --killed 10 \\
        --param brake_ttc_s=1.5 --reference 1.294e-4 --n-final 8000 16000 32000    # 16 min
    python research/gate_mixture.py --seeds 6 7 8 9 10 --pilots 3 --particles 100 --killed 10 \\
        --param brake_ttc_s=1.5 --reference 1.294e-4 --n-final 8000 16000 32000
    python research/gate_mixture.py --seeds 1 2 3 4 5 --pilots 3 --particles 100 --killed 10 \\
        --param brake_ttc_s=1.5 --reference 1.294e-4 --n-final 64000 --first-stream 3

``--n-final N1 N2 ...``: one pilot and fit per seed, then an estimate at each N_e, each from a stream of its own
(:data:`ESTIMATE_SEED`; the first from ``seed``, so that ``--n-final 8000`` alone gives the same numbers); each
line shows the estimate's failures, ESS, k-hat and its largest failure weight's share of the failures' weights, and
counts the pilot in its cost as a run of that N_e alone would.

``--refit N1``: a round of N1 rollouts from the pilot's mixture (its own stream) whose failures, weighted by their
exact importance weights, fit ``--refit-gates`` more gates, each to the failures the mixture so far covers least
(adaptive multiple importance sampling's refit: Cornuet, Marin, Mira & Robert, Scand. J. Stat. 39, 2012); the
estimate is the next round's alone, so it stays unbiased.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import state_gate  # noqa: E402

PILOT_SEED = 1_000_003
"""The pilot's stream is ``seed + PILOT_SEED``: apart from the estimate's (``seed``)."""
REFIT_SEED = 2_000_003
"""The refit round's stream (``--refit``) is ``seed + REFIT_SEED``."""
ESTIMATE_SEED = 3_000_017
"""The estimate at the i-th N_e of ``--n-final`` (from 0) draws from stream ``seed + (i + --first-stream)
ESTIMATE_SEED`` (by default the first from ``seed``)."""


@dataclass(frozen=True)
class Pilot:
    """The pilot's failures as :func:`state_gate.mixture_of_gates` takes them, and what they cost.

    Attributes:
        rows: float64 [F, T, O, G] the failing particles' object rows with their state features.
        detected: bool [F, T, O]; z: float64 [F, T, O, D] the errors standardised by the PEM's location and scale.
        families: the initial particles the failures descend from.
        log_p: the pilot's own estimate of log p (nats), for the record.
        cost: rollout-equivalents (simulated steps over T, the look-ahead's included, and the F replays).
    """

    rows: np.ndarray
    detected: np.ndarray
    z: np.ndarray
    families: int
    log_p: float
    cost: int


def problem(params: list[str]) -> Any:
    """The crossing's :class:`pemviz.core.problems.Problem` at ``--param`` values ``params`` ("name=value")."""
    from pemviz.cli import build_parser
    from pemviz.commands.run import config_from_args
    from pemviz.scenarios.registry import problem_for

    flags = [f for p in params for f in ("--param", p)]
    return problem_for(config_from_args(build_parser("run").parse_args(["run", "--scenario", "crossing", *flags])))


def pilot(pb: Any, seed: int, n: int, killed: int) -> Pilot:
    """Look-ahead splitting of N particles (``killed`` an iteration) from stream ``seed``: its failing particles with
    their state features (:class:`Pilot`)."""
    from pemviz.estimators.ams import run_ams

    s = run_ams(pb, n, killed, seed=seed, score="lookahead")
    failed = s.running[:, -1] < 0.0
    assert s.particles is not None
    batch = s.particles.select(failed)
    b, rows, z = _replayed(pb, batch)
    return Pilot(
        rows,
        np.asarray(b.detected, bool),
        z,
        int(np.unique(s.eve[failed]).size),
        float(s.estimate().log_mu_hat),
        s.n_simulations + batch.n,
    )


def pooled(pilots: list[Pilot]) -> Pilot:
    """Independent pilots' failures together (every failure alike), their costs summed, their log p averaged."""
    return Pilot(
        np.concatenate([p.rows for p in pilots]),
        np.concatenate([p.detected for p in pilots]),
        np.concatenate([p.z for p in pilots]),
        sum(p.families for p in pilots),
        float(np.log(np.mean(np.exp([p.log_p for p in pilots])))),
        sum(p.cost for p in pilots),
    )


def estimate(
    seed: int, gates: tuple[state_gate.ErrorGate, ...], params: list[str], share: float, n_stage: int, n_final: int
) -> tuple[Any, int, Any]:
    """The estimate stage (module docstring, 3.): the run's final :class:`pemviz.engine.experiment` result, the
    rollouts it simulated (each replayed once more for its features) and its final batch's
    :class:`pemviz.engine.events.RolloutsSampled`."""
    from pemviz.estimators.state import StateCrossEntropy

    restore = state_gate.install(True, 2, None, True, gates[0], gates)
    cap = StateCrossEntropy.__dict__.get("verdict_cap")
    StateCrossEntropy.verdict_cap = property(lambda self: self.problem.verdict_cap)  # type: ignore[method-assign,assignment]
    try:
        flags = [f for p in params for f in ("--param", p)]
        flags += ["--state-share", str(share), "--k", "1", "--n", str(n_stage), "--n-final", str(n_final)]
        seen, final, _ = state_gate.draw(seed, flags)
    finally:
        if cap is None:
            del StateCrossEntropy.verdict_cap
        else:
            StateCrossEntropy.verdict_cap = cap  # type: ignore[method-assign]
        restore()
    return final, sum(int(np.asarray(ev.failed).size if ev.n_total is None else ev.n_total) for ev in seen), seen[-1]


def largest_share(ev: Any, n_failures: int) -> float:
    """The largest failure weight's share of the failures' weights in the final batch ``ev`` (a
    :class:`pemviz.engine.events.RolloutsSampled`; a streamed stage's every log-weight and robustness), nan where
    its failures are not the estimate's ``n_failures`` (a pooled estimate)."""
    from scipy.special import logsumexp

    if ev.n_total is None:
        lw = np.asarray(ev.log_weight, np.float64)[np.asarray(ev.failed, bool)]
    else:
        lw = np.asarray(ev.stage_log_weight, np.float64)[np.asarray(ev.stage_robustness) < 0.0]
    if lw.size != n_failures or not lw.size:
        return math.nan
    return float(math.exp(lw.max() - logsumexp(lw)))


def weighted_failures(pb: Any, ev: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The failures of a drawn batch (a :class:`pemviz.engine.events.RolloutsSampled` of a whole stage) as
    :func:`state_gate.mixture_of_gates` takes them, with their importance weights: (rows [F, T, O, G], detected
    [F, T, O], z [F, T, O, D], w [F] over their sum)."""

    failed = np.asarray(ev.failed, bool)
    batch = ev.batch.select(failed)
    b, rows, z = _replayed(pb, batch)
    lw = np.asarray(ev.log_weight, dtype=np.float64)[failed]
    w = np.exp(lw - lw.max()) if lw.size else lw
    return rows, np.asarray(b.detected, bool), z, w / w.sum() if w.size else w


def one_seed(a: argparse.Namespace, seed: int, pb: Any, log_ref: float) -> list[dict[str, Any]]:
    """Pilot and fit for ``seed``, then an estimate at each N_e of ``--n-final`` from a stream of its own (the same
    gates: the pilot only chooses the q_j); prints a line per estimate and returns their numbers."""
    t0 = time.perf_counter()
    pilots = [pilot(pb, seed + PILOT_SEED + 7919 * r, a.particles, a.killed) for r in range(a.pilots)]
    pl = pilots[0] if len(pilots) == 1 else pooled(pilots)
    print(
        f"seed {seed}: pilot {pl.rows.shape[0]} failures from {pl.families} families, its p x"
        f"{math.exp(pl.log_p - log_ref):.3g} of the reference, {pl.cost:,} rollout-eq.",
        flush=True,
    )
    gates = state_gate.mixture_of_gates(pb, pl.rows, pl.detected, pl.z, a.depth, a.gates, label="  gate")
    if not gates:
        print(f"seed {seed}: no gate fitted")
        return [{"seed": seed, "n_final": n, "ratio": math.nan} for n in a.n_final]
    refit, replays = 0, 0
    if a.refit:  # a round from the pilot's mixture; its failures, weighted exactly, fit more gates
        _, refit, ev = estimate(seed + REFIT_SEED, gates, a.param, a.share, a.n_stage, a.refit)
        rows, det, z, w = weighted_failures(pb, ev)
        if w.size:
            more = state_gate.mixture_of_gates(pb, rows, det, z, a.depth, a.refit_gates, "  refit gate", w, gates)
            gates = (*gates, *more)
        print(f"seed {seed}: refit round {int(w.size)} failures, ESS {1.0 / float(np.sum(w**2)) if w.size else 0:.1f}")
        replays = refit + int(w.size)  # the round's replays in the run, and its failures' for the fit
    out = []
    for i, n_final in enumerate(a.n_final):
        t1 = time.perf_counter()
        stream = seed + (a.first_stream + i) * ESTIMATE_SEED
        final, simulated, ev = estimate(stream, gates, a.param, a.share, a.n_stage, n_final)
        e = final.estimate
        lo, hi = e.shown_log_ci
        holds = e.interval_backed and lo <= log_ref <= hi
        sim = pl.cost - pl.rows.shape[0] + refit + simulated  # replays (of features, no simulation) in total only
        total = pl.cost + refit + replays + 2 * simulated
        ratio = math.exp(e.log_mu_hat - log_ref)
        top = largest_share(ev, e.n_failures)
        interval = f"[{math.exp(lo):.3g}, {math.exp(hi):.3g}]" if e.interval_backed else "no interval"
        print(
            f"seed {seed} N_e {n_final}: {math.exp(e.log_mu_hat):.4g} {interval} x{ratio:.3g} of p, "
            f"{e.n_failures} failures, ESS {e.ess:.1f}, k-hat {e.khat:.2f}, largest weight {top:.3f} of the "
            f"failures', {e.verdict}, {len(gates)} gates, cost {sim:,} sim / {total:,} + replays, "
            f"{time.perf_counter() - t1:.0f} s ({time.perf_counter() - t0:.0f} s the seed) ({e.reason})",
            flush=True,
        )
        out.append(
            {
                "seed": seed,
                "n_final": n_final,
                "ratio": ratio,
                "holds": holds,
                "interval": e.interval_backed,
                "verdict": e.verdict,
                "ess": e.ess,
                "khat": e.khat,
                "top": top,
                "sim": sim,
                "total": total,
            }
        )
    return out


def summary(rows: list[dict[str, Any]], p: float) -> None:
    """The seeds' median relative error, within x2, intervals holding p, ``reliable`` outside x2, the ESS and k-hat
    (median, range) and the cost against plain Monte Carlo's for the same median error (its relative error
    sqrt((1 - p) / (n p))), for the estimates of one N_e."""
    ok = [r for r in rows if math.isfinite(r["ratio"])]
    rel = np.array([abs(r["ratio"] - 1.0) for r in ok] + [1.0] * (len(rows) - len(ok)))
    med = float(np.median(rel))
    within = sum(0.5 <= r["ratio"] <= 2.0 for r in ok)
    holds = sum(bool(r.get("holds")) for r in ok)
    printed = sum(bool(r.get("interval")) for r in ok)
    wrong = sum(r.get("verdict") == "reliable" and not 0.5 <= r["ratio"] <= 2.0 for r in ok)
    verdicts = {v: sum(r.get("verdict") == v for r in ok) for v in ("reliable", "doubtful", "unreliable")}
    sim, total = (float(np.mean([r[k] for r in ok])) if ok else math.nan for k in ("sim", "total"))
    ess, khat = (np.array([r[k] for r in ok], dtype=np.float64) for k in ("ess", "khat"))
    mc = (1.0 - p) / (p * med**2) if med > 0 else math.inf
    spread = ", ".join(f"{np.nanmedian(x):.2f} ({np.nanmin(x):.2f}-{np.nanmax(x):.2f})" for x in (ess, khat))
    n_final = ok[0]["n_final"] if ok else rows[0]["n_final"]
    print(
        f"N_e {n_final}, {len(rows)} seeds: median rel. error {med:.3f}, within x2 {within}/{len(rows)}, intervals "
        f"printed {printed}, holding p {holds}, reliable outside x2 {wrong}; verdicts {verdicts}; ESS, k-hat: "
        f"{spread}; mean cost {sim:,.0f} sim / {total:,.0f} + replays; plain MC for that error {mc:,.0f}: ratio "
        f"{sim / mc:.3f} / {total / mc:.3f}"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1])
    ap.add_argument("--param", action="append", default=[], help="the crossing's --param name=value")
    ap.add_argument("--reference", type=float, default=None, help="p (default: the scene's reference)")
    ap.add_argument("--particles", type=int, default=200, help="the pilot's particles N")
    ap.add_argument("--killed", type=int, default=20, help="the pilot's particles killed an iteration")
    ap.add_argument("--gates", type=int, default=4, help="K, the gates of the mixture")
    ap.add_argument("--depth", type=int, default=2, help="the most intervals a gate is the intersection of")
    ap.add_argument("--max-logit", type=float, default=6.0, help="a gate's largest |c| (nats)")
    ap.add_argument("--max-scale", type=float, default=40.0, help="a gate's largest widening exp(b) (1: the PEM's)")
    ap.add_argument("--pilots", type=int, default=1, help="independent pilots, their failures pooled")
    ap.add_argument("--share", type=float, default=0.1, help="s, the PEM's share of the mixture")
    ap.add_argument("--n-stage", type=int, default=50, help="the estimate stage's one CE stage (fits nothing)")
    ap.add_argument("--refit", type=int, default=0, help="a round of this many rollouts whose failures fit more gates")
    ap.add_argument("--refit-gates", type=int, default=2, help="the gates the refit round adds")
    ap.add_argument(
        "--n-final", type=int, nargs="+", default=[8000], help="N_e, the rollouts of the estimate (several: one each)"
    )
    ap.add_argument(
        "--first-stream", type=int, default=0, help="the i-th N_e draws from stream seed + (this + i) ESTIMATE_SEED"
    )
    a = ap.parse_args(argv)
    from threadpoolctl import threadpool_limits

    pb = problem(a.param)
    state_gate.LOGIT_GRID = np.linspace(-a.max_logit, a.max_logit, int(round(8 * a.max_logit)) + 1)
    state_gate.LOG_SCALE_GRID = np.log(np.linspace(1.0, a.max_scale, max(1, int(round(2 * (a.max_scale - 1)))) + 1))
    if a.reference is not None:
        log_ref = math.log(a.reference)
    else:
        log_ref = math.log(pb.reference.n_failures / pb.reference.n)
    with threadpool_limits(1):
        rows = [r for s in a.seeds for r in one_seed(a, s, pb, log_ref)]
    for n_final in a.n_final:
        summary([r for r in rows if r["n_final"] == n_final], math.exp(log_ref))
    return 0


def _replayed(pb: Any, batch: Any) -> tuple[Any, np.ndarray, np.ndarray]:
    """``batch`` with its state features replayed, its object rows [F, T, O, G], standardised errors z [F, T, O, D]."""
    from pemviz.core.features import with_state
    from pemviz.scenarios.crossing.scene import OBJECT_NAMES

    b = with_state(batch, pb.features(batch, None))
    rows = np.asarray(b.object_rows, dtype=np.float64)
    noise = np.asarray(b.noise, dtype=np.float64)
    own = rows.reshape(-1, rows.shape[-1])[:, : len(OBJECT_NAMES)]
    loc, log_scale = pb.target.noise_params(np.ascontiguousarray(own))
    z = ((noise.reshape(-1, noise.shape[-1]) - loc) * np.exp(-log_scale)).reshape(noise.shape)
    return b, rows, z


if __name__ == "__main__":
    raise SystemExit(main())
