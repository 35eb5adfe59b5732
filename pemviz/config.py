"""ExperimentConfig: every knob of a pemviz experiment, validated once.

What each knob is (symbol, words, allowed range, help, command-line flag, the estimator that reads it) lives in one
place, :data:`pemviz.settings.SETTINGS`, with the choices and limits beside it (:data:`METHODS`, :data:`MAX_SEED`,
... below are :mod:`pemviz.settings`'s): the config's checks, the command line (:mod:`pemviz.commands`), the panel's
form (:mod:`pemviz.app.form`) and the estimators (:func:`~pemviz.settings.settings_of`) all read it there. This module
holds :class:`ExperimentConfig`, its checks of the settings against each other and :class:`ConfigError`.

Where is alpha used? ``ExperimentConfig.smoothing`` here, then :class:`pemviz.estimators.cross_entropy.CrossEntropy`
(its CE stage) and :func:`pemviz.estimators.ce_fit.ce_update` (the weighted fit). The metric:
:class:`pemviz.engine.experiment.Experiment` ranks the rollouts with it
(:meth:`pemviz.core.problems.Problem.robustness`). The seed: the engine's rollout stream and the estimator's fit,
tie-breaking and initial-weight streams.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, cast

from pemviz.core.requirement import RequirementError, parse_requirement
from pemviz.settings import SETTINGS


def scene_defaults(scenario: str, params: Any = ()) -> dict[str, Any]:
    """The settings ``scenario`` runs with when neither a method nor a preset is asked for: its registry record's
    :attr:`~pemviz.scenarios.registry.Scenario.run_defaults`, or over an operating design domain (a drawn parameter
    among ``params``, the ``scenario_params`` pairs) its
    :attr:`~pemviz.scenarios.registry.Scenario.odd_defaults` where it has them; empty: the config's defaults (also
    for a scenario not registered)."""
    from pemviz.scenarios.odd import is_odd
    from pemviz.scenarios.registry import known

    record = known(scenario)
    if record is None:
        return {}
    drawn = any(isinstance(pair, tuple) and is_odd(pair[-1]) for pair in params)
    return dict(record.odd_defaults if drawn and record.odd_defaults else record.run_defaults)


def objects_of(scenario: str) -> int:
    """The objects ``scenario`` perceives a step (its registry record's
    :attr:`~pemviz.scenarios.registry.Scenario.n_objects`; 1 for one not registered): what the config checks a method
    against before anything is loaded."""
    from pemviz.scenarios.registry import known

    record = known(scenario)
    return record.n_objects if record is not None else 1


class ConfigError(ValueError):
    """An invalid experiment setting: the message says which, the value, and what is allowed.

    Attributes:
        field: the :class:`ExperimentConfig` attribute at fault (None when not one field).
    """

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.field = field


@dataclass(frozen=True)
class ExperimentConfig:
    """One experiment: the sampler of Innes & Ramamoorthy (2022, Algorithm 1) and its baselines.

    The defaults are the recommended sampler (preset :data:`pemviz.presets.DEFAULT_PRESET`);
    :data:`PRESETS["paper"] <pemviz.presets.PRESETS>` gives the paper's own settings.

    Attributes:
        method: one of :data:`METHODS`.
        n_stages: K, cross-entropy stages (adaptive only).
        n_per_stage: N, rollouts per stage; for mc / naive50 / mixed50 the number of rollouts; for ams the particles.
        n_final: N_e, fresh rollouts from the final proposal for the estimate (paper 100; the default 1000: once the
            proposal is fitted a rollout costs microseconds of simulation, a CE stage ~0.5 s of fitting, and these
            rollouts are the ones drawn from the best proposal).
        quantile_level: sigma in [0.5, 1): the stage threshold is the (1 - sigma) quantile of robustness.
        smoothing: alpha in (0, 1]: the power on the importance weights in the CE loss.
        metric: robustness semantics, one of :data:`METRICS`.
        seed: seeds the rollouts, the fits, tie-breaking and the proposal's initial weights, each its own stream;
            the same seed gives the same estimate.
        ce_epochs: the most Adam epochs per stage (paper 500; authors' code 1000; the default 150: each fit starts
            from the last stage's proposal and, with ``fit_tolerance``, stops once its loss stops falling).
        pretrain_rollouts, pretrain_epochs: PEM-driven rollouts and epochs to pretrain the proposal (paper: 1000;
            the default sampler 500, which measured as accurate on the braking job and saves a second).
        learning_rate: Adam step size for the proposal (paper 1e-3; the default 1e-2, with fewer epochs).
        weights: ``frozen`` (paper eq. 10-11) or ``recomputed`` with gradient (authors' code).
        final_estimate: ``pooled``: the N_e fresh rollouts together with every CE stage whose proposal was fitted to
            failures (the stage before it had reached gamma = 0), each rollout weighted by the proposal that drew
            it; ``fresh``: the N_e rollouts alone (paper); ``last-stage``: the last stage's batch (authors' code).
        pool_weights: how ``pooled`` combines its stages, one of :data:`POOL_WEIGHTS`: ``rollouts``, every rollout
            alike (stage kappa's estimate counts n_kappa / N); ``linear``, the j-th pooled stage's estimate counts in
            proportion to j n_kappa, so later proposals, fitted to more failures, count more; ``quadratic`` (the
            default), in proportion to j^2 n_kappa. All are fixed before any pooled stage is drawn, so all are
            unbiased.
        uniforms: how the rollouts of a batch draw their detections, one of :data:`UNIFORMS`: ``iid``, one
            independent U(0, 1) per rollout and step (the paper); ``array-rqmc`` (the default), the rollouts of each
            fixed block of 8,192 of a batch (of each sampler of a mixture but the target's own share;
            :data:`pemviz.core.rng.RQMC_BLOCK`, whatever the executor or chunk size) are stepped as one array; at each
            step those inside the sampler's window are ranked by their sampler's detect logit, then by their state
            (:func:`pemviz.core.rng.ranking_key`), and given the points of a randomly shifted golden-ratio lattice
            (:func:`pemviz.core.detectors.step_uniforms`; L'Ecuyer, Lecot & Tuffin, Operations Research 56(4), 2008).
            Each rollout still follows its sampler exactly, so every estimate keeps its expectation; the batch's
            estimate varies less (~40 % less variance at the default sampler's last stages on the braking job).
            The rollouts of a batch are no longer independent: an interval computed as if they were is
            conservative. ``ams`` draws its particles and continuations i.i.d.
        pem: path of PEM weights, or None for the shipped default.
        scenario: what is simulated, one of :data:`SCENARIOS`.
        scenario_params: ``(name, value)`` pairs setting the scenario's parameters (``pemviz run --param
            NAME=VALUE``): scalar fields of its dataclass, each name once, each value of its field's type (float, int,
            bool) and in the dataclass's range (:mod:`pemviz.scenarios.parameters`; units in the names: ``_m``
            metres, ``_mps`` m/s, ``_s`` seconds); ``()``: the scenario's defaults. The braking scenario's crash gap
            is also ``margin``: give it once.
        sim: the braking scenario's back-end, one of :data:`SIMULATORS`.
        executor: where rollouts are simulated, one of :data:`EXECUTORS`.
        ray_address: the Ray cluster to use with ``executor="ray"`` (None: start a local one).
        chunk_rollouts: None (serial stages above :data:`pemviz.engine.experiment.STREAM_ABOVE` rollouts stream
            in chunks of :data:`pemviz.core.lockstep.DEFAULT_CHUNK_SIZE`) or the most rollouts simulated and scored at a
            time (memory): a serial stage of more streams chunk by chunk. The rollouts, weights and estimate do not
            depend on it (detectors give a row the same bits in any batch: :mod:`pemviz.core.exact`; Array-RQMC
            couples fixed blocks, whatever the chunks).
        rel_error: None (the planned budget) or R, a precision target: after the planned stages the run adds final
            batches from the same sampler, pooled with the first, until the 95 % interval's relative half-width
            (:attr:`pemviz.core.estimate.Estimate.rel_half_width`) is at most R or a cap is hit
            (:class:`pemviz.estimators.precision.PrecisionTarget`).
        require: None or a requirement ``"p < T"`` (``<``, ``<=``, ``>``, ``>=``; T in (0, 1)): after the planned
            stages the run adds final batches as for ``rel_error`` until the interval of an alpha-spending sequential
            test lies wholly on one side of T (:mod:`pemviz.core.requirement`) or a cap is hit.
        margin: None or the braking scenario's crash gap in metres (``BrakingParams.crash_gap_m``, default 2): a
            failure is the gap dropping below it; 0 is contact (the severity curve's last point,
            :mod:`pemviz.core.severity`).
        pem_uncertainty: re-weight the rollouts under every member of the PEM's bootstrap ensemble and under the
            logit shifts :data:`pemviz.scenarios.problems.PEM_SHIFTS` (:mod:`pemviz.core.reweight`).
        pem_shift: None or D: re-weight the rollouts under the PEM with every logit shifted by D (log-odds).
        max_sims: with ``rel_error``, the most simulations in all (None: :data:`DEFAULT_MAX_SIMS`); at least the
            planned ones.
        max_time_s: with ``rel_error``, no batch is started after this many seconds of the run, and none is sized to
            end past it (None: no time cap); seconds.
        ams_killed: k, particles killed and resampled per AMS iteration at least (every tie at the level is killed
            too), 1 <= k < N (``method = "ams"``).
        ams_max_iterations: the most AMS iterations; a run stopped by it before its level reached the failure
            threshold gets the verdict ``doubtful``.
        ams_score: what ranks the AMS particles: ``robustness`` (the formula's classic robustness) or ``committor``
            (-log of the scenario's learned probability of failure, where it has one: the cut-in).

    Sampler improvements over the paper (on by default; :data:`PRESETS["paper"] <pemviz.presets.PRESETS>` turns them
    off; each one's effect is measured against exact answers in ``research/truth_sampler_improvements.py``):
        proposal_inputs: h(s), one of :data:`PROPOSAL_INPUTS`.
        proposal_window: the proposal replaces the PEM only where the detector can matter (the problem's
            ``window``: gap < 10 m); elsewhere q = p_PEM, so those steps weigh exactly 1 and are not fitted.
        skip_decided: with ``proposal_window``, the proposal also gives way to the PEM at steps where the outcome is
            already decided (the problem's ``decided_below``: a gap below the 2 m crash gap), so that the proposal
            network runs only where a detection can matter; those steps weigh exactly 1 and are not fitted.
        weights_until_failure: importance weights (estimate and CE fit) stop at the step where the failure
            happens: later actions change nothing, like the last action already left out.
        smoothing_at_failure: alpha in (0, 2] once gamma_kappa has reached the failure threshold 0 (None:
            ``smoothing``). 1.0 fits the failures with their full weights, the textbook CE target (the proposal
            nearest the zero-variance density in Kullback-Leibler divergence). Above 1 (the default, 1.2) a failure
            counts w^alpha = w x w^(alpha - 1): more where the samplers drew it too rarely. That is the gradient of
            the Renyi divergence of order alpha with the weights frozen at the samplers (Li & Turner, "Renyi
            divergence variational inference", NeurIPS 2016; alpha = 2 is the variance-minimisation program of de
            Boer, Kroese, Mannor & Rubinstein, "A tutorial on the cross-entropy method", Ann. Oper. Res. 2005):
            the proposal covers the failures it under-samples, which lightens the tail of the weights of the
            pooled stages.
        final_smoothing: alpha of the last stage's fit, whose proposal draws the N_e final rollouts (None: as the
            stages before it); needs ``fit_weights = "mixture"``, which weighs the whole failure pool again at every
            fit. The default 1.0 gives that proposal the plain CE fit: at 2,100 simulations on the braking job,
            median relative error 0.021 over seeds 0-99 with alpha 1.2 before it (0.022 with 1.0 throughout); at
            1,200 simulations 0.039 against 0.054.
        elite_ties: ``all`` (paper: every rollout with r <= gamma_kappa is an elite) or ``random``: the rollouts
            with r < gamma_kappa, plus ties at gamma_kappa drawn at random up to ceil((1 - sigma) N) elites (with a
            discrete robustness, e.g. the toy's integer distances, ties can make every rollout an elite and stall
            the adaptation, or make non-failing r = 0 rollouts elites at the last level).
        pretrain_cap: None (paper: pretrain on PEM-driven rollouts) or c in (0, 1): inside the problem's
            window the pretraining rollouts detect with min(p_PEM, c), so that the first proposal misses often
            enough for stage 1 to rank rollouts (with p = 0.999 all 100 rollouts of stage 1 look alike).
        defensive: eps in [0, 1): the CE stages' rollouts are drawn from the defensive mixture (1 - eps) q + eps x 50 %
            at every step, so that both outcomes keep probability >= eps / 2 at every step (0: the proposal itself,
            paper). It caps q(miss) at 1 - eps / 2: a failure that needs m misses in a row then has proposal
            probability <= (1 - eps / 2)^m, whence the two shares below.
        target_share, plain_share: once a stage has reached the failure level, a mixture over whole rollouts: these
            shares of each stage's rollouts come from the target p and from the proposal q without the per-step
            mixture, the rest from the per-step mixture; every rollout weighs p / (sum of share x sampler) (the
            balance heuristic), at most 1 / ``target_share`` (Hesterberg 1995; Owen & Zhou, "Safe and effective
            importance sampling", JASA 2000). 0 and 0: no mixture over rollouts.
        fit_all_failures: once a stage's threshold reached the failure level, each CE fit uses the failures of every
            stage since then, each weighted by the proposal that drew it (all are weighted samples of the same
            zero-variance density 1[fail] p / mu), instead of the stage's alone.
        fit_weights: how those fits weigh the failures (``fit_all_failures``), one of :data:`FIT_WEIGHTS`:
            ``sampler``, by the sampler that drew each; ``mixture``, by the mixture of the samplers of every stage
            since the failure level, each at its share of their rollouts (the balance heuristic: the
            deterministic-mixture weights of adaptive multiple importance sampling, Cornuet, Marin, Mira &
            Robert, Scand. J. Stat. 2012), which bounds the weight of a failure an early, poor proposal drew by
            what the later ones give it. Only the fits change: the estimate weighs every rollout by its own
            stage's samplers. Once the fitted steps are thinned (more than 20 x ``fit_rows`` of them) the steps
            keep the weights they have.

    Fitting cost (:data:`PRESETS["paper"] <pemviz.presets.PRESETS>` keeps the paper's: ``adam`` on every step):
        fit: one of :data:`FITS`; ``adam`` runs ``ce_epochs`` / ``pretrain_epochs`` epochs at ``learning_rate``,
            ``lbfgs`` at most ``fit_max_steps`` iterations per fit, stopping once converged.
        fit_precision: one of :data:`FIT_PRECISIONS`: the arithmetic of the ``adam`` fits of a weighted
            log-likelihood; the parameters stay float64, and every weight is computed in float64 from the density
            sampled from (the logit the sampler drew with), so the precision moves the proposal only, never the
            estimate's unbiasedness.
        fit_max_steps: the most L-BFGS iterations of one fit (``fit = "lbfgs"``).
        fit_rows: None (every fitted step) or the most steps one fit sees: beyond that, a weighted systematic
            subsample with the same expected CE objective, so a stage's fit costs the same at any N (the default
            5,000: at N = 100 the pretraining and the failure pool of the later stages are subsampled; it fits twice as
            fast as 10,000 at large N, and the default run's 100-seed accuracy is the same).
        fit_tolerance: early stopping of the CE stages' ``adam`` fits: a fit stops once its loss (nats per step)
            fell by less than this over the last 50 epochs; None: every epoch. The pretraining fit of at most
            ``fit_rows`` steps runs every epoch; ``lbfgs`` stops at its own tolerance.
    """

    method: str = "adaptive"
    n_stages: int = 10
    n_per_stage: int = 100
    n_final: int = 1000
    quantile_level: float = 0.95
    smoothing: float = 0.1
    metric: str = "classic"
    seed: int = 0
    ce_epochs: int = 150
    pretrain_rollouts: int = 100
    pretrain_epochs: int = 500
    learning_rate: float = 1e-2
    weights: str = "frozen"
    final_estimate: str = "pooled"
    pool_weights: str = "quadratic"
    uniforms: str = "array-rqmc"
    pem: str | None = None
    scenario: str = "braking"
    scenario_params: tuple[tuple[str, float | int | bool], ...] = ()
    sim: str = "batched"
    executor: str = "serial"
    ray_address: str | None = None
    chunk_rollouts: int | None = None
    rel_error: float | None = None
    require: str | None = None
    margin: float | None = None
    pem_uncertainty: bool = False
    pem_shift: float | None = None
    max_sims: int | None = None
    max_time_s: float | None = None
    proposal_inputs: str = "state"
    proposal_window: bool = True
    skip_decided: bool = True
    weights_until_failure: bool = True
    smoothing_at_failure: float | None = 1.2
    final_smoothing: float | None = 1.0
    elite_ties: str = "random"
    pretrain_cap: float | None = 0.9
    defensive: float = 0.2
    target_share: float = 0.1
    plain_share: float = 0.45
    fit_all_failures: bool = True
    fit_weights: str = "mixture"
    fit: str = "adam"
    fit_precision: str = "exact"
    fit_max_steps: int = 200
    fit_rows: int | None = 5_000
    fit_tolerance: float | None = 1e-3
    ams_killed: int = 10
    ams_max_iterations: int = 10_000
    ams_score: str = "robustness"

    def __post_init__(self) -> None:
        for setting in SETTINGS.values():  # each setting on its own: its range from SETTINGS
            value = getattr(self, setting.name)
            if not setting.accepts(value):
                verb = "use" if setting.kind in ("choice", "method", "scenario") else f"{setting.words} must be"
                raise ConfigError(f"{setting.title} = {value!r} is invalid: {verb} {setting.allowed}", setting.name)

        def need(ok: bool, name: str, allowed: str) -> None:  # the settings against each other
            if not ok:
                raise ConfigError(f"{SETTINGS[name].title} = {getattr(self, name)!r} is invalid: {allowed}", name)

        if self.scenario_params:  # the names, kinds and ranges of the scenario's own dataclass
            from pemviz.scenarios.parameters import ParameterError, check_pairs

            try:
                check_pairs(self.scenario, self.scenario_params)
            except ParameterError as exc:
                need(False, "scenario_params", str(exc))
        need(
            self.margin is None or "crash_gap_m" not in dict(self.scenario_params),
            "margin",
            "the crash gap is also the parameter crash_gap_m: give it once (--margin or --param crash_gap_m=...)",
        )
        need(self.ray_address is None or self.executor == "ray", "ray_address", "give it only with executor = 'ray'")
        need(
            self.scenario == "braking" or self.sim == "batched",
            "scenario",
            "the cut-in runs on its batched twin only; use sim = 'batched'",
        )
        need(self.target_share + self.plain_share <= 1.0, "target_share", "target_share + plain_share must be <= 1")
        need(
            self.fit_weights == "sampler" or self.fit_all_failures,
            "fit_weights",
            "'mixture' weighs the failures of fit_all_failures; set fit_weights = 'sampler' without it",
        )
        need(
            self.margin is None or self.scenario == "braking",
            "margin",
            "the crash gap is the braking scenario's; the cut-in's failure is its safe distance (R_G1)",
        )
        if self.require is not None:
            try:
                parse_requirement(self.require)
            except RequirementError as exc:
                need(False, "require", str(exc))
        need(
            self.require is None or self.rel_error is None,
            "require",
            "give one stop rule: a requirement (--require) or a precision target (--rel-error)",
        )
        from pemviz.methods import extensible_names, method_or_none

        method = method_or_none(self.method)
        if method is not None:  # the method's own settings against the others (Method.validate)
            need(
                self.stop_rule is None or method.extensible,
                self.stop_rule or "rel_error",
                f"method {method.name} has no final batch to add to; use it with method "
                f"{', '.join(extensible_names())}",
            )
            # a whole number: check_pairs checked the value's kind (the field's, an int)
            n_objects = cast(int, dict(self.scenario_params).get("n_objects", objects_of(self.scenario)))
            conflict = method.conflict(self, n_objects)
            if conflict is not None:
                need(False, *conflict)
        for cap in ("max_sims", "max_time_s"):
            need(
                getattr(self, cap) is None or self.stop_rule is not None,
                cap,
                "a cap on the rollouts added for a target relative error or a requirement: give it with rel_error "
                "(--rel-error) or require (--require)",
            )
        need(
            self.max_sims is None or self.max_sims >= self.n_simulations,
            "max_sims",
            f"{SETTINGS['max_sims'].words} must be at least the run's planned {self.n_simulations:,} simulations",
        )
        need(
            self.final_smoothing is None or self.fit_weights == "mixture",
            "final_smoothing",
            "a last fit of its own needs fit_weights = 'mixture' (which weighs the pool again at every fit); "
            "set final_smoothing = None with fit_weights = 'sampler'",
        )

    def replace(self, **changes: Any) -> "ExperimentConfig":
        """A copy with some fields changed, validated again."""
        return dataclasses.replace(self, **changes)

    @property
    def stop_rule(self) -> str | None:
        """``rel_error`` or ``require`` when the run adds final batches until a precision target or a decision
        (:class:`pemviz.estimators.precision.PrecisionTarget`), else None."""
        return "rel_error" if self.rel_error is not None else "require" if self.require is not None else None

    @property
    def fits_whole_rollouts(self) -> bool:
        """Whether the first cross-entropy stage fits whole elite rollouts, one object a step
        (:func:`pemviz.estimators.ce_fit.ce_update`): the weights are not frozen, or neither the window nor the weights
        until failure mark the steps that count (the ``paper`` preset)."""
        return not (self.weights == "frozen" and (self.weights_until_failure or self.proposal_window))

    @property
    def n_simulations(self) -> int:
        """Rollouts the experiment will simulate, pretraining included: those of the plan its method states
        (:meth:`pemviz.methods.Method.run_plan`; an open-ended plan, e.g. splitting's, the N initial
        particles; the run reports the rollout-equivalents its continuations or look-aheads add)."""
        from pemviz.methods import method_or_none

        method = method_or_none(self.method)
        planned = method.run_plan(self).n_simulations if method is not None else None
        return int(planned) if planned is not None else self.n_per_stage


def has_final_batch(config: ExperimentConfig) -> bool:
    """Whether a cross-entropy run of ``config`` ends with N_e fresh rollouts from its final proposal (not with
    ``final_estimate = "last-stage"``)."""
    return getattr(config, "final_estimate", "pooled") != "last-stage"


def whole_rollout_fit_refusal(config: ExperimentConfig, n_objects: int) -> str:
    """The one line refusing :attr:`ExperimentConfig.fits_whole_rollouts` on a problem of ``n_objects`` objects a
    step."""
    return (
        f"the cross-entropy fit of whole elite rollouts (weights {config.weights!r}, without the window or weights "
        f"until failure) takes one object per step; this problem perceives {n_objects}: use the default sampler"
    )


def default_of(name: str) -> Any:
    """The default value of the :class:`ExperimentConfig` field ``name``, read from the dataclass (no config is made:
    a command line's help and flags need the defaults before a run, and a config's checks read the scenario registry).

    Raises:
        KeyError: not a field.
    """
    for f in dataclasses.fields(ExperimentConfig):
        if f.name == name:
            if f.default is not dataclasses.MISSING:
                return f.default
            if f.default_factory is not dataclasses.MISSING:
                return f.default_factory()
            raise KeyError(f"ExperimentConfig.{name} has no default")
    raise KeyError(f"ExperimentConfig has no field {name!r}")
