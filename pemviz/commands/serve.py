"""``pemviz serve``: the interactive analysis panel in the browser (viser)."""

from __future__ import annotations

import argparse
import sys


def register(sub: argparse._SubParsersAction) -> None:
    from pemviz.app.runs import PANEL_PRESETS
    from pemviz.config import DEFAULT_PRESET

    p = sub.add_parser(
        "serve",
        help="open the interactive panel in the browser (viser)",
        description=(
            "Serve the pemviz panel: set metric, alpha, sigma, K, N, N_e, seed and PEM, run the adaptive "
            "sampler, watch the proposal adapt, replay the least-robust rollouts in 3D, compare up to 3 "
            "runs and export them to recordings/*.rrd."
        ),
    )
    p.add_argument("--host", default="127.0.0.1", help="interface to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=8080, help="TCP port (default 8080; the next free one if taken)")
    p.add_argument("--preset", default=DEFAULT_PRESET,
                   help=f"initial settings: {', '.join(PANEL_PRESETS)} (default {DEFAULT_PRESET})")
    p.add_argument("--recordings", default="recordings", help="folder for exported .rrd files (default recordings)")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from pemviz.app.runs import PANEL_PRESETS
    from pemviz.commands import UsageError

    if args.preset not in PANEL_PRESETS:
        raise UsageError(f"--preset {args.preset!r} is invalid: use one of {', '.join(PANEL_PRESETS)}")
    if not 0 <= args.port <= 65535:
        raise UsageError(f"--port {args.port} is invalid: use 0..65535")

    from pemviz.app.panel import serve

    def ready(app) -> None:
        print(f"pemviz serve: open {app.url} (Ctrl-C to stop)", flush=True)

    serve(args.host, args.port, recordings_dir=args.recordings, preset=args.preset, on_ready=ready)
    print("pemviz serve: stopped", file=sys.stderr)
    return 0
