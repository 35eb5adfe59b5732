"""Count the functions of a package longer than a limit (lines from ``def`` to the last line of the body,
decorators not counted), the measure the developers' guide caps.

    python scripts/long_functions.py                 # pemviz/, over 80 lines
    python scripts/long_functions.py --over 60 pemviz/app

Prints one row per long function (lines, place, name), longest first, then the count. Exit status 0.
"""

from __future__ import annotations

import argparse
import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def long_functions(root: Path, over: int) -> list[tuple[int, str, str]]:
    """``(lines, "path:line", name)`` for every function or method under ``root`` longer than ``over`` lines."""
    rows = []
    for path in sorted(root.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = (node.end_lineno or node.lineno) - node.lineno + 1
                if length > over:
                    rows.append((length, f"{path.relative_to(REPO)}:{node.lineno}", node.name))
    return sorted(rows, reverse=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", nargs="?", default=str(REPO / "pemviz"), help="folder to scan (default pemviz/)")
    parser.add_argument("--over", type=int, default=80, help="line limit (default 80)")
    args = parser.parse_args()
    rows = long_functions(Path(args.root).resolve(), args.over)
    for length, place, name in rows:
        print(f"{length:4d}  {place}  {name}")
    print(f"{len(rows)} functions over {args.over} lines")


if __name__ == "__main__":
    main()
