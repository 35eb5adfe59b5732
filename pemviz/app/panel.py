"""The viser server of ``pemviz serve``: one :class:`pemviz.app.session.Session` per browser client (its own form,
runs, Stop, plots and 3D scene; a client that leaves has its run stopped). The server holds what the sessions share:
the recordings folder, the scenario's constants, run numbers, a warm-up run and one player thread that steps every
session's playback and status line."""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable
from pathlib import Path

import viser

from pemviz.app.drawing import LanePanel, lane_panel, scenario_drawing
from pemviz.app.session import Session
from pemviz.config import ExperimentConfig
from pemviz.engine import experiment
from pemviz.presets import DEFAULT_PRESET, PRESETS
from pemviz.scenarios import registry
from pemviz.scenarios.problems import problem_for
from pemviz.sinks.colours import BLUE

STATUS_EVERY_S = 0.5
"""How often a running run's status line (elapsed, expected time) is refreshed."""


def idle_drawing(scenario: str) -> LanePanel:
    """The drawing object of the lane scene every session builds first: ``scenario``'s at its defaults where it
    draws one (:func:`pemviz.app.drawing.lane_panel`), else the first registered scenario's that does; a session
    then shows its chosen scenario's idle scene.

    Raises:
        ValueError: no registered scenario draws a lane scene."""
    for name in (scenario, *registry.registered()):
        drawing = lane_panel(scenario_drawing(name))
        if drawing is not None:
            return drawing
    raise ValueError(f"no registered scenario draws a lane scene for the panel's idle scene ({scenario!r} does not)")


class PanelApp:
    """The ``pemviz serve`` application: a viser server and one session per connected client.

    Args:
        host: interface to bind (``127.0.0.1``: this machine only).
        port: TCP port (0: any free port; see :attr:`port`).
        recordings_dir: where exports are written (created on the first export).
        config: the form's initial values (default: ``preset``'s settings).
        preset: the preset the form starts with, one of :data:`pemviz.presets.PRESETS`.
        pem: the PEM the form starts with (None: the shipped default), without ``config``.
        warm_up: import the simulator and run a tiny experiment in the background.
        verbose: let viser print its banner.

    Raises:
        ValueError: an unknown ``preset``."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 8080,
        *,
        recordings_dir: str | Path = "recordings",
        config: ExperimentConfig | None = None,
        preset: str = DEFAULT_PRESET,
        pem: str | None = None,
        warm_up: bool = True,
        verbose: bool = False,
    ) -> None:
        if preset not in PRESETS:
            raise ValueError(f"preset {preset!r} is invalid: use one of {', '.join(PRESETS)}")
        self.preset_name = preset
        self.config0 = config or ExperimentConfig.of(**PRESETS[preset], pem=pem)
        self.recordings_dir = Path(recordings_dir)
        self.drawing: LanePanel = idle_drawing(self.config0.scenario)
        """The lane scene every session builds first (:func:`idle_drawing`), before it draws the chosen scenario's
        idle scene; each run's own scene, thresholds and stages come with its first event
        (:class:`pemviz.app.runs.PanelRun`)."""
        self.host = host
        self.lock = threading.RLock()
        self.sessions: dict[int, Session] = {}
        """Client id -> its session, for the clients connected now."""
        self._run_ids = itertools.count(1)
        self._closed = threading.Event()
        self._session_added = threading.Condition(self.lock)

        self.server = viser.ViserServer(host=host, port=port, label="pemviz", verbose=verbose)
        self.server.gui.configure_theme(control_width="large", show_share_button=False, brand_color=BLUE)
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)
        self._warm = threading.Thread(target=self._warm_up, name="pemviz-warm-up", daemon=True)
        if warm_up:
            self._warm.start()
        self._player = threading.Thread(target=self._play_loop, name="pemviz-player", daemon=True)
        self._player.start()

    # == public API ====================================================================================
    @property
    def port(self) -> int:
        """The port the server actually bound."""
        return int(self.server.get_port())

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def next_run_id(self) -> int:
        """Run numbers are unique across the server's sessions (labels and export names never clash)."""
        with self.lock:
            return next(self._run_ids)

    def wait_for_session(self, known: set[int], timeout: float = 60.0) -> Session:
        """Block until a client not in ``known`` (client ids) has its session built; return it.

        Raises:
            TimeoutError: none within ``timeout`` seconds."""
        end = time.monotonic() + timeout
        with self._session_added:
            while True:
                new = [s for cid, s in self.sessions.items() if cid not in known]
                if new:
                    return new[0]
                left = end - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no new browser session within {timeout} s")
                self._session_added.wait(left)

    def wait_warm(self) -> None:
        if self._warm.is_alive():
            self._warm.join()

    def close(self) -> None:
        """Cancel every session's run, wait for them (up to 10 s in all) and stop the server."""
        self._closed.set()
        with self.lock:
            sessions = list(self.sessions.values())
        for s in sessions:
            s.close()
        end = time.monotonic() + 10.0
        for s in sessions:
            s.wait_for_run(max(0.0, end - time.monotonic()))
        self.server.stop()

    # == sessions ======================================================================================
    def _on_connect(self, client: viser.ClientHandle) -> None:
        session = Session(self, client)
        with self._session_added:
            self.sessions[client.client_id] = session
            self._session_added.notify_all()

    def _on_disconnect(self, client: viser.ClientHandle) -> None:
        with self.lock:
            session = self.sessions.pop(client.client_id, None)
        if session is not None:
            session.close()

    def _warm_up(self) -> None:
        """Import the simulator and run torch once, so that the first real run is not slowed by them."""
        try:
            tiny = ExperimentConfig.of(
                n_stages=1, n_per_stage=2, n_final=1, ce_epochs=1, pretrain_rollouts=1, pretrain_epochs=1
            )
            experiment.Experiment(tiny, [], self._closed, problem=problem_for(tiny)).run()
        except Exception:  # warming up is best effort; a real run reports its own errors
            pass

    def _play_loop(self) -> None:
        dt = self.drawing.dt_s
        every = max(1, round(STATUS_EVERY_S / dt))
        for tick in itertools.count():
            if self._closed.wait(dt):
                return
            with self.lock:
                sessions = list(self.sessions.values())
            for s in sessions:
                try:
                    s.play_tick()
                    if tick % every == 0:
                        s.tick()
                except Exception:  # a client that is going away; the next tick sees it gone
                    continue


def serve(
    host: str = "127.0.0.1",
    port: int = 8080,
    *,
    recordings_dir: str | Path = "recordings",
    preset: str = DEFAULT_PRESET,
    pem: str | None = None,
    on_ready: Callable[[PanelApp], None] | None = None,
) -> None:
    """Run the panel until Ctrl-C (what ``pemviz serve`` does), its form starting at ``preset`` and ``pem``.

    Raises:
        ValueError: an unknown ``preset``."""
    app = PanelApp(host, port, recordings_dir=recordings_dir, preset=preset, pem=pem)
    try:
        if on_ready is not None:
            on_ready(app)
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        app.close()
