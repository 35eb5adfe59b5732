"""The *Explain* tab of a :class:`pemviz.app.session.Session`: the rollout shown in the 3D scene, step by step."""

from __future__ import annotations

import html

import viser

from pemviz.app import explain_charts, plots
from pemviz.app import objects_view as OV
from pemviz.app.captions import show_chart
from pemviz.app.drawing import LaneExplanation, LanePanel
from pemviz.app.html import GREEN, GREY, RED, TABLE_STYLE, box, explanation_html
from pemviz.app.objects_view import ObjectsExplanation, explain_objects, objects_summary
from pemviz.app.runs import PanelRun, Trajectory


def _proposal_html(ox: ObjectsExplanation, traj: Trajectory, t: int) -> str:
    """Each object's q(detect) and p(detect) at step ``t`` and its chart; empty where the rollout has none."""
    if traj.object_p is None:
        return ""
    assert traj.object_q is not None  # set with object_p (pemviz.app.runs.trajectory)
    return (
        f"<div><b>Each object's proposal</b>: q(detect) of the sampler (blue), "
        f"p(detect) of the PEM (grey, "
        f"dashed), 0 to 1 in its band; at step {t}: "
        + html.escape(
            ", ".join(
                f"{ox.names[j]} q {traj.object_q[t, j]:.3g} p {traj.object_p[t, j]:.3g}"
                for j in range(traj.object_p.shape[1])
            )
        )
        + "</div>"
        + OV.detect_svg(ox.names, traj.object_p, traj.object_q, t)
    )


class ExplainTab:
    """The *Explain* tab: owns its charts and HTML and the explanation of the rollout shown, :attr:`explanation` (a
    lane scene) or :attr:`objects_ex` (a scene of several objects); the 3D scene (:class:`pemviz.app.scene_view
    .SceneView`) chooses the rollout and the step."""

    def __init__(self, client: viser.ClientHandle, strip_title: str = "distance and speeds") -> None:
        self.client, self.strip_title = client, strip_title
        self.explanation: LaneExplanation | None = None
        """The shown rollout's explanation in a lane scene (None: none shown, or one of several objects)."""
        self.objects_ex: ObjectsExplanation | None = None
        """The shown rollout's explanation when its scene has several objects (then :attr:`explanation` is None)."""

    def build(self) -> None:
        """Add the tab's HTML and charts to the tab open in ``client.gui``."""
        gui = self.client.gui
        self.explain_html = gui.add_html(box("Choose a rollout in the Rollouts tab to explain it.", GREY))
        self.strip = plots.strip_plots(gui, self.strip_title)
        self.strip["controller"] = explain_charts.controller_plot(gui, order=self.strip["gap"].order + 0.5)
        # a rollout of several objects: car 0's gap and lateral offset, truth and tracker, and the controller (hidden
        # until one with a story is shown), then the decisive errors, every car's events and the scene from above
        self.object_plots = explain_charts.object_plots(gui)
        self.objects_html = gui.add_html("")

    def explain_lane(self, traj: Trajectory, drawing: LanePanel) -> LaneExplanation:
        """Explain a rollout of a lane scene (its strip charts shown, those of several objects hidden); fill them with
        :meth:`fill`."""
        self.objects_ex = None
        self.show_strips(True)
        self.explanation = drawing.lane_explanation(traj.batch, 0)
        return self.explanation

    def explain_objects(self, record: PanelRun, traj: Trajectory) -> ObjectsExplanation:
        """Explain a rollout of a scene of several objects (:mod:`pemviz.app.objects_view`): the lane scene's strip
        charts are hidden meanwhile, the tracker and controller charts
        (:func:`pemviz.app.explain_charts.fill_object_plots`) shown where the drawing tells the rollout's story."""
        ox = explain_objects(record.problem, record.view, traj.batch, traj.crashed)
        self.objects_ex, self.explanation = ox, None
        self.show_strips(False)
        if ox.story is not None:
            explain_charts.fill_object_plots(self.object_plots, ox, 0, f"{record.short_label} {traj.name}")
        return ox

    def show_strips(self, visible: bool) -> None:
        """Show the lane scene's strip charts or hide them (several objects); the charts and details of several objects
        are hidden with a lane scene's rollout and until a rollout of several objects fills them."""
        for plot in self.strip.values():
            show_chart(plot, visible)
        explain_charts.hide_object_plots(self.object_plots)
        if visible:
            self.objects_html.content = ""

    def hide_unused(self) -> None:
        """Hide the charts and details of several objects while no rollout of several objects is explained."""
        if self.objects_ex is None:
            with self.client.atomic():
                explain_charts.hide_object_plots(self.object_plots)
                self.objects_html.content = ""

    def fill(self, record: PanelRun, traj: Trajectory, drawing: LanePanel) -> None:
        """Fill the strip charts, the controller's chart and the text of the lane scene's rollout explained."""
        ex = self.explanation
        if ex is None:
            return
        title = f"{record.short_label} {traj.name}"
        assert record.view is not None  # its drawing drew the lane scene
        plots.fill_strip_plots(
            self.strip,
            drawing.strip_series(traj.batch, 0),
            traj.detected,
            ex,
            0,
            title,
            record.view.thresholds,
            drawing.panel_scene().strip_title,
        )
        explain_charts.fill_controller_plot(self.strip["controller"], ex, 0, title)
        self.explain_html.content = explanation_html(record, traj, ex, title, drawing.dt_s)

    def move_marker(self, step: int) -> None:
        """Move the strip charts' marker to ``step`` of the lane scene's rollout shown."""
        plots.move_strip_marker(self.strip, step)

    def render_objects(self, record: PanelRun, traj: Trajectory, t: int) -> None:
        """The tab at step ``t`` of the shown rollout of several objects: its header, the decisive errors, every
        object's events and the scene from above."""
        ox = self.objects_ex
        if ox is None:
            return
        what = (
            "the most likely failure found"
            if traj is record.most_likely_failure
            else ("a failure" if traj.crashed else "no failure")
        )
        head = (
            f"<b>{html.escape(record.short_label)} {traj.name}</b>: {what} · robustness {traj.robustness:+.4g} "
            f"({record.config.metric}) · under the PEM (every object): {html.escape(traj.log_p_words())}"
        )
        why = f"<b>Which errors decided it</b> (each undone alone, replayed): {html.escape(objects_summary(ox))}"
        story = OV.story_html(ox) or (
            "No story: this scene's drawing tells none of this rollout, so neither its "
            "tracker nor its controller is charted."
        )
        legend = (
            f"<span style='color:{OV.GREEN}'>&#9632; detected</span> <span style='color:{OV.ORANGE}'>&#9632; "
            f"missed</span> <span style='color:{OV.UNSEEN}'>&#9632; unseen</span> <span style='color:{OV.RED}'>"
            f"&#9632; decisive</span> <span style='color:{OV.BLUE}'>&#9679; measured; dashed: the noise PEM's "
            f"{OV.ELLIPSE_SCALES:g}-scale ellipse</span> <span style='color:{OV.TRACK}'>&#9633; the tracker's "
            "estimate</span>"
        )
        body = (
            TABLE_STYLE
            + '<div style="margin:0 0.6em; font-size:0.8em">'
            + OV.decisive_table(ox)
            + f"<div><b>Every object, step by step</b> · {html.escape(OV.state_counts(ox, t))}</div>"
            + OV.raster_svg(ox, t)
            + _proposal_html(ox, traj, t)
            + f"<div><b>From above at step {t}</b> (the road runs right; the ego's right is down)</div>"
            + OV.birds_eye_svg(ox, t)
            + f"<div>{legend}</div></div>"
        )
        with self.client.atomic():
            self.explain_html.content = box(f"{head}<br>{story}<br>{why}", RED if traj.crashed else GREEN)
            self.objects_html.content = body
            if ox.story is not None:
                plots.move_strip_marker(self.object_plots, t)

    def clear(self, why: str) -> None:
        """No rollout explained: say ``why``."""
        self.explanation, self.objects_ex = None, None
        self.explain_html.content = box(html.escape(why), GREY)
