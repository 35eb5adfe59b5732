"""``pemviz data fetch | where``: download the KITTI salient files (SHA-256 checked) or show where they are."""

from __future__ import annotations

import argparse
import sys

from pemviz.commands import UsageError, add_command
from pemviz.io import data

DESCRIPTION = """
The KITTI salient files are never shipped: fetch them or show where pemviz finds them.
"""
"""``pemviz data --help``'s description."""


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``pemviz data`` and its actions ``fetch`` and ``where`` to the sub-command parsers ``sub``."""
    p = add_command(sub, "data", DESCRIPTION)
    actions = p.add_subparsers(dest="data_command", required=True)
    f = actions.add_parser(
        "fetch",
        help="download the four files and check their SHA-256",
        description=f"Download the salient files from {data.ORIGIN_BASE_URL} into the user cache "
        f"({data.user_cache_dir()}) or --dest, checking each SHA-256; a bad download writes nothing.",
    )
    f.add_argument("--dest", metavar="DIR", help="target folder (default: the user cache)")
    f.add_argument(
        "--base-url",
        default=data.ORIGIN_BASE_URL,
        metavar="URL",
        help="folder URL to fetch <URL>/<file> from (default: the public origin)",
    )
    f.add_argument("--force", action="store_true", help="download even files that are present and correct")
    f.set_defaults(func=fetch_main)
    w = actions.add_parser(
        "where",
        help="print the folder pemviz reads the files from, and check their SHA-256",
        description="Search $PEMVIZ_DATA_DIR, ../shared/data/kitti-salient and the user cache, in that order.",
    )
    w.set_defaults(func=where_main)


def fetch_main(args: argparse.Namespace) -> int:
    """``pemviz data fetch``: download the salient files and check their SHA-256.

    Returns:
        The exit status: 0, or 1 after one error line when a download or its check fails (nothing written).

    Raises:
        UsageError: ``--base-url`` is not an http(s):// or file:// URL."""
    if not args.base_url.startswith(("http://", "https://", "file://")):
        raise UsageError(f"--base-url {args.base_url!r}: must be an http(s):// or file:// URL")
    try:
        folder = data.fetch(
            args.dest,
            args.base_url,
            force=args.force,
            on_file=lambda name, status: print(f"  {name}: {status}, SHA-256 ok"),
        )
    except (data.DataError, OSError) as exc:
        print(f"pemviz data fetch: error: {exc}", file=sys.stderr)
        return 1
    print(f"salient files in {folder}")
    return 0


def where_main(args: argparse.Namespace) -> int:
    """``pemviz data where``: print the data folder found and each file's SHA-256 check.

    Returns:
        The exit status: 0, or 1 when no data folder is found or a file does not match its SHA-256."""
    try:
        folder = data.find_data_dir()
    except data.DataNotFoundError as exc:
        print(f"pemviz data where: error: {exc}", file=sys.stderr)
        return 1
    print(folder)
    status = 0
    for name, expected in data.FILE_SHA256.items():
        path = folder / name
        if not path.is_file():
            print(f"  {name}: absent")
            continue
        ok = data.sha256_file(path) == expected
        print(f"  {name}: SHA-256 {'ok' if ok else 'MISMATCH (run `pemviz data fetch --force`)'}")
        status = status if ok else 1
    return status
