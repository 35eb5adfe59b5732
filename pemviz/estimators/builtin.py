"""The built-in methods' hooks that are not their estimators' own, as :mod:`pemviz.methods` names them (each
imported on first use): the builders of ``mc``, ``naive50``, ``mixed50`` (:mod:`pemviz.estimators.fixed`) and
``tilt``, and the methods' checks, budgets and advice. Each builder is ``(config, problem, check) -> Estimator``."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from pemviz.core.plan import RunPlan
from pemviz.settings import plain_fallback_most, setting_of

if TYPE_CHECKING:  # light to import: a config's checks read these hooks
    from pemviz.config import ExperimentConfig
    from pemviz.core.problems import Problem
    from pemviz.estimators.base import Check, Estimator


def adaptive_then_most(config: ExperimentConfig, simulations: int) -> tuple[int, str]:
    """The most rollouts the fallback (:func:`pemviz.estimators.fallback.with_plain_fallback`) may draw after stages of
    ``simulations`` rollout-equivalents: the retry's (:meth:`pemviz.settings.FallbackSettings.retry_n`) and plain
    Monte Carlo's (:func:`pemviz.settings.plain_fallback_most`); 0 with ``plain_fallback`` = 0 or over an operating
    design domain; and the cost line's words for them."""
    _, most, words = _then(config, simulations, None)
    return most, words


def adaptive_then_plan(config: ExperimentConfig) -> RunPlan | None:
    """The stages the fallback (:func:`pemviz.estimators.fallback.with_plain_fallback`) runs once more before plain
    Monte Carlo: the plan at the retry's N
    (:meth:`pemviz.settings.FallbackSettings.retry_n`), or None where the run has no retry (or no fallback at all)."""
    return _then(config, 0, None)[0]


def adaptive_then_drawn(
    config: ExperimentConfig, simulations: int, problem: Problem
) -> tuple[RunPlan | None, int, str]:
    """What the fallback may draw on ``problem`` after stages of ``simulations`` rollout-equivalents, by the rules
    :class:`pemviz.estimators.fallback.PlainFallback` draws by: no retry where the scene refuses it
    (:func:`pemviz.estimators.fallback.retry_refused`), no plain rollouts where they could decide nothing
    (:func:`pemviz.estimators.fallback.plain_cannot_decide`)."""
    return _then(config, simulations, problem)


def _then(config: ExperimentConfig, simulations: int, problem: Problem | None) -> tuple[RunPlan | None, int, str]:
    """(the retry's plan or None, the most simulations after the stages, their words); ``problem`` None: whatever
    the scene."""
    if config.over_odd or config.fallback.plain_fallback <= 0:
        return None, 0, ""
    from pemviz.estimators.ce_plan import adaptive_run_plan

    again = config.fallback.retry_n(config.n_per_stage, config.stop_rule)
    if problem is not None:
        from pemviz.estimators.fallback import plain_cannot_decide, retry_refused, stated_log_p

        again = None if retry_refused(problem) is not None else again
    plan = None if again is None else adaptive_run_plan(config.replace(n_per_stage=again))
    retry = 0 if again is None else int(config.replace(n_per_stage=again).n_simulations)
    most = plain_fallback_most(config.fallback.plain_fallback, simulations + retry, config.most_simulations)
    if problem is not None and plain_cannot_decide(most, stated_log_p(problem), config.stop.require) is not None:
        most = 0
    when = "if the stages' weights back no interval"
    if retry == 0:
        return None, most, f"plain rollouts {when}" if most else ""
    then = ", then plain Monte Carlo" if most else ""
    return plan, retry + most, f"rollouts {when} (their retry at N = {again:,}{then})"


def mc(config: ExperimentConfig, problem: Problem, check: Check | None = None) -> Estimator:
    """Plain Monte Carlo: one batch drawn by the PEM itself (:func:`pemviz.estimators.fixed.monte_carlo`)."""
    from pemviz.estimators.fixed import monte_carlo

    return monte_carlo(problem, config.n_per_stage, config.weights_until_failure, config.seed)


def naive50(config: ExperimentConfig, problem: Problem, check: Check | None = None) -> Estimator:
    """One batch by a 50 % detector (:func:`pemviz.estimators.fixed.naive50`)."""
    from pemviz.estimators.fixed import naive50 as build

    return build(problem, config.n_per_stage, config.weights_until_failure, config.seed)


def mixed50(config: ExperimentConfig, problem: Problem, check: Check | None = None) -> Estimator:
    """One batch by 50 % inside the window, the PEM outside (:func:`pemviz.estimators.fixed.mixed50`)."""
    from pemviz.estimators.fixed import mixed50 as build

    return build(problem, config.n_per_stage, config.weights_until_failure, config.seed)


def tilt(config: ExperimentConfig, problem: Problem, check: Check | None = None) -> Estimator:
    """The scenario's own tilted proposal (:class:`pemviz.estimators.tilt.CommittorTilt`)."""
    from pemviz.estimators.tilt import CommittorTilt

    return CommittorTilt(problem, config.n_per_stage, config.weights_until_failure, config.seed)


# -- the built-in methods' own settings, advice and words (pemviz.methods.Method's hooks) ----------------


def adaptive_conflict(config: ExperimentConfig, n_objects: int) -> tuple[str, str] | None:
    """The cross-entropy sampler's settings (the adaptive and state methods') against each other
    (:meth:`pemviz.methods.adaptive.CrossEntropySettings.conflict`), the run's and the scene (:attr:`Method.validate
    <pemviz.methods.Method>`): a mixture over rollouts needs frozen weights that stop somewhere, the fit of
    whole elite rollouts one object a step, a stop rule a final batch to add to."""
    ce = config.adaptive
    own = ce.conflict()
    if own is not None:
        return own
    if ce.target_share + ce.plain_share > 0.0 and ce.fits_whole_rollouts(config.weights_until_failure):
        return "target_share", (
            "a mixture over rollouts needs weights = 'frozen' and weights_until_failure or "
            "proposal_window; set target_share = plain_share = 0 (preset state-ce-step) for the "
            "others"
        )
    if n_objects != 1 and ce.fits_whole_rollouts(config.weights_until_failure):
        return "scenario", ce.whole_rollouts_refusal(n_objects)
    if config.stop_rule is not None and not ce.has_final_batch:
        return config.stop_rule, (
            "a stop rule adds final batches; final_estimate = 'last-stage' has none (use pooled " "or fresh)"
        )
    return None


def ams_conflict(config: ExperimentConfig, n_objects: int) -> tuple[str, str] | None:
    """Splitting's settings: k, the particles killed an iteration, below N."""
    from pemviz.settings import SETTINGS

    if config.ams.ams_killed >= config.n_per_stage:
        return "ams_killed", f"{SETTINGS['ams_killed'].words} must be a whole number in [1, N - 1]"
    return None


def adaptive_more_budget(config: ExperimentConfig, text: Any) -> str | None:
    """The cross-entropy sampler's route (:attr:`Method.more_budget <pemviz.methods.Method>`): a run at
    4 N (pretraining, K stages of 4 N and the final batch) or a precision target."""
    ce = config.adaptive
    sims = ce.pretrain_rollouts + ce.n_stages * 4 * config.n_per_stage + (ce.n_final if ce.has_final_batch else 0)
    return text.importance_route(config, sims)


def tilt_more_budget(config: ExperimentConfig, text: Any) -> str | None:
    """The tilted proposal's route: more batches of it to a 20 % interval."""
    m = text.cap(config)
    if m is None:
        return None
    return (
        f"more tilted batches (--rel-error 0.2 --max-sims {m}{text.tail()}: up to {m:,} simulations"
        f"{text.time(m, text.s_per)})"
    )


def ams_more_budget(config: ExperimentConfig, text: Any) -> str | None:
    """Splitting's route: no final batch to add to, so more particles (about 4 times the time), or a graded score the
    scene has: its learned committor (``text.committor``: the scene has one; None: not known), else the nominal
    look-ahead, which any scene that splits can rank by (:mod:`pemviz.estimators.lookahead_score`)."""
    n = int(getattr(config, "n_per_stage", 100))
    more = f"more particles (--n {4 * n}{text.time(4.0, text.wall_s) if text.wall_s else ''})"
    score = setting_of(config, "ams_score", "robustness")
    if text.committor and score != "committor":
        return f"{more}, or particles ranked by the scenario's learned committor (--ams-score committor)"
    if score == "robustness":
        return (
            f"{more}, or particles ranked by the nominal look-ahead (--ams-score lookahead: where the robustness "
            "is flat every particle ties and the run dies out)"
        )
    return more


def adaptive_no_failure(n: int) -> str:
    """What to try after a cross-entropy run of ``n`` rollouts without a failure."""
    return (
        "the sampler never reached a crash. More stages (K), more rollouts (N) or the state-ce preset move the "
        "proposal further towards the failures."
    )


def mc_no_failure(n: int) -> str:
    """What to try after ``n`` plain rollouts without a failure."""
    return (
        f"plain Monte Carlo draws every rollout from the PEM itself, so a failure of probability p shows up about "
        f"once in 1/p rollouts; none in {n:,} only says p is likely below {3.0 / n:.2g}. The adaptive method "
        "(state-ce preset) reaches failures far rarer than that."
    )


def ams_no_failure(n: int) -> str:
    """What to try after a splitting run whose particles reached no failure."""
    return "no particle reached a failure: more particles (N) or the adaptive method (state-ce preset)."
