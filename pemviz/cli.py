"""pemviz: estimate the probability of rare safety failures of a perception-driven controller with a perception
error model (PEM) and adaptive importance sampling, recorded for rerun and shown in a browser panel.

Each sub-command lives in ``pemviz/commands/<name>.py`` and exposes ``register(subparsers)``."""

from __future__ import annotations

import argparse
import errno
import functools
import importlib
import os
import signal
import sys
from typing import NoReturn

import pemviz.commands
from pemviz import __version__
from pemviz.commands import COMMANDS, Terminated, UsageError, command_help


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line (``pemviz run: error: argument --k: 'abc' is not a number;
    ...``), exit status 2, without the usage block; an unknown flag gets the nearest known one (``--rel-eror: did
    you mean --rel-error?``)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}{self._nearest(message)}\n")

    def format_help(self) -> str:
        """The help, each action's text that says what is registered (``describe``: the scenarios of ``--scenario``
        and of ``pemviz --help``'s ``run``) read now, when it is shown, not when the parser was built."""
        for action in self._actions:
            choices = action._choices_actions if isinstance(action, argparse._SubParsersAction) else []
            for each in (action, *choices):
                describe = getattr(each, "describe", None)
                if describe is not None:
                    each.help = describe()
        return super().format_help()

    def _flags(self) -> set[str]:
        """Every long flag of this parser and of its commands' parsers."""
        flags: set[str] = set()
        for action in self._actions:
            flags.update(s for s in action.option_strings if s.startswith("--"))
            if isinstance(action, argparse._SubParsersAction):
                for sub in action.choices.values():
                    flags |= sub._flags() if isinstance(sub, OneLineParser) else set()
        return flags

    def _nearest(self, message: str) -> str:
        """``; --rel-eror: did you mean --rel-error?`` for each unknown flag of an ``unrecognized arguments`` message
        with a known flag close to it (:func:`difflib.get_close_matches`); ``""`` otherwise."""
        if not message.startswith("unrecognized arguments:"):
            return ""
        import difflib

        known = sorted(self._flags())
        hints = []
        for word in message.split(":", 1)[1].split():
            flag = word.split("=", 1)[0]
            close = difflib.get_close_matches(flag, known, n=1, cutoff=0.75) if flag.startswith("--") else []
            if close:
                hints.append(f"{flag}: did you mean {close[0]}?")
        return "".join(f"; {h}" for h in hints)


def build_parser(command: str | None = None, *, full: bool = True) -> argparse.ArgumentParser:
    """The ``pemviz`` parser. With ``full`` every command's parser is built (the user guide's reference, the tests);
    without, only ``command``'s, the others listed by their help alone, so that a command imports no other command's
    module and ``pemviz --help`` imports none."""
    parser = OneLineParser(
        prog="pemviz",
        description=__doc__.split("\n\n")[0].replace("\n", " "),
        epilog="`pemviz COMMAND --help` describes a command; the user guide is in docs/ (mkdocs serve).",
    )
    parser.add_argument("--version", action="version", version=f"pemviz {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, (module, help_text) in COMMANDS.items():
        if full or name == command:
            importlib.import_module(module).register(sub)
        else:
            sub.add_parser(name, help=help_text)
    for choice in sub._choices_actions:  # run's help lists the registered scenarios when shown
        choice.describe = functools.partial(command_help, choice.dest)  # type: ignore[attr-defined]
    return parser


_SIGTERM_SEEN: list[bool] = []
"""Non-empty once SIGTERM reached the run: a library that turns the handler's :class:`Terminated` into a plain
``KeyboardInterrupt`` (Ray's ``ray.get`` does while it waits) does not make it read as Ctrl-C."""


def _raise_terminated(signum: int, frame: object) -> None:
    _SIGTERM_SEEN.append(True)
    raise Terminated()


def main(argv: list[str] | None = None) -> int:
    """Run one command; returns the exit status: 0 done; 1 a failure while working (full disk, out of memory), one
    line; 2 bad input, one line, nothing written; 130 Ctrl-C and 143 SIGTERM, one line saying what was finished
    (``PEMVIZ_DEBUG=1``: the traceback). Run as the program (``argv`` None), the process ends as soon as the command
    has (:func:`_exit_now`)."""
    pemviz.commands.AS_PROGRAM = pemviz.commands.AS_PROGRAM or argv is None
    previous = None
    if signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, None):
        try:
            previous = signal.signal(signal.SIGTERM, _raise_terminated)
        except ValueError:  # not the main thread (pemviz called from a worker thread): leave it
            pass
    try:
        status = _run(argv)
    finally:
        if argv is None:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
            executors = sys.modules.get("pemviz.engine.executors")  # os._exit skips atexit: kill the pool's workers
            if executors is not None:
                executors.close_executors()
                __import__("multiprocessing.util").util._run_finalizers(0)  # what atexit does: its semaphores freed
        elif previous is not None:
            signal.signal(signal.SIGTERM, previous)
    if argv is None:
        _exit_now(status)
    return status


def _exit_now(status: int) -> None:
    """End the program with ``status`` once the command has returned (its files committed, its recordings flushed
    and closed), skipping the interpreter's teardown of torch's and rerun's modules and threads; standard output and
    error are flushed first, a closed pipe changing nothing."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(status)


def _interrupt_in(exc: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C / SIGTERM behind ``exc``: itself, or one it was raised from (an import machinery or a
    library can wrap it, e.g. ``RuntimeError`` from ``__set_name__``)."""
    seen = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, KeyboardInterrupt):
            return cur
        seen.add(id(cur))
        cur = cur.__cause__ or cur.__context__
    return None


def _run(argv: list[str] | None) -> int:
    name = "pemviz"
    try:
        words = sys.argv[1:] if argv is None else argv
        command = next((w for w in words if not w.startswith("-")), None)
        args = build_parser(command, full=False).parse_args(argv)
        name = f"pemviz {args.command}"
        return int(args.func(args) or 0)
    except Exception as exc:
        interrupt = _interrupt_in(exc)
        if interrupt is None or os.environ.get("PEMVIZ_DEBUG"):
            return _failure(name, exc)
        return _interrupted(name, interrupt)
    except KeyboardInterrupt as exc:
        if os.environ.get("PEMVIZ_DEBUG"):
            raise
        return _interrupted(name, exc)


def _interrupted(name: str, exc: KeyboardInterrupt) -> int:
    how, code = ("SIGTERM", 143) if isinstance(exc, Terminated) or _SIGTERM_SEEN else ("Ctrl-C", 130)
    done = f"; {exc.args[0]}" if exc.args else "; nothing written"
    print(f"{name}: interrupted ({how}){done}", file=sys.stderr)
    return code


def _failure(name: str, exc: Exception) -> int:
    """One line for bad input (exit 2) or a failure while working (exit 1); anything else is re-raised."""
    if os.environ.get("PEMVIZ_DEBUG"):
        raise exc
    if isinstance(exc, (UsageError, ValueError, FileNotFoundError)):  # bad input: nothing written
        print(f"{name}: error: {exc}", file=sys.stderr)
        return 2
    if isinstance(exc, MemoryError):
        what = "out of memory; nothing partial was left"
    elif isinstance(exc, OSError) and exc.errno in WRITE_ERRNOS:
        where = f" {exc.filename}" if getattr(exc, "filename", None) else ""
        what = f"cannot write{where}: {exc.strerror or exc}; nothing partial was left"
    elif isinstance(exc, OSError):  # a connection refused, a device gone ...
        what = str(exc)
    else:
        raise exc
    print(f"{name}: failed: {what}", file=sys.stderr)
    return 1


WRITE_ERRNOS = {errno.ENOSPC, errno.EFBIG, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EIO}


if __name__ == "__main__":  # python -m pemviz.cli: the program is pemviz.cli's main: it sets commands.AS_PROGRAM
    from pemviz.cli import main as program

    sys.exit(program())
