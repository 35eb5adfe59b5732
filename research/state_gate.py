"""A gated state proposal on the crossing (a study outside the product): does ``pemviz run --method state`` deliver an
interval when its proposal departs from the PEM only on the few events that decide a failure, or when its fits'
weights are tempered? Its figures are on the Validation page, "A proposal that reads the tracker's state".

The proposal (patched into :class:`pemviz.estimators.state.StateCrossEntropy` by :func:`install`, the package
untouched): q(detect) and the measurement errors are the PEM's except inside a gate, an intersection of up to
``--depth`` intervals of columns of the object rows with their state features (the tracker's, the ego's), where the
detection's logit is shifted by c and the errors' scale widened by exp(b) per component. Each CE stage refits gate, c
and b by the cross-entropy objective (Rubinstein & Kroese, "The Cross-Entropy Method", 2004; Innes & Ramamoorthy
2022, eq. 10-11: the elites' weighted log-likelihood of their events), the interval ends at the elites' weighted
quantiles of a column (:func:`fit_error_gate`): widening or tilting where the elites' events are typical costs
log-likelihood, so the fit picks the interval that holds the events that tell them apart. ``--gate-only``: the
state GLM's linear part stays 0 (q is the PEM outside the gate); else the gate is added to it.

Tempering (``--min-ess``): the failure pool's weights w_i raised to the largest power beta <= 1 whose Kish effective
sample size is at least the floor (:func:`tempering`; the adaptive tempering of sequential Monte Carlo samplers: Jasra,
Stephens, Doucet & Tsagaris, Scand. J. Stat. 38, 2011), for the GLM's fit and the gate's.

``--oracle FILE``: the gate (``--oracle-gates K``: a mixture of the PEM, its share ``--state-share``, and K gates,
each fitted to the failures the ones before cover least) fitted once to plain Monte Carlo failures (``--collect N``:
N plain rollouts of the crossing, their failures with their state features written to FILE) and kept fixed: the
best this family does with the true failures in hand; ``--held-out FILE``: the cost of gates and mixtures of gates
fitted to half of them, on the other half (:func:`held_out`).

Commands whose figures were recorded (seeds 1-5; 1-1.7 min a run on the loaded 2-core machine, two at a time)::

    nice -n 10 python research/state_gate.py --collect 400000 --seed 7 --out /tmp/fails.npz    # 100 failures, 4 min
    python research/state_gate.py --held-out /tmp/fails.npz    # the gates' cost on failures held out of the fit
    nice -n 10 python research/state_gate.py --seed S --min-ess 10
    nice -n 10 python research/state_gate.py --seed S --gated --max-logit 2 --max-scale 4 --min-ess 5
    nice -n 10 python research/state_gate.py --seed S --gated --gate-only --max-logit 1.25 --max-scale 1 \\
        -- --n 500 --sigma 0.9 --n-final 8000
    nice -n 10 python research/state_gate.py --seed S --gated --gate-only --max-scale 1 --oracle /tmp/fails.npz \\
        -- --k 1 --n-final 8000
    nice -n 10 python research/state_gate.py --seed S --oracle /tmp/fails.npz --oracle-gates 4 \\
        -- --k 1 --n 500 --n-final 8000    # and --n-final 16000

Each run is ``pemviz run --scenario crossing --method state --plain-fallback 0 --no-record --seed S`` with the flags
after ``--``; it prints each stage's failures, their log-weights' top and ESS, and the run's answer against the
reference 2.98e-4.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
from scipy.special import log_expit

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pemviz.core.detector_noise import noise_names_of, standard_log_density  # noqa: E402
from pemviz.core.diagnostics import effective_sample_size  # noqa: E402

GATE_QUANTILES = 20
"""The gate's interval ends are the elites' weighted quantiles of a column at 0, 1 / 20, ..., 1 (and -inf, +inf)."""
LOG_SCALE_GRID = np.log(np.linspace(1.0, 40.0, 79))  # --max-scale sets it
"""The log-scale shifts the fit chooses from (nats): a widening of the error's scale by 1 to 40."""
LOGIT_GRID = np.linspace(-6.0, 6.0, 49)  # --max-logit sets it
"""The shifts of the detection's logit inside the gate the fit chooses from (nats)."""
MIN_GAIN = 0.05
"""The least gain of the objective (nats per elite rollout) for a gate (or one more interval) to be used."""


@dataclass(frozen=True)
class ErrorGate:
    """Inside the gate (rows whose column ``c`` lies in [lo, hi) for every (c, lo, hi) of ``bounds``) the detection's
    logit shifted by ``logit_shift`` and the errors' scale widened by ``exp(log_scale)`` [D]; the PEM elsewhere.

    Attributes:
        bounds: the gate's conditions (a column of the rows with their state features, its interval's ends).
        logit_shift: the shift of logit q(detect) inside the gate (nats).
        log_scale: float64 [D] the log-scale shift of each error component inside the gate (nats, >= 0).
        gain: the objective's gain over the PEM (nats per elite rollout) at the fit.
    """

    bounds: tuple[tuple[int, float, float], ...]
    logit_shift: float
    log_scale: np.ndarray
    gain: float

    def inside(self, rows: np.ndarray) -> np.ndarray:
        """bool [N]: the rows [N, G] inside the gate."""
        rows = np.asarray(rows, dtype=np.float64)
        out = np.ones(rows.shape[0], bool)
        for c, lo, hi in self.bounds:
            out &= (rows[:, c] >= lo) & (rows[:, c] < hi)
        return out

    def shift(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(location shift [N, D] in units of the PEM's scale: 0, log-scale shift [N, D]) at rows [N, G]
        (:meth:`pemviz.core.sampling.Proposal.noise_shift_of`'s form)."""
        b = np.where(self.inside(rows)[:, None], self.log_scale[None, :], 0.0)
        return np.zeros_like(b), b


def error_gains(z: np.ndarray, family: str, df: np.ndarray | None) -> np.ndarray:
    """float64 [S, D, B]: each error's gain in log density (nats) from widening its scale by ``exp(b)``, b over
    :data:`LOG_SCALE_GRID`, at standardised errors ``z`` [S, D] of a location-scale ``family``:
    ``log f(z e^-b) - b - log f(z)``."""
    z = np.asarray(z, dtype=np.float64)
    b = LOG_SCALE_GRID[None, None, :]
    nu = None if df is None else np.asarray(df, dtype=np.float64)[None, :, None]
    return (
        standard_log_density(family, nu, z[:, :, None] * np.exp(-b))
        - b
        - standard_log_density(family, df, z)[:, :, None]
    )


def detection_gains(logit_p: np.ndarray, detected: np.ndarray) -> np.ndarray:
    """float64 [S, C]: each event's gain in log-likelihood (nats) from shifting its detection's logit by c, c over
    :data:`LOGIT_GRID`, at the PEM's logits ``logit_p`` [S] and the detections taken ``detected`` bool [S]; 0 where
    the PEM is certain."""
    lp = np.asarray(logit_p, dtype=np.float64)
    finite = np.isfinite(lp)
    z = np.where(finite, lp, 0.0)[:, None] + LOGIT_GRID[None, :]
    sign = np.where(np.asarray(detected, bool), 1.0, -1.0)[:, None]
    gain = log_expit(sign * z) - log_expit(sign * np.where(finite, lp, 0.0)[:, None])
    return np.where(finite[:, None], gain, 0.0)


def _best_interval(
    rows: np.ndarray, weights: np.ndarray, det: np.ndarray, err: np.ndarray, keep: np.ndarray
) -> tuple[float, int, float, float] | None:
    """(gain, column, lo, hi) of the best interval of one column over the events ``keep`` (module docstring)."""
    best: tuple[float, int, float, float] | None = None
    idx = np.flatnonzero(keep)
    for j in range(rows.shape[1]):
        x = rows[idx, j]
        if x.size == 0 or np.all(x == x[0]):
            continue
        order = idx[np.argsort(x, kind="stable")]
        xs, ws = rows[order, j], weights[order]
        cw = np.cumsum(ws)
        levels = np.searchsorted(cw, np.linspace(0.0, 1.0, GATE_QUANTILES + 1)[1:-1] * cw[-1], side="left")
        ends = np.unique(np.concatenate([[-np.inf], xs[np.minimum(levels, xs.size - 1)], [np.inf]]))
        cut = np.searchsorted(xs, ends, side="left")
        d_tot = np.concatenate([np.zeros((1, det.shape[1])), np.cumsum(det[order], axis=0)])[cut]
        e_tot = np.concatenate([np.zeros((1, *err.shape[1:])), np.cumsum(err[order], axis=0)])[cut]
        for a in range(ends.size - 1):
            d_in = (d_tot[a + 1 :] - d_tot[a]).max(axis=1)
            e_in = np.maximum((e_tot[a + 1 :] - e_tot[a]).max(axis=2), 0.0).sum(axis=1)
            gain = d_in + e_in
            c = int(np.argmax(gain))
            if best is None or gain[c] > best[0]:
                best = (float(gain[c]), j, float(ends[a]), float(ends[a + 1 + c]))
    return best


def fit_error_gate(
    rows: np.ndarray,
    detected: np.ndarray,
    logit_p: np.ndarray,
    z: np.ndarray,
    weights: np.ndarray,
    family: str,
    df: np.ndarray | None,
    depth: int = 2,
) -> ErrorGate | None:
    """The gate (up to ``depth`` intervals of columns, each found inside the last), the detection's logit shift and
    the errors' log-scale shifts that maximise the elites' weighted log-likelihood (module docstring).

    Args:
        rows: float64 [S, G] the elites' object events inside the window (rows with their state features).
        detected: bool [S] the detections taken; logit_p: float64 [S] the PEM's logit of a detection there.
        z: float64 [S, D] the errors standardised by the PEM's location and scale at the row (ignored where missed).
        weights: float64 [S] >= 0, each event's weight: its rollout's (tempered) importance weight over the elites'
            total, so that a gain is in nats per elite rollout.
        family, df: the PEM's error family (:data:`pemviz.core.detector_noise.NOISE_FAMILIES`).
        depth: the most intervals the gate is the intersection of (>= 1).
    Returns:
        The best :class:`ErrorGate`, or None where no gate gains :data:`MIN_GAIN` (or no event is given).
    """
    rows, weights = np.asarray(rows, dtype=np.float64), np.asarray(weights, dtype=np.float64)
    detected = np.asarray(detected, bool)
    if rows.shape[0] == 0 or not np.any(weights > 0):
        return None
    det = detection_gains(logit_p, detected) * weights[:, None]
    err = np.where(detected[:, None, None], error_gains(np.where(detected[:, None], z, 0.0), family, df), 0.0)
    err = err * weights[:, None, None]
    keep, bounds, gain = np.ones(rows.shape[0], bool), [], MIN_GAIN
    for _ in range(depth):
        found = _best_interval(rows, weights, det, err, keep)
        if found is None or found[0] < gain + (MIN_GAIN if bounds else 0.0):
            break
        gain, j, lo, hi = found
        bounds.append((j, lo, hi))
        keep &= (rows[:, j] >= lo) & (rows[:, j] < hi)
    if not bounds:
        return None
    d_in, e_in = det[keep].sum(axis=0), err[keep].sum(axis=0)  # [C], [D, B]
    shift = np.where(e_in.max(axis=1) > 0.0, LOG_SCALE_GRID[np.argmax(e_in, axis=1)], 0.0)
    return ErrorGate(tuple(bounds), float(LOGIT_GRID[int(np.argmax(d_in))]), shift, gain)


def tempering(log_w: np.ndarray, min_ess: float) -> float:
    """The largest beta in [0, 1] whose weights w_i^beta (``log_w`` [S], nats) have a Kish effective sample size of
    at least ``min(min_ess, S)`` (bisection to 1e-6; 1.0 where the weights themselves reach it)."""
    lw = np.asarray(log_w, dtype=np.float64)
    lw = lw[np.isfinite(lw)]
    if lw.size <= 1:
        return 1.0
    goal = min(float(min_ess), float(lw.size)) * (1.0 - 1e-9)
    if effective_sample_size(lw) >= goal:
        return 1.0
    lo, hi = 0.0, 1.0  # ESS falls as beta grows (Kish's ESS of w^beta is non-increasing in beta)
    while hi - lo > 1e-6:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if effective_sample_size(mid * lw) >= goal else (lo, mid)
    return lo if math.isfinite(lo) else 0.0


def install(
    gate_only: bool,
    depth: int,
    min_ess: float | None,
    gated: bool,
    oracle: ErrorGate | None = None,
    mixture: tuple[ErrorGate, ...] = (),
) -> Callable[[], None]:
    """Patch the state method: the gated proposal (``gated``; ``oracle``: that gate, fixed), tempered fits
    (``min_ess``; None: the method's own weights), and (``mixture``) every stage drawn from a mixture over whole
    rollouts of the PEM (its share ``state_share``, whether or not a stage reached the failure level) and the gates,
    in equal shares, each alone inside the window. Returns the function that undoes the patches."""
    from pemviz.estimators.state import StateCrossEntropy
    from pemviz.estimators.state_glm import StateGLM

    names = ("_pool_log_weight", "_pretrain", "_fit_noise", "gate", "gated_head", "noise_shift", "detect_logit")
    names = (*names, "_mixture")
    patched = [(c, n, c.__dict__.get(n, None)) for c in (StateCrossEntropy, StateGLM) for n in (*names, "fit_counts")]
    patched += [(StateGLM, "noise_shift_of", StateGLM.__dict__.get("noise_shift_of", None))]

    def restore() -> None:
        for cls, name, value in patched:
            if value is not None:
                setattr(cls, name, value)
            elif name in cls.__dict__:
                delattr(cls, name)

    glm_logit, glm_fit = StateGLM.detect_logit, StateGLM.fit_counts
    pretrain, pool_log_weight = StateCrossEntropy._pretrain, StateCrossEntropy._pool_log_weight

    def detect_logit(self, obs):  # noqa: ANN001, ANN202
        out = glm_logit(self, obs)
        gate = getattr(self, "gate", None)
        return out if gate is None else out + np.where(gate.inside(np.asarray(obs)), gate.logit_shift, 0.0)

    def fit_counts(self, inputs, counts, check=None):  # noqa: ANN001, ANN202
        return [] if gate_only else glm_fit(self, inputs, counts, check)

    def noise_shift_of(self, obs):  # noqa: ANN001, ANN202
        if self.gate is None:
            return np.zeros((len(obs), self.n_noise)), np.zeros((len(obs), self.n_noise))
        return self.gate.shift(obs)

    def _pretrain(self, batch):  # noqa: ANN001, ANN202
        pretrain(self, batch)
        d = len(noise_names_of(self.problem.target))
        self.proposal.gate, self.proposal.n_noise = oracle, d
        if d:  # an error head of the proposal's own (the samplers then draw the errors from noise_shift_of)
            self.proposal.gated_head = True

    def _pool_log_weight(self, rollout, obs, actions, counts, noise=None):  # noqa: ANN001, ANN202
        log_w = pool_log_weight(self, rollout, obs, actions, counts, noise)
        if min_ess is None or log_w.size == 0:
            return log_w
        _, first = np.unique(rollout, return_index=True)
        return tempering(log_w[first], min_ess) * log_w

    def _fit_noise(self, fit):  # noqa: ANN001, ANN202
        self._noise_data = []
        steps = self._steps
        if oracle is not None or steps is None or not steps.keep_observations or steps.thinned or not steps.parts:
            return
        if steps.observations[0][2] is None:
            return
        order, _, actions, log_w = (np.concatenate(a) for a in zip(*steps.parts, strict=False))
        rows, counts = (np.concatenate([o[i] for o in steps.observations]) for i in (0, 1))
        noise = np.concatenate([o[2] for o in steps.observations])
        _, first, inverse = np.unique(order, return_index=True, return_inverse=True)
        per = log_w[first]
        if min_ess is not None:
            per = tempering(per, min_ess) * per
        w = np.exp(per - per.max())
        w = (w / w.sum())[inverse]
        target = cast(Any, self.problem.target)
        logit_p = np.asarray(target.detect_logit(rows), dtype=np.float64)
        loc, log_scale = (np.asarray(a, dtype=np.float64) for a in target.noise_params(rows))
        z = (noise - loc) * np.exp(-log_scale)
        self.proposal.gate = fit_error_gate(rows, actions, logit_p, z, w, target.noise_family, target.noise_df, depth)
        print(f"  gate after stage {self._plan.stage}: {self.proposal.gate} ({first.size} elites)")

    StateCrossEntropy._pool_log_weight = _pool_log_weight  # type: ignore[method-assign]
    if not gated:
        return restore
    StateGLM.gate, StateGLM.gated_head = None, False  # type: ignore[attr-defined]
    StateGLM.noise_shift = property(lambda self: True if self.gated_head else None)  # type: ignore[assignment]
    StateGLM.detect_logit = detect_logit  # type: ignore[method-assign]
    StateGLM.fit_counts = fit_counts  # type: ignore[method-assign]
    StateGLM.noise_shift_of = noise_shift_of  # type: ignore[attr-defined]
    StateCrossEntropy._pretrain = _pretrain  # type: ignore[method-assign]
    StateCrossEntropy._fit_noise = _fit_noise  # type: ignore[method-assign]
    if mixture:

        def _mixture(self, n):  # noqa: ANN001, ANN202
            if getattr(self, "gate_samplers", None) is None:
                self.gate_samplers = []
                for gate in mixture:
                    proposal = copy.deepcopy(self.proposal)
                    proposal.gate = gate
                    self.gate_samplers.append(self._samplers_around(proposal)[1])
            n_p = int(round(self.ce.target_share * n))
            sizes = np.diff(np.round(np.linspace(0, n - n_p, len(mixture) + 1)).astype(int))
            return ((n_p, self.problem.target), *zip(sizes.tolist(), self.gate_samplers, strict=True))

        StateCrossEntropy._mixture = _mixture  # type: ignore[method-assign]
    return restore


def collect(n: int, seed: int, out: str) -> int:
    """N plain Monte Carlo rollouts of the crossing; their failures' rows with state features, detections and
    standardised errors written to ``out`` (npz)."""
    from pemviz.cli import build_parser
    from pemviz.commands.run import config_from_args
    from pemviz.core.features import with_state
    from pemviz.engine.events import RolloutsSampled
    from pemviz.engine.experiment import Experiment
    from pemviz.scenarios.registry import problem_for

    argv = ["run", "--scenario", "crossing", "--method", "mc", "--n", str(n), "--seed", str(seed), "--no-record"]
    cfg = config_from_args(build_parser("run").parse_args(argv))
    pb = problem_for(cfg)
    got: list = []

    def listen(ev):  # noqa: ANN001, ANN202
        if isinstance(ev, RolloutsSampled) and ev.failed.any():
            b = ev.batch.select(np.asarray(ev.failed))
            got.append(with_state(b, pb.features(b, None)))

    Experiment(cfg, problem=pb, listeners=[listen]).run()
    from pemviz.scenarios.crossing.scene import OBJECT_NAMES

    rows = np.concatenate([b.object_rows for b in got])
    flat = rows.reshape(-1, rows.shape[-1])[:, : len(OBJECT_NAMES)]  # the rows' own columns, the PEM's
    noise = np.concatenate([b.noise for b in got])
    loc, ls = pb.target.noise_params(flat)
    z = ((noise.reshape(-1, noise.shape[-1]) - loc) * np.exp(-ls)).reshape(noise.shape)
    np.savez(out, rows=rows, detected=np.concatenate([b.detected for b in got]), z=z)
    print(f"{rows.shape[0]} failures in {n:,} rollouts written to {out}")
    return 0


def oracle_gate(path: str, depth: int) -> ErrorGate | None:
    """The gate fitted to the failures of ``path`` (:func:`collect`), every failure alike."""
    from pemviz.scenarios.crossing.problem import crossing_problem

    d = np.load(path)
    rows, det, z = d["rows"], d["detected"], d["z"]
    pb = crossing_problem()
    win = rows[..., 0] < pb.window
    n = rows.shape[0]
    w = np.broadcast_to((np.ones(n) / n)[:, None, None], win.shape)[win]
    from pemviz.scenarios.crossing.scene import OBJECT_NAMES

    lp = pb.target.detect_logit(np.ascontiguousarray(rows[win][:, : len(OBJECT_NAMES)]))
    gate = fit_error_gate(rows[win], det[win], lp, z[win], w, pb.target.noise_family, pb.target.noise_df, depth)
    if gate is not None:
        print(f"oracle gate: {gate}, {gate.inside(rows[win]).sum() / n:.1f} events a failure inside")
    return gate


def oracle_mixture(path: str, depth: int, k: int) -> tuple[ErrorGate, ...]:
    """``k`` gates fitted to the failures of ``path`` (:func:`collect`) by :func:`mixture_of_gates`."""
    from pemviz.scenarios.crossing.problem import crossing_problem

    d = np.load(path)
    return mixture_of_gates(crossing_problem(), d["rows"], d["detected"], d["z"], depth, k)


def mixture_of_gates(
    pb: Any,
    rows: np.ndarray,
    det: np.ndarray,
    z: np.ndarray,
    depth: int,
    k: int,
    label: str = "oracle gate",
    weights: np.ndarray | None = None,
    given: tuple[ErrorGate, ...] = (),
) -> tuple[ErrorGate, ...]:
    """``k`` gates fitted to failures of the crossing problem ``pb``, each to the failures the ones before cover
    least (weights 1 / the mean of their q / p), as :func:`held_out` fits them, on every failure.

    Args:
        rows: float64 [F, T, O, G] the failures' object rows with their state features (time first).
        det: bool [F, T, O] the detections taken; z: float64 [F, T, O, D] the errors standardised by the PEM's
            location and scale at the row (:func:`collect`).
        depth: the most intervals a gate is the intersection of; k: the most gates.
        weights: float64 [F] >= 0, each failure's weight in the failures' law (None: every failure alike), e.g. its
            importance weight under the proposal that drew it.
        given: gates already in the mixture: the first new gate is fitted to the failures they cover least.
    Returns:
        The new gates (fewer than ``k`` where one more gains too little: :func:`fit_error_gate`).
    """
    from pemviz.scenarios.crossing.scene import OBJECT_NAMES

    t = cast(Any, pb.target)
    win = rows[..., 0] < pb.window
    n, inside_rows = rows.shape[0], rows[win]
    lp = t.detect_logit(np.ascontiguousarray(inside_rows[:, : len(OBJECT_NAMES)]))
    logit = np.zeros(win.shape)
    logit[win] = lp
    sign = np.where(det, 1.0, -1.0)
    base = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)

    def ratio(gate: ErrorGate) -> np.ndarray:
        """q_gate / p of each failure [F]."""
        ins = np.zeros(win.shape, bool)
        ins[win] = gate.inside(inside_rows)
        dq = np.where(ins, log_expit(sign * (logit + gate.logit_shift)) - log_expit(sign * logit), 0.0)
        b = gate.log_scale
        f = standard_log_density(t.noise_family, t.noise_df, z * np.exp(-b)) - b
        eq = (f - standard_log_density(t.noise_family, t.noise_df, z)).sum(-1)
        return np.exp((dq + np.where(ins & det, eq, 0.0)).sum(axis=(1, 2)))

    gates: list[ErrorGate] = []
    ratios: list[np.ndarray] = [ratio(g) for g in given]
    w = base / np.mean(ratios, axis=0) if ratios else base
    for _ in range(k):
        ew = np.broadcast_to((w / w.sum())[:, None, None], win.shape)[win]
        gate = fit_error_gate(inside_rows, det[win], lp, z[win], ew, t.noise_family, t.noise_df, depth)
        if gate is None:
            break
        ratios.append(ratio(gate))
        gates.append(gate)
        print(f"{label} {len(gates)}: {gate}")
        w = base / np.mean(ratios, axis=0)
    return tuple(gates)


def held_out(path: str) -> int:
    """The cost against plain Monte Carlo's, E[p / q] over the failures' law, of proposals fitted to the even failures
    of ``path`` (:func:`collect`) and weighed on the odd ones: one gate and mixtures of up to four (each fitted to the
    failures the ones before cover least, every gate of ``depth`` intervals), with the PEM's share s."""
    from pemviz.scenarios.crossing.problem import crossing_problem
    from pemviz.scenarios.crossing.scene import OBJECT_NAMES

    d = np.load(path)
    rows, det, z = d["rows"], d["detected"], d["z"]
    pb = crossing_problem()
    t = cast(Any, pb.target)
    win = rows[..., 0] < pb.window
    n, inside_rows = rows.shape[0], rows[win]
    lp = t.detect_logit(np.ascontiguousarray(inside_rows[:, : len(OBJECT_NAMES)]))
    logit = np.zeros(win.shape)
    logit[win] = lp
    sign = np.where(det, 1.0, -1.0)

    def log_ratio(gate: ErrorGate) -> np.ndarray:
        """log q_gate / p of each failure [n]."""
        ins = np.zeros(win.shape, bool)
        ins[win] = gate.inside(inside_rows)
        dq = np.where(ins, log_expit(sign * (logit + gate.logit_shift)) - log_expit(sign * logit), 0.0)
        b = gate.log_scale
        f = standard_log_density(t.noise_family, t.noise_df, z * np.exp(-b)) - b
        eq = (f - standard_log_density(t.noise_family, t.noise_df, z)).sum(-1)
        return (dq + np.where(ins & det, eq, 0.0)).sum(axis=(1, 2))

    fitted = np.arange(n) % 2 == 0
    for depth in (1, 2, 3):
        ratios: list[np.ndarray] = []
        w = np.where(fitted, 1.0, 0.0)
        for k in range(4):
            ew = np.broadcast_to((w / w.sum())[:, None, None], win.shape)[win]
            gate = fit_error_gate(inside_rows, det[win], lp, z[win], ew, t.noise_family, t.noise_df, depth)
            if gate is None:
                break
            ratios.append(np.exp(log_ratio(gate)))
            cover = np.mean(ratios, axis=0)
            out = []
            for share in (0.1, 0.3):
                inv = 1.0 / (share + (1.0 - share) * cover)
                out.append(
                    f"s = {share}: fitted half {inv[fitted].mean():.3f}, held-out half {inv[~fitted].mean():.3f}"
                )
            print(f"gates of {depth} intervals, {k + 1} in the mixture: " + "; ".join(out))
            w = np.where(fitted, 1.0 / cover, 0.0)
    return 0


def main(argv: list[str] | None = None) -> int:
    global LOGIT_GRID, LOG_SCALE_GRID
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--gated", action="store_true", help="the gated proposal")
    ap.add_argument("--gate-only", action="store_true", help="no GLM part: the PEM outside the gate")
    ap.add_argument("--depth", type=int, default=2, help="intervals the gate is the intersection of")
    ap.add_argument("--max-logit", type=float, default=6.0, help="largest |c| (nats)")
    ap.add_argument("--max-scale", type=float, default=40.0, help="largest widening exp(b) (1: the PEM's errors)")
    ap.add_argument("--min-ess", type=float, default=None, help="tempered fits: the weights' ESS floor")
    ap.add_argument("--oracle", default=None, help="npz of plain Monte Carlo failures (--collect): their gate, fixed")
    ap.add_argument("--collect", type=int, default=0, help="write N plain rollouts' failures to --out")
    ap.add_argument("--out", default="/tmp/crossing_failures.npz")
    ap.add_argument("--held-out", default=None, help="npz of failures (--collect): the gates' cost, held out")
    ap.add_argument("--oracle-gates", type=int, default=0, help="with --oracle: a mixture of this many gates")
    ap.add_argument("flags", nargs="*", help="pemviz run's flags (after --)")
    a = ap.parse_args(argv)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        if a.collect:
            return collect(a.collect, a.seed, a.out)
        if a.held_out:
            return held_out(a.held_out)
        LOGIT_GRID = np.linspace(-a.max_logit, a.max_logit, int(round(8 * a.max_logit)) + 1)
        LOG_SCALE_GRID = np.log(np.linspace(1.0, a.max_scale, max(1, int(round(2 * (a.max_scale - 1)))) + 1))
        if a.oracle and a.oracle_gates:
            gates = oracle_mixture(a.oracle, a.depth, a.oracle_gates)
            install(True, a.depth, None, True, gates[0], gates)
            return one_run(a.seed, a.flags)
        fixed = oracle_gate(a.oracle, a.depth) if a.oracle else None
        if fixed is not None and a.max_scale <= 1.0:
            fixed = dataclasses.replace(fixed, log_scale=0.0 * fixed.log_scale)
        install(a.gate_only, a.depth, a.min_ess, a.gated or fixed is not None, fixed)
        return one_run(a.seed, a.flags)


def draw(seed: int, flags: list[str]) -> tuple[list[Any], Any, float]:
    """``pemviz run --scenario crossing --method state --plain-fallback 0 FLAGS --seed SEED`` (no recording): each
    stage's :class:`pemviz.engine.events.RolloutsSampled`, the final estimate and log p of the reference (nan:
    none at these parameters)."""
    from pemviz.cli import build_parser
    from pemviz.commands.run import config_from_args
    from pemviz.engine.events import RolloutsSampled
    from pemviz.engine.experiment import Experiment
    from pemviz.scenarios.registry import problem_for

    seen: list[Any] = []
    argv = ["run", "--scenario", "crossing", "--method", "state", "--plain-fallback", "0", "--no-record", *flags]
    cfg = config_from_args(build_parser("run").parse_args([*argv, "--seed", str(seed)]))
    pb = problem_for(cfg)
    listen = [lambda ev: isinstance(ev, RolloutsSampled) and seen.append(ev)]
    final = Experiment(cfg, problem=pb, listeners=listen).run().final
    return seen, final, math.nan if pb.reference is None else float(pb.reference.log_p)


def one_run(seed: int, flags: list[str]) -> int:
    """The run (:func:`draw`), each stage's failures and the answer against the reference."""
    t0 = time.perf_counter()
    seen, final, truth = draw(seed, flags)
    for ev in seen:
        f, lw = np.asarray(ev.failed), np.asarray(ev.log_weight)
        top = np.sort(lw[f])[::-1]
        line = f"stage {ev.stage:2d} {ev.kind:8s} failures {int(f.sum()):4d}/{f.size}"
        if f.any():
            mu = float(np.logaddexp.reduce(top)) - math.log(f.size)
            ess = effective_sample_size(top)
            line += f"  mu/p x{math.exp(mu - truth):.3g}  ESS {ess:.1f}  top log w {np.round(top[:5], 1)}"
        print(line)
    e = final.estimate
    lo, hi = e.shown_log_ci
    holds = "holds" if e.interval_backed and lo <= truth <= hi else ("misses" if e.interval_backed else "none")
    print(
        f"seed {seed}: x{math.exp(e.log_mu_hat - truth):.3g} of p, {e.verdict}, ESS {e.ess:.1f}, interval {holds}, "
        f"{final.n_simulations:,} simulations, {time.perf_counter() - t0:.0f} s ({e.reason})"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
