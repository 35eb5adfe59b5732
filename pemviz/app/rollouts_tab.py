"""The *Rollouts* tab of a :class:`pemviz.app.session.Session`: the chosen run's kept rollouts, sorted and filtered, and
the explanation of the one chosen."""

from __future__ import annotations

import html

import numpy as np

from pemviz.app import charts, plots
from pemviz.app import objects_view as OV
from pemviz.app.explain import explain
from pemviz.app.html import (
    GREEN,
    GREY,
    NO_ROLLOUT,
    RED,
    TABLE_STYLE,
    box,
    explanation_html,
)
from pemviz.app.objects_view import RobustnessOutcome, explain_objects, objects_summary
from pemviz.app.runs import MAX_POPULATION, PanelRun, Population, Trajectory, scene_positions
from pemviz.scenarios.braking_failures import Severity, severity


MAX_LISTED = 100
"""Rollouts offered in the rollout list (the table below it lists every one)."""

MAX_ROWS = 200
"""Rows of the rollouts table (a larger table slows every update of the page; the groups cover every failure)."""

SAVING = "last saving detection at "
"""Dropped from a group's label in the rollouts table (its column says it: ``last saving detection``)."""

MAX_GROUPS = 8
"""Groups of failures shown, largest share first (the rest summed in one row)."""


def format_share(share: float | None) -> str:
    """A share of p as a percentage with three significant digits, ``-`` for none."""
    return "-" if share is None else f"{100 * share:.3g} %"


def groups_html(pop: Population | None) -> str:
    """The groups of failures, largest share of p first (at most :data:`MAX_GROUPS`, the rest in one row), with what
    they share; empty without a population."""
    if pop is None or not pop.groups:
        return ""
    shown, rest = pop.groups[:MAX_GROUPS], pop.groups[MAX_GROUPS:]
    rows = "".join(f"<tr><td style='text-align:left'>{html.escape(g.label)}</td><td>{g.count:,}</td>"
                   f"<td>{format_share(g.share)}</td></tr>" for g in shown)  # fmt: skip
    if rest:
        rows += (f"<tr><td style='text-align:left'>{len(rest)} more groups</td><td>{sum(g.count for g in rest):,}</td>"
                 f"<td>{format_share(sum(g.share for g in rest))}</td></tr>")  # fmt: skip
    return (
        f"<b>Groups of failures</b> by {html.escape(pop.basis)} ({len(pop.groups)} groups; shares add up to 100 %):"
        '<table class="pemviz-table" style="width:100%"><tr><th>group</th><th>failures</th><th>share of p</th></tr>'
        f"{rows}</table>"
    )


class RolloutsTab:
    """The *Rollouts* tab's part of a session (a mixin of :class:`pemviz.app.session.Session`)."""

    @staticmethod
    def rollout_label(t: Trajectory, most_likely: bool = False, sev: Severity | None = None,
                      share: float | None = None) -> str:  # fmt: skip
        """The rollout list entry (no rank in it, so a chosen rollout stays chosen while later stages re-rank); the
        outcome in :attr:`Severity.short`'s words when ``sev`` is given; a failure's share of p when known."""
        outcome = f" · {sev.short}" if sev is not None and (t.crashed or sev.failed) else (" · failed" * t.crashed)
        head = "most likely failure · " if most_likely else ""
        part = f" · {share:.3g} of p" if share is not None else ""
        return (
            f"{head}stage {t.stage} rollout {t.index}{part} · rho {t.robustness:+.4g} · log p {t.log_p_total:.1f}"
            f"{outcome}"
        )

    def severity_of(self, record: PanelRun, t: Trajectory) -> Severity | RobustnessOutcome:
        """The severity of a listed rollout (computed once per rollout): the braking scenario's, else failed or safe
        by its robustness."""
        key = (record.run_id, t.key)
        if key not in self._severities:
            braking = record.view is not None and record.view.scene is not None
            self._severities[key] = severity(t.gap_m, self.params) if braking else RobustnessOutcome(t.robustness,
                                                                                                      t.crashed)
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
        """The rollouts the Rollouts tab lists, in its order (``sort by``), failures only if ticked: once the run has
        its final estimate, every failure of it (:attr:`PanelRun.population`) and the kept least-robust rollouts of
        other stages; before, the kept least-robust rollouts. ``importance weight``: the largest share of p first (the
        rollouts outside the estimate, which carry none, last, least robust first)."""
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
                self._set_rollouts(self.listed)

    def _set_rollouts(self, record: PanelRun) -> None:
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
        labels.update({self.rollout_label(t, sev=self.severity_of(record, t), share=shares.get(t.key)): t
                       for t in trajectories[:MAX_LISTED]})  # fmt: skip
        self._rollout_labels = labels
        current = self.rollout_dropdown.value
        self.rollout_dropdown.options = (NO_ROLLOUT, *labels)
        if current not in labels:
            self.rollout_dropdown.value = NO_ROLLOUT
        if not n_kept and pop is None:
            self.rollout_html.content = box(f"No rollouts of {html.escape(record.short_label)} yet.", GREY)
            return
        best_text = (
            f"Most likely failure found: stage {best.stage} rollout {best.index}, log p_PEM = "
            f"{best.log_p_total:.1f} nats (the failing rollout most probable under the PEM), "
            f"{self.severity_of(record, best).short}."
            if best is not None
            else "No failure found yet."
        )

        def outcome(t: Trajectory) -> str:
            sev = self.severity_of(record, t)
            return f"<b style=color:{RED}>{html.escape(sev.short)}</b>" if t.crashed else html.escape(sev.short)

        group = {} if pop is None else {t.key: pop.group_label(r) for r, t in enumerate(pop.rollouts) if t is not None}
        rows = "".join(
            f"<tr><td>{i + 1}</td><td>{t.stage}</td><td>{t.index}</td>"
            f"<td>{format_share(shares.get(t.key))}</td><td>{t.robustness:+.4g}</td>"
            f"<td>{t.log_p_total:.1f}</td><td style='text-align:left'>{outcome(t)}</td>"
            f"<td style='text-align:left'>{html.escape(group.get(t.key, '-').replace(SAVING, ''))}</td></tr>"
            for i, t in enumerate(trajectories[:MAX_ROWS])
        )
        which = " that failed" if self.failures_only.value else ""
        if pop is None:
            what = (f"The {n_kept} least robust rollouts of {html.escape(record.short_label)}{which} (metric "
                    f"{record.config.metric}; every failure of the estimate is listed once the run has "
                    "it)")  # fmt: skip
        else:
            n_pop = pop.shares.n
            listed = sum(t is not None for t in pop.rollouts)
            safe = f", then the run's {n_kept} least robust rollouts outside it"
            missing = (f" (the {listed:,} with the largest shares listed; a streamed stage keeps a sample, and the "
                       f"panel at most {MAX_POPULATION:,})" if listed < n_pop else "")  # fmt: skip
            what = (f"Every failure of the final estimate of {html.escape(record.short_label)}: {n_pop:,}{missing}"
                    f"{safe}")  # fmt: skip
        self.rollout_html.content = TABLE_STYLE + (
            f'<div style="margin:0 0.6em 0.5em; font-size:0.8em">{html.escape(best_text)}<br>'
            + groups_html(pop)
            + f"{what}, by {html.escape(self.rollout_order.value)}; share: the fraction of p the failure carries "
            "(its importance weight over the failures'); log p: log-probability under the PEM, nats"
            + (f"; the list above holds the first {MAX_LISTED}" if len(trajectories) > MAX_LISTED else "")
            + (f"; the table the first {MAX_ROWS:,} of {len(trajectories):,} (the groups cover every failure)"
               if len(trajectories) > MAX_ROWS else "")
            + ':<div style="max-height:22em; overflow-y:auto"><table class="pemviz-table" style="width:100%">'
            "<tr><th>#</th><th>stage</th><th>rollout</th><th>share of p</th><th>robustness</th><th>log p</th>"
            f"<th>outcome</th><th>{'last saving detection' if record.view and record.view.scene else 'group'}</th></tr>"
            f"{rows}</table></div></div>"
        )

    def _show_default_rollout(self, record: PanelRun) -> None:
        """After a run: choose its most likely failure (else its least-robust rollout), paused at the start."""
        if record is not self.listed:
            return
        for label, t in self._rollout_labels.items():
            if t is record.most_likely_failure or record.most_likely_failure is None:
                if self.rollout_dropdown.value == label:  # the same label (an identical run): no callback
                    self._on_rollout_chosen(label)
                else:
                    self.rollout_dropdown.value = label
                return

    def _after_run(self, record: PanelRun) -> None:
        """A run ended without finishing (stopped, failed): explain its most likely failure, or say it ended."""
        if record is not self.listed or self.shown_record is record:
            return
        self._set_rollouts(record)
        self._show_default_rollout(record)
        if self.shown_record is not record:
            self._clear_scene(
                f"{record.short_label} {'was stopped' if record.status == 'cancelled' else 'failed'} after "
                f"{len(record.stages)} stages, before any rollout to show"
            )

    def _on_rollout_chosen(self, label: str) -> None:
        traj = self._rollout_labels.get(label)
        if traj is None:
            return
        with self.lock:
            record = self.listed or self.record
            scene = record.view.scene if record is not None and record.view is not None else None
            if scene is None:
                if traj.batch is not None and record.view.objects_xy is not None:  # a scene of several objects
                    self._show_objects(record, traj)
                return  # else a problem without a scene (a toy): nothing to replay
            self.objects_ex = None
            self._show_strips(True)
            self._scene_kind(0)
            self.explanation = explain(traj.gap_m, traj.detected, traj.log_p, traj.log_q, scene)
            self.shown = traj
            self.shown_record = record
            self._shown_x = scene_positions(traj, scene)
            self.step_slider.max = traj.n_steps - 1
            self._set_playing(False)
            self._fill_explanation()
            self._place_rollout()
            self.shown_step = -1
            if self.step_slider.value != 0:
                self.step_slider.value = 0  # renders step 0 through the slider's callback
            else:
                self._render_step(0)

    def _show_objects(self, record: PanelRun, traj: Trajectory) -> None:
        """Explain a rollout of a scene of several objects (:mod:`pemviz.app.objects_view`), paused at its first
        decisive step (else step 0); the braking scenario's strip charts are hidden meanwhile, the cut-in's tracker
        and ACC charts (:func:`pemviz.app.charts.fill_object_plots`) shown where the rollout tells its story."""
        ox = explain_objects(record.problem, record.view, traj.batch, traj.crashed)
        self.objects_ex, self.explanation = ox, None
        self.shown, self.shown_record, self._shown_x = traj, record, None
        self.step_slider.max = traj.n_steps - 1
        self._set_playing(False)
        self.shown_step = -1
        self._show_strips(False)
        if ox.story is not None:
            charts.fill_object_plots(self.object_plots, ox, 0, f"{record.short_label} {traj.key}")
        self._scene_kind(ox.detected.shape[1])
        self._frame_objects()
        self.scene_html.content = box(
            f"Scene: {html.escape(record.short_label)} {traj.key}, every car seen from the ego (blue-grey): green "
            "detected, orange missed, grey unseen. Explain draws them from above with where each was measured.", GREY
        )
        decisive = ox.counterfactuals.decisive if ox.counterfactuals is not None else ()
        first = decisive[0].step if decisive else 0
        if self.step_slider.value != first:
            self.step_slider.value = first  # renders it through the slider's callback
        else:
            self._render_step(first)

    def _show_strips(self, visible: bool) -> None:
        """Show the braking scenario's strip charts (a braking rollout) or hide them (several objects); the cut-in's
        charts and details are hidden with a braking rollout and until a rollout of several objects fills them."""
        for plot in self.strip.values():
            plot.visible = visible
        charts.hide_object_plots(self.object_plots)
        if visible:
            self.objects_html.content = ""

    def _render_objects(self, step: int) -> None:
        """*Explain* at ``step`` of the shown rollout of several objects: its header, the decisive errors, every
        object's events and the scene from above."""
        traj, ox, record = self.shown, self.objects_ex, self.shown_record
        if traj is None or ox is None or record is None:
            return
        t = int(np.clip(step, 0, traj.n_steps - 1))
        self.shown_step = t
        what = ("the most likely failure found" if traj is record.most_likely_failure
                else ("a failure" if traj.crashed else "no failure"))  # fmt: skip
        head = (f"<b>{html.escape(record.short_label)} {traj.key}</b>: {what} · robustness {traj.robustness:+.4g} "
                f"({record.config.metric}) · log p_PEM {traj.log_p_total:.1f} nats (every object's detections and "
                f"errors)")  # fmt: skip
        why = f"<b>Which errors decided it</b> (each undone alone, replayed): {html.escape(objects_summary(ox))}"
        story = OV.story_html(ox) or ("No story: this scene's rows hold none of the cut-in's tracker and ACC columns, "
                                      "so neither its tracker nor its controller is charted.")  # fmt: skip
        legend = (f"<span style='color:{OV.GREEN}'>&#9632; detected</span> <span style='color:{OV.ORANGE}'>&#9632; "
                  f"missed</span> <span style='color:{OV.UNSEEN}'>&#9632; unseen</span> <span style='color:{OV.RED}'>"
                  f"&#9632; decisive</span> <span style='color:{OV.BLUE}'>&#9679; measured; dashed: the noise PEM's "
                  f"{OV.ELLIPSE_SCALES:g}-scale ellipse</span> <span style='color:{OV.TRACK}'>&#9633; the tracker's "
                  "estimate</span>")  # fmt: skip
        body = (
            TABLE_STYLE
            + '<div style="margin:0 0.6em; font-size:0.8em">'
            + OV.decisive_table(ox)
            + f"<div><b>Every object, step by step</b> · {html.escape(OV.state_counts(ox, t))}</div>"
            + OV.raster_svg(ox, t)
            + ("" if traj.object_p is None else
               f"<div><b>Each object's proposal</b>: q(detect) of the sampler (blue), p(detect) of the PEM (grey, "
               f"dashed), 0 to 1 in its band; at step {t}: "
               + html.escape(", ".join(f"{ox.names[j]} q {traj.object_q[t, j]:.3g} p {traj.object_p[t, j]:.3g}"
                                       for j in range(traj.object_p.shape[1])))
               + "</div>" + OV.detect_svg(ox.names, traj.object_p, traj.object_q, t))
            + f"<div><b>From above at step {t}</b> (the road runs right; the ego's right is down)</div>"
            + OV.birds_eye_svg(ox, t)
            + f"<div>{legend}</div></div>"
        )
        with self.client.atomic():
            self.explain_html.content = box(f"{head}<br>{story}<br>{why}", RED if traj.crashed else GREEN)
            self.objects_html.content = body
            if ox.story is not None:
                plots.move_strip_marker(self.object_plots, t)
        self._render_objects_scene(ox, t, f"{record.short_label} {traj.key} step {t}\n{OV.state_counts(ox, t)}")

    def _fill_explanation(self) -> None:
        traj, ex, record = self.shown, self.explanation, self.shown_record
        if traj is None or ex is None or record is None:
            return
        title = f"{record.short_label} {traj.key}"
        plots.fill_strip_plots(self.strip, traj, ex, 0, title, record.view.thresholds)
        charts.fill_controller_plot(self.strip["controller"], ex, 0, title)
        self.explain_html.content = explanation_html(record, traj, ex, title, record.view.scene.dt_s)

