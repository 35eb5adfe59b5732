"""A method's settings field and its row of the settings table (:func:`setting`): what a settings dataclass of a method
(:attr:`pemviz.methods.Method.settings`, or the cross-entropy sampler's group
:class:`pemviz.methods.adaptive.CrossEntropySettings`) is made of. Imports nothing of pemviz, so that a method's
settings module (:mod:`pemviz.methods.state`) can be imported by the registry that names it."""

from __future__ import annotations

import dataclasses
from typing import Any

ROW = "pemviz.setting"
"""The key of a method's setting's row in its dataclass field's metadata (:func:`setting`)."""


def setting(default: Any, words: str, help: str, **row: Any) -> Any:
    """A field of a method's settings dataclass (:attr:`pemviz.methods.Method.settings`, or a built-in method's group
    such as :class:`pemviz.methods.adaptive.CrossEntropySettings`) and its row of the settings table
    (:class:`pemviz.settings.Setting`): ``default``, then what the row says of it (``words``, ``help`` and any of
    ``kind``, ``symbol``, ``short``, ``unit``, ``lo``, ``hi``, ``lo_open``, ``hi_open``, ``optional``, ``choices``,
    ``choice_help``, ``flags``, ``panel``: the place of a built-in method's setting in the panel's form); the field's
    name is the setting's (and the key a run records it by), the method's name its owner."""
    return dataclasses.field(default=default, metadata={ROW: {"words": words, "help": help, **row}})
