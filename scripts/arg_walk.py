"""Where a command's parsed arguments travel: every call of a pemviz function that takes the command's
``argparse.Namespace`` as one of its arguments (a *stay*), in call order, grouped into visits of its module (a *room*:
consecutive stays in the same module are one visit); a *climb back* is a visit to a module the arguments had already
left. A run whose outputs are planned once from the arguments, then handed down as a plan, visits few rooms and
climbs back rarely; one that checks its output paths piece by piece between steps of the run goes back and forth.

Found by running the command in this process under :func:`sys.setprofile` (a quick run by default), not by reading
the source: what is counted is what happened.

    python scripts/arg_walk.py                                   # pemviz run --preset quick --no-record --json ...
    python scripts/arg_walk.py -- run --preset quick --no-record # any pemviz command line after --

Prints one line of counts, then each visit with its stays. Exit status: the command's.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any

REPO = Path(__file__).resolve().parents[1]


@dataclass
class Walk:
    """The stays of one command's arguments: ``(module path under pemviz/, function)`` in call order."""

    stays: list[tuple[str, str]] = field(default_factory=list)

    @property
    def visits(self) -> list[tuple[str, list[str]]]:
        """The rooms in visit order, each with the functions of its stays (consecutive stays in one module: one)."""
        out: list[tuple[str, list[str]]] = []
        for module, name in self.stays:
            if out and out[-1][0] == module:
                out[-1][1].append(name)
            else:
                out.append((module, [name]))
        return out

    @property
    def rooms(self) -> int:
        return len({module for module, _ in self.stays})

    @property
    def climbs_back(self) -> int:
        """Visits to a module the arguments had already been in and left."""
        seen: set[str] = set()
        climbs = 0
        for module, _ in self.visits:
            climbs += module in seen
            seen.add(module)
        return climbs

    def summary(self) -> str:
        return (
            f"{len(self.stays)} stays in {self.rooms} rooms ({len(self.visits)} visits), climbing back "
            f"{self.climbs_back} times"
        )


def walk(argv: list[str]) -> tuple[Walk, int]:
    """Run ``pemviz <argv>`` in this process and follow its parsed arguments; ``(the walk, the exit status)``."""
    sys.path.insert(0, str(REPO))
    from pemviz import cli

    found: dict[str, Any] = {"args": None}
    result = Walk()

    def profile(frame: FrameType, event: str, arg: object) -> None:
        if event != "call":
            return
        code = frame.f_code
        if "/pemviz/" not in code.co_filename.replace("\\", "/"):
            return
        names = code.co_varnames[: code.co_argcount + code.co_kwonlyargcount]
        values = [frame.f_locals.get(name) for name in names]
        if found["args"] is None:  # the command's arguments: the first Namespace that carries its function
            found["args"] = next(
                (v for v in values if isinstance(v, argparse.Namespace) and getattr(v, "func", None)), None
            )
        args = found["args"]
        if args is not None and any(v is args for v in values):
            module = code.co_filename.replace("\\", "/").split("/pemviz/", 1)[1]
            result.stays.append((module, code.co_name))

    sys.setprofile(profile)
    try:
        status = cli.main(list(argv))
    finally:
        sys.setprofile(None)
    return result, int(status or 0)


def default_argv(folder: str) -> list[str]:
    """A quick run that writes a result document into ``folder`` (the outputs are what the walk follows)."""
    return ["run", "--preset", "quick", "--no-record", "--json", str(Path(folder) / "run.json")]


def main() -> int:
    given = sys.argv[1:]
    argv = given[given.index("--") + 1 :] if "--" in given else None
    with tempfile.TemporaryDirectory() as folder:
        w, status = walk(argv or default_argv(folder))
    print(w.summary())
    for module, names in w.visits:
        print(f"  {module}: {', '.join(names)}")
    return status


if __name__ == "__main__":
    sys.exit(main())
