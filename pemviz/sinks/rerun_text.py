"""What the rerun recording (:mod:`pemviz.sinks.recording`) says of its estimate: the ``estimate`` document, the
parts of the ``description`` below its head (:func:`pemviz.sinks.rerun_views.intro_markdown`) and the values of the
``final`` entity, as Markdown or plain values from the engine's events and config: no state, no I/O, no rerun."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from pemviz.core.estimate import Estimate, Reference, error_text, format_probability
from pemviz.engine.events import FinalEstimate, StageResult

if TYPE_CHECKING:
    from pemviz.config import ExperimentConfig


def description_markdown(intro: str, status: str, stage_rows: list[str], config: str) -> str:
    """The ``description`` document: its head ``intro``, the run's result ``status`` (empty: none yet), the table of
    the finished stages (each a row of :func:`stage_row`) and the config (:func:`config_markdown`)."""
    table = ""
    if stage_rows:
        table = (
            "\n## Stages\n\n| stage | name | gamma | failures | mu_hat | NLL | ESS | wall s |\n"
            "|---|---|---|---|---|---|---|---|\n" + "\n".join(stage_rows) + "\n"
        )
    status = f"\n## Result\n\n{status}\n" if status else ""
    return intro + status + table + config


def config_markdown(cfg: ExperimentConfig) -> str:
    """The ``description``'s table of the run's settings (every field of its config)."""
    rows = "\n".join(f"| {k} | `{v}` |" for k, v in vars(cfg).items())
    return f"\n## Config\n\n| setting | value |\n|---|---|\n{rows}\n"


def _num(x: float, fmt: str) -> str:
    return format(x, fmt) if math.isfinite(x) else "-"


def stage_row(res: StageResult, label: str) -> str:
    """A finished stage's row of the ``description``'s table (``label``: its name in the run's plan)."""
    e = res.estimate
    return (
        f"| {res.stage} | {label} | {_num(res.gamma, '.4f')} | "
        f"{e.n_failures}/{e.n} | {format_probability(e.log_mu_hat)} | {_num(e.nll_mean, '.2f')} | "
        f"{_num(e.ess, '.2f')} | {res.wall_s:.2f} |"
    )


def estimate_markdown(
    e: Estimate, where: str, exact_log_p: float | None, reference: Reference | None, final: FinalEstimate | None = None
) -> str:
    """The ``estimate`` document of ``e``, headed ``where`` (e.g. "Final estimate"): mu_hat with its interval (or its
    bound), k-hat, verdict, the exact answer (``exact_log_p``) or the ``reference`` where known and, for the
    ``final`` estimate, its simulations and wall time."""
    lines = [
        f"# {where}",
        "",
        f"## mu_hat = {format_probability(e.log_mu_hat, 4)}",
        "",
        (f"95 % interval **{e.interval_text()}**" if e.interval_backed else f"**{e.bound_text()}**"),
        "",
        f"**{e.verdict}**: {e.reason}",
    ]
    exact = exact_log_p
    if exact is not None:
        lines += [
            "",
            f"exact answer **{format_probability(exact, 4)}**: {error_text(e.log_mu_hat, exact)}, "
            f"{e.holds_text(exact, '**outside**')}",
        ]
    elif reference is not None:
        lines += ["", reference.comparison(e, outside="**outside**")]
    if e.n_failures == 0:
        lines += ["", f"No failure among {e.n} rollouts: mu_hat = 0 says only that the sampler found no crash."]
    khat = "-" if math.isnan(e.khat) else f"{e.khat:.2f}"
    nll = f" · NLL {e.nll_mean:.1f} nats" if math.isfinite(e.nll_mean) else ""
    lines += ["", f"failures {e.n_failures}/{e.n} · ESS {e.ess:.1f} · k-hat {khat}{nll}"]
    if final is not None:
        lines += ["", f"{final.n_simulations:,} simulations in {final.wall_s:.1f} s"]
    return "\n".join(lines) + "\n"


def final_status(ev: FinalEstimate) -> str:
    """The ``description``'s result of a finished run: the final estimate in one line, then the severity curve's
    Markdown (where it has more than one level) and the estimate's spread under other PEMs (where computed)."""
    e = ev.estimate
    status = (
        f"**Final estimate** mu_hat = {format_probability(e.log_mu_hat, 4)} (log mu_hat = "
        f"{e.log_mu_hat:.4f} nats; {e.n_failures}/{e.n} failures, ESS {e.ess:.2f}) from "
        f"{ev.n_simulations} simulations in {ev.wall_s:.1f} s."
    )
    if ev.severity is not None and len(ev.severity.points) > 1:
        status += "\n\n" + ev.severity.markdown()
    if ev.pem_spread is not None:
        status += "\n\n```text\n" + "\n".join(ev.pem_spread.lines()) + "\n```\n"
    return status


def final_values(ev: FinalEstimate) -> dict[str, Any]:
    """The values of the ``final`` entity (:class:`rerun.AnyValues`): the final estimate, its 95 % interval (or lower
    bound), k-hat, verdict, simulations and wall time."""
    e = ev.estimate
    return dict(
        log_mu_hat=e.log_mu_hat,
        mu_hat=format_probability(e.log_mu_hat, 4),
        n_failures=e.n_failures,
        n=e.n,
        nll_mean=e.nll_mean,
        ess=e.ess,
        log_ci_low=e.shown_log_ci[0],
        log_ci_high=e.shown_log_ci[1],
        interval="95 % CI" if e.interval_backed else "95 % lower bound, no upper bound",
        khat=e.khat,
        verdict=e.verdict,
        reason=e.reason,
        n_simulations=ev.n_simulations,
        wall_s=ev.wall_s,
    )
