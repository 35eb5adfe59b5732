"""Sub-commands of the ``pemviz`` command line; each module exposes ``register(subparsers)``."""


class UsageError(Exception):
    """A bad command-line value: printed as one line, exit status 2, nothing written."""
