"""Where ``pemviz run`` sends its recording: rerun's script flags with ``--no-record``, the target asked for, the viewer
check of ``--connect`` and the default name. Only :func:`serve` imports rerun."""

from __future__ import annotations

import argparse
import socket
import sys
from datetime import datetime
from pathlib import Path
from urllib.parse import quote, urlsplit

from pemviz.commands import UsageError
from pemviz.config import ExperimentConfig
from pemviz.io.files import free_default_path

DEFAULT_VIEWER_URL = "rerun+http://127.0.0.1:9876/proxy"
CONNECT_TIMEOUT_S = 3.0


def add_recording_args(p: argparse.ArgumentParser) -> None:
    """rerun's standard script flags (those of ``rerun.script_add_args``: --save, --serve, --connect, --url, --stdout,
    --headless, defined here so that the parser needs no rerun import) plus ``--no-record`` and the ports of
    ``--serve``."""
    rec = p.add_argument_group("recording (rerun's standard script flags; at most one of them)")
    rec.add_argument(
        "--stdout",
        action="store_true",
        help="write the recording to standard output, to be piped into a rerun viewer (... | rerun -)",
    )
    rec.add_argument(
        "--save",
        metavar="PATH.rrd",
        help="write the recording to this file "
        "(default recordings/<scenario>-<method>-<preset>-<metric>-<sim>-seed<seed>-<time>.rrd)",
    )
    rec.add_argument(
        "--serve",
        action="store_true",
        help="serve the recording over gRPC and a web viewer, print both addresses, keep serving until Ctrl-C",
    )
    rec.add_argument(
        "--connect",
        nargs="?",
        const=True,
        default=False,
        metavar="URL",
        help=f"stream to a running rerun viewer (default URL {DEFAULT_VIEWER_URL}; or give it with --url)",
    )
    rec.add_argument("--url", help="the viewer for --connect, e.g. rerun+http://127.0.0.1:9876/proxy")
    rec.add_argument("--headless", action="store_true", help="open no browser (with --serve)")
    rec.add_argument("--grpc-port", dest="grpc_port", type=int, default=9876, help="--serve: gRPC port (default 9876)")
    rec.add_argument(
        "--web-port", dest="web_port", type=int, default=9090, help="--serve: web viewer port (default 9090)"
    )
    rec.add_argument("--no-record", action="store_true", help="write no recording")


def recording_target(args: argparse.Namespace) -> str:
    """Which one of save / serve / connect / stdout / none the flags ask for (default: save).

    Raises:
        UsageError: two of them at once, a port without --serve, or a bad port."""
    if isinstance(args.connect, str):  # --connect URL
        if args.url is not None and args.url != args.connect:
            raise UsageError(f"--connect {args.connect} and --url {args.url}: give the viewer URL once")
        args.url = args.connect
    if args.url is not None:
        args.connect = True
    chosen = [
        flag
        for flag, on in (
            ("--save", args.save is not None),
            ("--serve", args.serve),
            ("--connect", bool(args.connect)),
            ("--stdout", args.stdout),
            ("--no-record", args.no_record),
        )
        if on
    ]
    if len(chosen) > 1:
        raise UsageError(f"{' and '.join(chosen)} cannot be combined: choose one place for the recording")
    for flag, port, default in (("--grpc-port", args.grpc_port, 9876), ("--web-port", args.web_port, 9090)):
        if port != default and not args.serve:
            raise UsageError(f"{flag} {port}: only with --serve")
        if not 1 <= port <= 65535:
            raise UsageError(f"{flag} {port}: not a port (1..65535)")
    return chosen[0].lstrip("-") if chosen else "save"


def probe_viewer(url: str | None, timeout_s: float = CONNECT_TIMEOUT_S) -> str:
    """Check that a rerun viewer listens at ``url`` (default :data:`DEFAULT_VIEWER_URL`) before any work.

    Returns:
        The URL.

    Raises:
        UsageError: not a ``rerun+http(s)://HOST:PORT/...`` URL, or nothing answers within ``timeout_s``."""
    url = url or DEFAULT_VIEWER_URL
    scheme: str | None
    host: str | None
    port: int | None
    try:
        parts = urlsplit(url)
        scheme, host, port = parts.scheme, parts.hostname, parts.port
    except ValueError:  # e.g. a port that is not a number
        scheme = host = port = None
    if not (scheme or "").startswith("rerun") or not host or port is None:
        raise UsageError(f"--connect {url}: not a rerun viewer URL (expected e.g. {DEFAULT_VIEWER_URL})")
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except OSError as exc:
        reason = f"no answer within {timeout_s:g} s" if isinstance(exc, TimeoutError) else (exc.strerror or str(exc))
        raise UsageError(
            f"--connect {url}: no rerun viewer there ({reason.lower()}); "
            "start one with `rerun`, or use --serve or --save"
        ) from None
    return url


def web_viewer_url(grpc_url: str, web_port: int) -> str:
    """The address of rerun's web viewer that opens the gRPC stream ``grpc_url``."""
    return f"http://127.0.0.1:{web_port}/?url={quote(grpc_url, safe='')}"


def default_recording_path(cfg: ExperimentConfig, preset: str, folder: Path = Path("recordings")) -> Path:
    """``recordings/<scenario>-<method>-<preset>-<metric>-<sim>-seed<seed>-<time>.rrd``: the name says what ran; a name
    already taken (two runs in one second) gets ``-2``, ``-3``, ... so a default name never collides."""
    return free_default_path(
        folder,
        f"{cfg.scenario}-{cfg.method}-{preset}-{cfg.metric}-{cfg.sim}-seed{cfg.seed}-"
        f"{datetime.now():%Y%m%d-%H%M%S}",
    )


def serve(args: argparse.Namespace):
    """A sink serving gRPC on ``--grpc-port`` and rerun's web viewer on ``--web-port``; prints both addresses."""
    import rerun as rr

    from pemviz.sinks.recording import RerunSink

    sink = RerunSink.to_grpc(serve=True, grpc_port=args.grpc_port)
    url = sink.serve_url or f"rerun+http://127.0.0.1:{args.grpc_port}/proxy"
    rr.serve_web_viewer(web_port=args.web_port, open_browser=not args.headless, connect_to=url)
    print(f"recording: serving at {url} (native viewer: rerun {url})", file=sys.stderr)
    print(f"recording: web viewer at {web_viewer_url(url, args.web_port)}", file=sys.stderr)
    print(
        "warning: rerun's servers listen on every network interface, without authentication",
        file=sys.stderr,
        flush=True,
    )
    return sink
