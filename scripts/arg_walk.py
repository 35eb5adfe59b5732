"""Where a command's parsed arguments travel: every call of a pemviz function that takes the command's
``argparse.Namespace`` as one of its arguments (a *stay*), in call order, grouped into visits of its module (a *room*:
consecutive stays in the same module are one visit); a *climb back* is a visit to a module the arguments had already
left. A run whose outputs are planned once from the arguments, then handed down as a plan, visits few rooms and
climbs back rarely; one that checks its output paths piece by piece between steps of the run goes back and forth.

Found by running the command in this process under :func:`sys.setprofile` (a quick run by default), not by reading
the source: what is counted is what happened.

    python scripts/arg_walk.py                                   # pemviz run --preset quick --no-record --json ...
    python scripts/arg_walk.py -- run --preset quick --no-record # any pemviz command line after --
    python scripts/arg_walk.py --config                          # and the run's config made from them
    python scripts/arg_walk.py --config --distinct               # each function once: the call graph's walk

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


LOOKUPS = ("get_method", "method_or_none")
"""The method registry's look-ups by name."""


@dataclass
class Walk:
    """The stays of one command's arguments: ``(module path under pemviz/, function)`` in call order."""

    stays: list[tuple[str, str]] = field(default_factory=list)
    lookups: list[tuple[str, str]] = field(default_factory=list)
    """Each look-up of a method by its name (``pemviz.methods.get_method`` or ``method_or_none``), by its caller."""

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


def walk(argv: list[str], config: bool = False) -> tuple[Walk, int]:
    """Run ``pemviz <argv>`` in this process and follow its parsed arguments (and, with ``config``, every
    :class:`pemviz.config.ExperimentConfig` made after them: the run's settings as the config carries them on);
    ``(the walk, the exit status)``."""
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
        if code.co_name in LOOKUPS and code.co_filename.replace("\\", "/").endswith("/pemviz/methods/__init__.py"):
            caller = frame.f_back.f_code if frame.f_back is not None else code
            result.lookups.append((caller.co_filename.replace("\\", "/").split("/pemviz/")[-1], caller.co_name))
        names = code.co_varnames[: code.co_argcount + code.co_kwonlyargcount]
        values = [frame.f_locals.get(name) for name in names]
        if found["args"] is None:  # the command's arguments: the first Namespace that carries its function
            found["args"] = next(
                (v for v in values if isinstance(v, argparse.Namespace) and getattr(v, "func", None)), None
            )
        args = found["args"]
        held = [v for n, v in zip(names, values, strict=True) if n != "self"]  # the config's own methods: not a stay
        made = config and any(type(v).__name__ == "ExperimentConfig" for v in held)
        carried = args is not None and (made or any(v is args for v in held))
        if carried:
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


def distinct(w: Walk) -> Walk:
    """The walk with each ``(module, function)`` kept at its first stay only: the call graph the arguments go down,
    each edge once, as a reading of the source would follow them (the repeated calls of a loop not counted)."""
    seen: set[tuple[str, str]] = set()
    return Walk([s for s in w.stays if not (s in seen or seen.add(s))], sorted(set(w.lookups)))


def main() -> int:
    given = sys.argv[1:]
    argv = given[given.index("--") + 1 :] if "--" in given else None
    mine = given[: given.index("--")] if "--" in given else given
    with tempfile.TemporaryDirectory() as folder:
        w, status = walk(argv or default_argv(folder), config="--config" in mine)
    w = distinct(w) if "--distinct" in mine else w
    print(w.summary() + f"; the method looked up by name {len(w.lookups)} times")
    for module, names in w.visits:
        print(f"  {module}: {', '.join(names)}")
    for module, name in w.lookups:
        print(f"  look-up by name from {module}: {name}")
    return status


if __name__ == "__main__":
    sys.exit(main())
