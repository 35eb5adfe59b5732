"""The *Rollouts* tab of a :class:`pemviz.app.session.Session`: the chosen run's kept rollouts, sorted and filtered, and
the one chosen, shown in the 3D scene and explained."""

from __future__ import annotations

import html
import threading
from typing import cast

import viser

from pemviz.app._viser_compat import set_value
from pemviz.app.html import GREY, NO_ROLLOUT, RED, TABLE_STYLE, box
from pemviz.app.objects_view import RobustnessOutcome
from pemviz.app.runs import MAX_POPULATION, PanelRun, Population, Trajectory
from pemviz.app.scene_view import SceneView
from pemviz.core.drawing import Drawing, Severity

ROLLOUT_ORDERS = ("importance weight", "robustness", "log p", "severity")
"""How the Rollouts tab orders its rollouts: least robust, most probable under the PEM, or worst outcome first."""

MAX_LISTED = 100
"""Rollouts offered in the rollout list (the table below it lists every one)."""

MAX_ROWS = 200
"""Rows of the rollouts table (a larger table slows every update of the page; the groups cover every failure)."""

MAX_GROUPS = 8
"""Groups of failures shown, largest share first (the rest summed in one row)."""


def format_share(share: float | None) -> str:
    """A share of p as a percentage with three significant digits, ``-`` for none."""
    return "-" if share is None else f"{100 * share:.3g} %"


def group_heading(record: PanelRun) -> tuple[str, str]:
    """The rollouts table's group column of ``record``: (heading, the start of each group's label that the heading
    says), from its drawing (:meth:`pemviz.app.drawing.PanelDrawing.group_heading`); else ``group``."""
    heading = getattr(record.view.drawing if record.view is not None else None, "group_heading", None)
    return heading() if callable(heading) else ("group", "")


def _unsaid(label: str, said: str) -> str:
    """``label`` without ``said``, which its column's heading says."""
    return label.replace(said, "") if said else label


def groups_html(pop: Population | None) -> str:
    """The groups of failures, largest share of p first (at most :data:`MAX_GROUPS`, the rest in one row), with what
    they share; empty without a population."""
    if pop is None or not pop.groups:
        return ""
    shown, rest = pop.groups[:MAX_GROUPS], pop.groups[MAX_GROUPS:]
    rows = "".join(
        f"<tr><td style='text-align:left'>{html.escape(g.label)}</td><td>{g.count:,}</td>"
        f"<td>{format_share(g.share)}</td></tr>"
        for g in shown
    )
    if rest:
        rows += (
            f"<tr><td style='text-align:left'>{len(rest)} more groups</td><td>{sum(g.count for g in rest):,}</td>"
            f"<td>{format_share(sum(g.share for g in rest))}</td></tr>"
        )
    return (
        f"<b>Groups of failures</b> by {html.escape(pop.basis)} ({len(pop.groups)} groups; shares add up to 100 %):"
        '<table class="pemviz-table" style="width:100%"><tr><th>group</th><th>failures</th><th>share of p</th></tr>'
        f"{rows}</table>"
    )


class RolloutsTab:
    """The *Rollouts* tab: owns its list, order, filter and table, the run it lists (:attr:`listed`, the one chosen
    under *Runs*), its rollouts' labels and severities; a chosen rollout goes to the :class:`pemviz.app.scene_view
    .SceneView` it is given."""

    def __init__(self, client: viser.ClientHandle, lock: threading.RLock, scene: SceneView) -> None:
        self.client, self.lock, self.scene = client, lock, scene
        self.listed: PanelRun | None = None
        """The run whose rollouts the Rollouts tab lists and Explain explains: the one chosen under Runs (a new run
        chooses itself)."""
        self._severities: dict[tuple[int, str], Severity] = {}
        self._rollout_labels: dict[str, Trajectory] = {}

    def build(self) -> None:
        """Add the list, its order and filter and the table to the tab open in ``client.gui``."""
        gui = self.client.gui
        self.rollout_dropdown = gui.add_dropdown(
            "rollout",
            (NO_ROLLOUT,),
            initial_value=NO_ROLLOUT,
            hint="the most likely failure found, then the rollouts in the order of sort by (the first 100)",
        )
        self.rollout_order = gui.add_dropdown(
            "sort by",
            ROLLOUT_ORDERS,
            initial_value=ROLLOUT_ORDERS[0],
            hint="importance weight: the largest share of p first; robustness: least robust first; log p: the "
            "largest log-likelihood under the PEM first; severity: worst first",
        )
        self.failures_only = gui.add_checkbox("failures only", False, hint="list only the rollouts that failed")
        self.rollout_html = gui.add_html(box("No rollouts yet: run an experiment.", GREY))
        self.rollout_dropdown.on_update(lambda _: self._on_rollout_chosen(self.rollout_dropdown.value))
        for handle in (self.rollout_order, self.failures_only):
            handle.on_update(lambda _: self._relist())

    @staticmethod
    def rollout_label(
        t: Trajectory, most_likely: bool = False, sev: Severity | None = None, share: float | None = None
    ) -> str:
        """The rollout list entry (no rank in it, so a chosen rollout stays chosen while later stages re-rank); the
        outcome in :attr:`pemviz.core.drawing.Outcome.short`'s words when ``sev`` is given; a failure's share of p
        when known."""
        outcome = f" · {sev.short}" if sev is not None and (t.crashed or sev.failed) else (" · failed" * t.crashed)
        head = "most likely failure · " if most_likely else ""
        part = f" · {share:.3g} of p" if share is not None else ""
        return (
            f"{head}stage {t.stage} rollout {t.index}{part} · rho {t.robustness:+.4g} · log p {t.log_p_total:.1f}"
            f"{outcome}"
        )

    def severity_of(self, record: PanelRun, t: Trajectory) -> Severity:
        """The severity of a listed rollout (computed once per rollout): the outcome of its scenario's drawing object
        (:meth:`pemviz.core.drawing.Drawing.outcome`, the words the recording shows), else (no drawing, or rows
        without the columns it reads) failed or safe by its robustness."""
        key = (record.run_id, t.key)
        if key not in self._severities:
            drawing = record.view.drawing if record.view is not None else None
            told: Severity = RobustnessOutcome(t.robustness, t.crashed)
            if drawing is not None:
                try:
                    told = cast(Drawing, drawing).outcome(t.batch, 0)
                except ValueError:  # not the scenario's own columns (a rollout file of another problem)
                    pass
            self._severities[key] = told
        return self._severities[key]

    @staticmethod
    def shares_of(record: PanelRun) -> dict[str, float]:
        """Rollout key -> the share of p it carries, for every failure of the run's final estimate (empty before)."""
        pop = record.population
        if pop is None:
            return {}
        share = pop.shares.share()
        return {t.key: float(share[rank]) for rank, t in enumerate(pop.rollouts) if t is not None}

    def ordered_rollouts(self, record: PanelRun) -> list[Trajectory]:
        """The rollouts the tab lists, in its order (``sort by``), failures only if ticked: every failure of the
        run's final estimate (:attr:`PanelRun.population`) and the other stages' kept least-robust rollouts, or
        before it the kept least-robust ones; ``importance weight`` puts the largest share of p first."""
        with record.lock:
            kept, pop = list(record.trajectories), record.population
        if pop is not None:
            failures = [t for t in pop.rollouts if t is not None]
            listed = {t.key for t in failures}
            kept = failures + sorted((t for t in kept if t.key not in listed), key=lambda t: t.robustness)
        if self.failures_only.value:
            kept = [t for t in kept if t.crashed]
        order = self.rollout_order.value
        if order == "log p":
            return sorted(kept, key=lambda t: -t.log_p_total)
        if order == "severity":
            return sorted(kept, key=lambda t: -self.severity_of(record, t).rank)
        if order == "robustness" or pop is None:
            return sorted(kept, key=lambda t: t.robustness)  # sorted() is stable: kept order on ties
        return kept  # importance weight: the population's order, then the safe ones least robust first

    def _relist(self) -> None:
        with self.lock:
            if self.listed is not None:
                self.set_rollouts(self.listed)

    def list_run(self, record: PanelRun) -> None:
        """Rollouts and Explain follow ``record`` (the run chosen under Runs): its rollouts, and its most likely
        failure explained once it has ended."""
        with self.lock:
            if record is self.listed:
                return
            self.listed = record
            self.set_rollouts(record)
            if record.done:
                self.show_default_rollout(record)
                if self.scene.shown_record is not record:
                    self.scene.clear(f"{record.short_label} ({record.status}) has no rollout to show")
            else:
                self.scene.clear(f"{record.short_label} is going: its rollouts appear in the Rollouts tab")

    def set_rollouts(self, record: PanelRun) -> None:
        """List ``record``'s rollouts (when it is the run listed): the dropdown and the table."""
        if record is not self.listed:
            return  # another run is chosen under Runs
        with record.lock:
            best = record.most_likely_failure
            n_kept = len(record.trajectories)
            pop = record.population
        trajectories = self.ordered_rollouts(record)
        shares = self.shares_of(record)
        labels = {}
        if best is not None:
            labels[self.rollout_label(best, True, self.severity_of(record, best), shares.get(best.key))] = best
        labels.update(
            {
                self.rollout_label(t, sev=self.severity_of(record, t), share=shares.get(t.key)): t
                for t in trajectories[:MAX_LISTED]
            }
        )
        self._rollout_labels = labels
        current = self.rollout_dropdown.value
        self.rollout_dropdown.options = (NO_ROLLOUT, *labels)
        if current not in labels:
            set_value(self.rollout_dropdown, NO_ROLLOUT)
        if not n_kept and pop is None:
            self.rollout_html.content = box(f"No rollouts of {html.escape(record.short_label)} yet.", GREY)
            return
        best_text = (
            f"Most likely failure found: stage {best.stage} rollout {best.index} (the failing rollout with the "
            f"largest log p under the PEM; {best.log_p_words()}), {self.severity_of(record, best).short}."
            if best is not None
            else "No failure found yet."
        )

        def outcome(t: Trajectory) -> str:
            sev = self.severity_of(record, t)
            return f"<b style=color:{RED}>{html.escape(sev.short)}</b>" if t.crashed else html.escape(sev.short)

        heading, said = group_heading(record)
        group = {} if pop is None else {t.key: pop.group_label(r) for r, t in enumerate(pop.rollouts) if t is not None}
        rows = "".join(
            f"<tr><td>{i + 1}</td><td>{t.stage}</td><td>{t.index}</td>"
            f"<td>{format_share(shares.get(t.key))}</td><td>{t.robustness:+.4g}</td>"
            f"<td>{t.log_p_total:.1f}</td><td style='text-align:left'>{outcome(t)}</td>"
            f"<td style='text-align:left'>{html.escape(_unsaid(group.get(t.key, '-'), said))}</td></tr>"
            for i, t in enumerate(trajectories[:MAX_ROWS])
        )
        which = " that failed" if self.failures_only.value else ""
        if pop is None:
            what = (
                f"The {n_kept} least robust rollouts of {html.escape(record.short_label)}{which} (metric "
                f"{record.config.metric}; every failure of the estimate is listed once the run has "
                "it)"
            )
        else:
            n_pop = pop.shares.n
            listed = sum(t is not None for t in pop.rollouts)
            safe = f", then the run's {n_kept} least robust rollouts outside it"
            missing = (
                f" (the {listed:,} with the largest shares listed; a streamed stage keeps a sample, and the "
                f"panel at most {MAX_POPULATION:,})"
                if listed < n_pop
                else ""
            )
            what = (
                f"Every failure of the final estimate of {html.escape(record.short_label)}: {n_pop:,}{missing}"
                f"{safe}"
            )
        self.rollout_html.content = TABLE_STYLE + (
            f'<div style="margin:0 0.6em 0.5em; font-size:0.8em">{html.escape(best_text)}<br>'
            + groups_html(pop)
            + f"{what}, by {html.escape(self.rollout_order.value)}; share: the fraction of p the failure carries "
            "(its importance weight over the failures'); log p: log-likelihood under the PEM over T - 1 steps, "
            "nats: the log-probability of the detections plus, where the detector mislocates, the log-density of "
            "the measurement errors (a density: it can exceed 0)"
            + (f"; the list above holds the first {MAX_LISTED}" if len(trajectories) > MAX_LISTED else "")
            + (
                f"; the table the first {MAX_ROWS:,} of {len(trajectories):,} (the groups cover every failure)"
                if len(trajectories) > MAX_ROWS
                else ""
            )
            + ':<div style="max-height:22em; overflow-y:auto"><table class="pemviz-table" style="width:100%">'
            "<tr><th>#</th><th>stage</th><th>rollout</th><th>share of p</th><th>robustness</th><th>log p</th>"
            f"<th>outcome</th><th>{html.escape(heading)}</th></tr>"
            f"{rows}</table></div></div>"
        )

    def show_default_rollout(self, record: PanelRun) -> None:
        """After a run: choose its most likely failure (else its least-robust rollout), paused at the start."""
        if record is not self.listed:
            return
        for label, t in self._rollout_labels.items():
            if t is record.most_likely_failure or record.most_likely_failure is None:
                if self.rollout_dropdown.value == label:  # the same label (an identical run): no callback
                    self._on_rollout_chosen(label)
                else:
                    set_value(self.rollout_dropdown, label)
                return

    def after_run(self, record: PanelRun) -> None:
        """A run ended without finishing (stopped, failed): explain its most likely failure, or say it ended."""
        if record is not self.listed or self.scene.shown_record is record:
            return
        self.set_rollouts(record)
        self.show_default_rollout(record)
        if self.scene.shown_record is not record:
            self.scene.clear(
                f"{record.short_label} {'was stopped' if record.status == 'cancelled' else 'failed'} after "
                f"{len(record.stages)} stages, before any rollout to show"
            )

    def _on_rollout_chosen(self, label: str) -> None:
        traj = self._rollout_labels.get(label)
        if traj is None:
            return
        with self.lock:
            assert self.listed is not None  # the labels are those of the run listed (set_rollouts)
            self.scene.show(self.listed, traj)
