"""The cross-entropy sampler's settings (``method = "adaptive"``): :class:`CrossEntropySettings`, the adaptive method's
:attr:`pemviz.methods.Method.settings` (a run's :attr:`pemviz.config.ExperimentConfig.method_settings`, read as its
:attr:`~pemviz.config.ExperimentConfig.adaptive`; the state method's settings add theirs to them), with their choices
and limits. Each field, made by :func:`pemviz.methods.setting`, carries its row of :data:`pemviz.settings.SETTINGS`
(symbol, range, unit, help, flag; owner ``adaptive``): a setting added here is the config's, checked, a flag (where it
names one) and recorded after the keys runs record today; :class:`pemviz.estimators.cross_entropy.CrossEntropy` reads
them. Light to import: no estimator is loaded."""

from __future__ import annotations

from dataclasses import dataclass

from pemviz.methods import setting

STATE_INPUTS = "state"
"""The proposal's inputs h(s) of every observation column (:attr:`CrossEntropySettings.proposal_inputs`)."""
PROPOSAL_INPUTS = ("gap", STATE_INPUTS)
"""h(s) of the proposal: ``gap`` (paper: gap / 12 m) or ``state`` (every observation column of the problem,
e.g. gap, ego speed and lead speed of the braking scenario; distance and stopped flag of the toy)."""

WEIGHT_MODES = ("frozen", "recomputed")
FINAL_MODES = ("pooled", "fresh", "last-stage")
FIT_WEIGHTS = ("mixture", "sampler")
"""How the CE fits weigh the failures of every stage since the failure level
(:attr:`CrossEntropySettings.fit_weights`)."""
POOL_WEIGHTS = ("quadratic", "linear", "rollouts")
"""How ``final_estimate = "pooled"`` weighs its stages (:attr:`CrossEntropySettings.pool_weights`)."""
ELITE_TIES = ("all", "random")
FITS = ("adam", "lbfgs")
"""How the proposal is fitted each stage (:func:`pemviz.estimators.ce_fit.ce_update`; choices' help in the field)."""
FIT_PRECISIONS = ("exact", "float32", "float64")
"""The arithmetic of the proposal's Adam fits (:func:`pemviz.core.sampling.fit_proposal`): ``exact``
(:func:`pemviz.core.exact_fit.fit_exact`) gives the same proposal on every CPU; torch's kernels' last bits depend on the
CPU's vector unit and BLAS kernel."""
MAX_STAGES = 1_000
"""Largest K: the paper uses 10; past a few dozen stages the proposal has long converged."""
MAX_SMOOTHING_AT_FAILURE = 2.0
"""Largest alpha once the failure level is reached: 2 is the variance-minimisation program; beyond it the weights'
tail decides the fit."""
MAX_EPOCHS = 100_000
"""Largest Adam epochs per stage (paper 500, authors' code 1000; 10^5 epochs take ~10 min a stage)."""


@dataclass(frozen=True)
class CrossEntropySettings:
    """Algorithm 1 of Innes & Ramamoorthy (2022) as pemviz runs it; the defaults are the recommended sampler
    (:data:`PRESETS["paper"] <pemviz.presets.PRESETS>` gives the paper's own). N, the rollouts of a stage, is the run's
    :attr:`pemviz.config.ExperimentConfig.n_per_stage`; whether the weights stop at the failure step is the run's
    :attr:`~pemviz.config.ExperimentConfig.weights_until_failure` (every method's). Each field's help is its row of the
    settings table; what it does not say:

    Attributes:
    n_final: N_e (paper 100; the default 1000: a fitted proposal's rollout costs microseconds, a CE stage's fit ~0.5 s).
    quantile_level: sigma in [0.5, 1): the stage threshold is the (1 - sigma) quantile of robustness.
    smoothing: alpha in (0, 1]: the power on the importance weights in the CE loss.
    ce_epochs, pretrain_epochs, learning_rate: paper 500, 1000 and 1e-3 (the authors' code 1000 epochs a stage); the
        defaults fit fewer epochs at a larger step, from the last stage's proposal, until ``fit_tolerance``.
    weights: ``frozen`` is the paper's eq. 10-11; ``recomputed`` (with gradient) the authors' code.
    final_estimate: ``pooled`` pools the stages whose proposal was fitted to failures (the stage before reached
        gamma = 0); ``fresh`` is the paper's, ``last-stage`` the authors' code's.
    pool_weights: fixed before any pooled stage is drawn, so every choice is unbiased.
    proposal_window, skip_decided: outside the problem's ``window`` (gap < 10 m), or below its ``decided_below``,
        q = p_PEM: those steps weigh exactly 1 and are not fitted.
    smoothing_at_failure: alpha in (0, 2]. Above 1 a failure counts w^alpha = w x w^(alpha - 1), more where the
        samplers drew it too rarely: the gradient of the Renyi divergence of order alpha with the weights frozen at
        the samplers (Li & Turner, "Renyi divergence variational inference", NeurIPS 2016; alpha = 2 is the
        variance-minimisation program of de Boer, Kroese, Mannor & Rubinstein, "A tutorial on the cross-entropy
        method", Ann. Oper. Res. 2005), which lightens the tail of the pooled stages' weights.
    elite_ties: with a discrete robustness (the toy's integer distances) ties can make every rollout an elite and
        stall the adaptation; ``random`` draws the ties up to ceil((1 - sigma) N) elites.
    pretrain_cap: c in (0, 1), so that the first proposal misses often enough for stage 1 to rank rollouts.
    defensive: eps in [0, 1): both outcomes keep probability >= eps / 2 at every step, so a failure of m misses in a
        row has proposal probability <= (1 - eps / 2)^m.
    target_share, plain_share: a mixture over whole rollouts once a stage reached the failure level; every rollout
        weighs p / (sum of share x sampler) (the balance heuristic), at most 1 / ``target_share`` (Hesterberg 1995;
        Owen & Zhou, "Safe and effective importance sampling", JASA 2000).
    fit_all_failures, fit_weights: the failures of every stage since the failure level are weighted samples of the
        same zero-variance density 1[fail] p / mu; ``mixture`` weighs them by the deterministic mixture of the
        stages' samplers (adaptive multiple importance sampling, Cornuet, Marin, Mira & Robert, Scand. J. Stat.
        2012). Only the fits change: the estimate weighs every rollout by its own stage's samplers.
    fit: ``lbfgs`` is L-BFGS with a strong-Wolfe line search (Nocedal & Wright, "Numerical Optimization", 2006,
        Alg. 7.5).
    fit_precision: the parameters and every weight stay float64, so it moves the proposal, never the unbiasedness.
    fit_rows: a weighted systematic subsample keeps the expected CE objective, so a fit costs the same at any N."""

    n_stages: int = setting(
        10,
        "the number of cross-entropy stages K",
        "stages of N rollouts, the proposal refitted after each",
        kind="int",
        symbol="K",
        lo=1,
        hi=MAX_STAGES,
        flags=("--k", "--stages"),
        panel="main",
    )
    n_final: int = setting(
        1000,
        "the rollouts of the final estimate N_e",
        "fresh rollouts from the final proposal for the estimate",
        kind="int",
        symbol="N_e",
        lo=1,
        flags=("--n-final",),
        panel="main",
    )
    quantile_level: float = setting(
        0.95,
        "the quantile level sigma",
        "the stage threshold is the (1 - sigma) quantile of robustness",
        symbol="sigma",
        lo=0.5,
        hi=1.0,
        hi_open=True,
        flags=("--sigma",),
        panel="main",
    )
    smoothing: float = setting(
        0.1,
        "the smoothing alpha",
        "the power on the importance weights in the CE loss",
        symbol="alpha",
        lo=0.0,
        hi=1.0,
        lo_open=True,
        flags=("--alpha",),
        panel="main",
    )
    ce_epochs: int = setting(
        150,
        "the Adam epochs per stage",
        "the most Adam epochs of a cross-entropy stage's fit",
        kind="int",
        short="CE epochs",
        lo=1,
        hi=MAX_EPOCHS,
        flags=("--ce-epochs",),
        panel="advanced",
    )
    pretrain_rollouts: int = setting(
        100,
        "the pretraining rollouts",
        "PEM-driven rollouts the first proposal is fitted to",
        kind="int",
        short="pretrain rollouts",
        lo=1,
        panel="advanced",
    )
    pretrain_epochs: int = setting(
        500,
        "the pretraining epochs",
        "Adam epochs of the first proposal's fit",
        kind="int",
        short="pretrain epochs",
        lo=1,
        hi=MAX_EPOCHS,
        flags=("--pretrain-epochs",),
        panel="advanced",
    )
    learning_rate: float = setting(
        0.01, "the learning rate", "Adam's step size for the proposal", lo=0.0, lo_open=True, panel="advanced"
    )
    weights: str = setting(
        "frozen",
        "the importance weights of the fit",
        "how the CE loss holds the importance weights",
        kind="choice",
        choices=WEIGHT_MODES,
        choice_help=(
            ("frozen", "constants of each fit (the paper's eq. 10-11)"),
            ("recomputed", "recomputed from the proposal, with their gradient (the authors' code)"),
        ),
        panel="advanced",
    )
    final_estimate: str = setting(
        "pooled",
        "the final estimate",
        "which rollouts the estimate weighs",
        kind="choice",
        choices=FINAL_MODES,
        choice_help=(
            (
                "pooled",
                "the final rollouts and every stage fitted to failures, each weighted by the proposal that drew it",
            ),
            ("fresh", "the final rollouts alone (the paper)"),
            ("last-stage", "the last stage's batch (the authors' code)"),
        ),
        panel="advanced",
    )
    pool_weights: str = setting(
        "quadratic",
        "the weights of the pooled stages",
        "how the pooled estimate counts its stages",
        kind="choice",
        choices=POOL_WEIGHTS,
        choice_help=(
            ("quadratic", "the j-th pooled stage in proportion to j^2 n_j"),
            ("linear", "in proportion to j n_j"),
            ("rollouts", "every rollout alike"),
        ),
    )
    proposal_inputs: str = setting(
        STATE_INPUTS,
        "the proposal's inputs h(s)",
        "what the proposal sees",
        kind="choice",
        choices=PROPOSAL_INPUTS,
        choice_help=(
            ("gap", "the gap to the lead car (the paper)"),
            (STATE_INPUTS, "every observation column of the problem"),
        ),
    )
    proposal_window: bool = setting(
        True, "the proposal window", "the proposal replaces the PEM only where the detector can matter", kind="bool"
    )
    skip_decided: bool = setting(
        True,
        "the skip of decided steps",
        "with the window, the proposal also gives way to the PEM where the outcome is already decided",
        kind="bool",
    )
    smoothing_at_failure: float | None = setting(
        1.2,
        "the smoothing alpha at the failure level",
        "alpha once the stage threshold has reached the failure level (None: the smoothing alpha)",
        short="alpha at failure",
        lo=0.0,
        hi=MAX_SMOOTHING_AT_FAILURE,
        lo_open=True,
        optional=True,
    )
    final_smoothing: float | None = setting(
        1.0,
        "the smoothing alpha of the last fit",
        "alpha of the last stage's fit, whose proposal draws the final rollouts (None: as the stages before it)",
        short="final alpha",
        lo=0.0,
        hi=MAX_SMOOTHING_AT_FAILURE,
        lo_open=True,
        optional=True,
    )
    elite_ties: str = setting(
        "random",
        "the elite ties",
        "which rollouts tied at the stage threshold are elites",
        kind="choice",
        choices=ELITE_TIES,
        choice_help=(
            ("all", "every rollout at or below the threshold (the paper)"),
            ("random", "ties drawn at random up to ceil((1 - sigma) N) elites"),
        ),
    )
    pretrain_cap: float | None = setting(
        0.9,
        "the pretraining detection cap",
        "inside the window the pretraining rollouts detect with at most this probability (None: the PEM's)",
        lo=0.0,
        hi=1.0,
        lo_open=True,
        hi_open=True,
        optional=True,
    )
    defensive: float = setting(
        0.2,
        "the defensive share eps",
        "the CE stages draw from (1 - eps) q + eps x 50 % at every step",
        lo=0.0,
        hi=1.0,
        hi_open=True,
    )
    target_share: float = setting(
        0.1,
        "the target's share",
        "once the failure level is reached, the share of a stage's rollouts drawn from the target p",
        lo=0.0,
        hi=1.0,
    )
    plain_share: float = setting(
        0.45,
        "the plain proposal's share",
        "the share of a stage's rollouts drawn from the proposal without the per-step mixture",
        lo=0.0,
        hi=1.0,
    )
    fit_all_failures: bool = setting(
        True,
        "the fit to all failures",
        "each fit uses the failures of every stage since the failure level",
        kind="bool",
    )
    fit_weights: str = setting(
        "mixture",
        "the weights of the failures in a fit",
        "how the fits weigh the failures of every stage",
        kind="choice",
        choices=FIT_WEIGHTS,
        choice_help=(
            ("mixture", "by the mixture of the samplers since the failure level"),
            ("sampler", "by the sampler that drew each"),
        ),
    )
    fit: str = setting(
        "adam",
        "the fitting method",
        "how the proposal is fitted each stage",
        kind="choice",
        choices=FITS,
        choice_help=(
            ("adam", "full-batch Adam, a number of epochs"),
            ("lbfgs", "L-BFGS from the previous proposal until converged"),
        ),
    )
    fit_precision: str = setting(
        "exact",
        "the fit's precision",
        "the arithmetic of the proposal's Adam fits (the parameters and every weight stay float64)",
        kind="choice",
        choices=FIT_PRECISIONS,
        choice_help=(
            ("exact", "the same proposal on every CPU; the default"),
            ("float32", "torch's float32 kernels: the last bits depend on the CPU"),
            ("float64", "torch's float64 kernels, as the paper's fits"),
        ),
    )
    fit_max_steps: int = setting(
        200, "the L-BFGS iterations", "the most L-BFGS iterations of one fit", kind="int", lo=1
    )
    fit_rows: int | None = setting(
        5_000,
        "the rows of a fit",
        "the most steps one fit sees, beyond them a weighted subsample with the same expected loss (None: every "
        "step)",
        kind="int",
        lo=1,
        optional=True,
    )
    fit_tolerance: float | None = setting(
        0.001,
        "the fit tolerance",
        "a CE stage's Adam fit stops once its loss fell by less than this over the last 50 epochs (None: every "
        "epoch)",
        unit="nats per step",
        lo=0.0,
        lo_open=True,
        optional=True,
    )

    @property
    def reads_state(self) -> bool:
        """Whether the proposal reads every observation column (``proposal_inputs`` :data:`STATE_INPUTS`)."""
        return self.proposal_inputs == STATE_INPUTS

    @property
    def has_final_batch(self) -> bool:
        """Whether a run ends with N_e fresh rollouts from its final proposal (``final_estimate`` not last-stage)."""
        return self.final_estimate != "last-stage"

    def fits_whole_rollouts(self, weights_until_failure: bool) -> bool:
        """Whether the first cross-entropy stage fits whole elite rollouts, one object a step
        (:func:`pemviz.estimators.ce_fit.ce_update`): the weights are not frozen, or neither the window nor the run's
        weights until failure mark the steps that count (the ``paper`` preset)."""
        return not (self.weights == "frozen" and (weights_until_failure or self.proposal_window))

    def whole_rollouts_refusal(self, n_objects: int) -> str:
        """The one line refusing :meth:`fits_whole_rollouts` on a problem of ``n_objects`` objects a step."""
        return (
            f"the cross-entropy fit of whole elite rollouts (weights {self.weights!r}, without the window or weights "
            f"until failure) takes one object per step; this problem perceives {n_objects}: use the default sampler"
        )

    def conflict(self) -> tuple[str, str] | None:
        """(setting, what is allowed) of the first of these settings that conflicts with another, or None: checked
        when a config is made (:func:`pemviz.estimators.builtin.adaptive_conflict`)."""
        if self.target_share + self.plain_share > 1.0:
            return "target_share", "target_share + plain_share must be <= 1"
        if self.fit_weights == "mixture" and not self.fit_all_failures:
            return (
                "fit_weights",
                "'mixture' weighs the failures of fit_all_failures; set fit_weights = 'sampler' without it",
            )
        if self.final_smoothing is not None and self.fit_weights != "mixture":
            return "final_smoothing", (
                "a last fit of its own needs fit_weights = 'mixture' (which weighs the pool again at every fit); "
                "set final_smoothing = None with fit_weights = 'sampler'"
            )
        return None
