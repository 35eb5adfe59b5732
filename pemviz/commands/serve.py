"""``pemviz serve``: the interactive analysis panel in the browser (viser)."""

from __future__ import annotations

import argparse
import ipaddress
import os
import socket
import sys
from typing import cast

from pemviz.commands import UsageError, add_command, add_setting, pem_argument
from pemviz.presets import DEFAULT_PRESET, PRESETS, preset_help

DESCRIPTION = """
Serve the pemviz panel: set metric, alpha, sigma, K, N, N_e, seed and PEM (--pem: the one it starts with), run the
adaptive sampler, watch the proposal adapt, replay the least-robust rollouts in 3D, compare up to 4 runs and export
them to recordings/*.rrd.
"""
"""``pemviz serve --help``'s description."""


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``pemviz serve`` and its flags to the sub-command parsers ``sub``."""
    p = add_command(sub, "serve", DESCRIPTION)
    p.add_argument("--host", default="127.0.0.1", help="interface to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=8080, help="TCP port (default 8080; the next free one if taken)")
    p.add_argument(
        "--preset",
        default=DEFAULT_PRESET,
        help=f"the form's initial settings, one of {', '.join(PRESETS)} (default {DEFAULT_PRESET}): "
        f"{preset_help()}",
    )
    add_setting(p, "pem")
    p.add_argument("--recordings", default="recordings", help="folder for exported .rrd files (default recordings)")
    p.set_defaults(func=main)


def check_host(host: str) -> bool:
    """Check that ``host`` is an address of this machine (resolve it and bind a socket to it on a free port).

    Returns:
        True for a loopback-only address (127.0.0.0/8, ::1, ``localhost``); False for any other (``0.0.0.0``,
        ``''`` and ``::`` bind every interface).
    Raises:
        UsageError: the name does not resolve or is not an address of this machine."""
    if host in ("", "0.0.0.0", "::"):
        return False
    try:
        infos = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError, ValueError) as exc:
        raise UsageError(f"--host {host!r}: not an address or a name that resolves ({exc})") from None
    for family, kind, proto, _, addr in infos:
        try:
            with socket.socket(family, kind, proto) as sock:
                sock.bind(addr)
        except OSError as exc:
            raise UsageError(
                f"--host {host!r}: not an address of this machine ({exc.strerror or exc}); use "
                "127.0.0.1 (this machine only) or an interface address"
            ) from None
    # an IPv4 / IPv6 address: its host a str
    return all(ipaddress.ip_address(cast(str, addr[0]).split("%")[0]).is_loopback for *_, addr in infos)


def main(args: argparse.Namespace) -> int:
    """``pemviz serve``: serve the viser panel until Ctrl-C (a warning line where ``--host`` reaches other machines).

    Returns:
        The exit status, 0.

    Raises:
        UsageError: an unknown preset, a port outside 0..65535, or a bad PEM."""
    if args.preset not in PRESETS:
        raise UsageError(f"--preset {args.preset!r} is invalid: use one of {', '.join(PRESETS)}")
    if not 0 <= args.port <= 65535:
        raise UsageError(f"--port {args.port} is invalid: use 0..65535")
    pem = pem_argument(args.pem)
    if pem is not None:  # read it now, as pemviz run does: a bad file is refused before the panel serves
        from pemviz.pem import load_pem

        load_pem(pem)
    if not check_host(args.host):
        print(
            f"pemviz serve: warning: --host {args.host!r} is reachable from other machines and the panel has no "
            "authentication: anyone who reaches it can run experiments and write recordings",
            file=sys.stderr,
        )

    def ready(app) -> None:
        print(f"pemviz serve: open {app.url} (Ctrl-C to stop)", flush=True)

    from pemviz.app import panel  # viser and the panel: ~1.9 s to import, paid only by this command

    panel.serve(args.host, args.port, recordings_dir=args.recordings, preset=args.preset, pem=pem, on_ready=ready)
    print("pemviz serve: stopped", file=sys.stderr)
    if sys.argv[1:2] == ["serve"]:  # the program itself (not pemviz.cli.main called from Python)
        sys.stdout.flush()
        sys.stderr.flush()
        # Every export is already committed (atomic writes). Leave without interpreter teardown: a native worker
        # thread still alive then aborts the process ("terminate called without an active exception", about 1
        # stop in 10 under load), which would turn a clean Ctrl-C into exit status -6.
        os._exit(0)
    return 0
