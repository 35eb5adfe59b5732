"""Sub-commands of the ``pemviz`` command line; each module exposes ``register(subparsers)``."""


class UsageError(Exception):
    """A bad command-line value: printed as one line, exit status 2, nothing written."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (``timeout``, CI, containers), raised where Python runs, handled like Ctrl-C: the command
    finishes what can be finished (a recording marked interrupted), says so in one line, exit status 143."""


def interrupted(exc: KeyboardInterrupt, done: str) -> KeyboardInterrupt:
    """The same interrupt (Ctrl-C or :class:`Terminated`) carrying what the command finished, for the one line
    the command line prints."""
    return type(exc)(done)
