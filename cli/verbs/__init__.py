"""One module per ``glossrig`` verb, discovered automatically.

The verb's name is the module name (``_`` -> ``-``); modules whose name starts with
``_`` are not verbs (helpers, or sub-verbs kept in a module of their own such as
``_design_exposures``). A verb module defines ``HELP`` (one line; its docstring is the
``--help`` description) and either

* ``add_arguments(parser)`` and ``run(args) -> int``: a verb without sub-verbs; or
* ``SUBVERBS``: a sequence of :class:`SubVerb`, for a verb with sub-verbs
  (``calibrate camera``, ``design coverage``, ``model fit``). Each sub-verb has a
  name, a one-line help, its own ``add_arguments(parser)`` and ``run(args) -> int``,
  and optionally a longer description for its ``--help``; they are listed in the
  order given. ``SUBVERB_METAVAR`` (default ``"SUBVERB"``) names the sub-verb in
  the verb's usage line. :func:`add_subverbs` builds the sub-parsers and makes the
  chosen sub-verb's ``run`` the one that runs; nothing else is needed.

Adding a sub-verb is one more :class:`SubVerb` in its verb's ``SUBVERBS``; a sub-verb
that lives in a module of its own (defining ``HELP``, ``add_arguments`` and ``run``
like a verb) is listed with :meth:`SubVerb.from_module`. ``glossrig.cli.main`` adds
``-v``/``-q`` and the help formatter (defaults shown) to every parser, sub-verbs
included.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class SubVerb:
    """One sub-verb of a verb (``glossrig VERB NAME ...``)."""

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    description: str | None = None     # the sub-verb's --help description (none if not given)

    @classmethod
    def from_module(cls, name: str, module, description: str | None = None) -> SubVerb:
        """A sub-verb from a module that defines ``HELP``, ``add_arguments`` and ``run``."""
        return cls(name, module.HELP, module.add_arguments, module.run, description)


def add_subverbs(parser: argparse.ArgumentParser, subverbs: Sequence[SubVerb], metavar: str = "SUBVERB") -> None:
    """Add ``subverbs`` (required: one must be named) below ``parser``; the chosen
    sub-verb's ``run`` becomes ``args._run``, what ``glossrig.cli.main`` calls."""
    sub = parser.add_subparsers(dest="subverb", metavar=metavar, required=True)
    for sv in subverbs:
        p = sub.add_parser(sv.name, help=sv.help, description=sv.description)
        sv.add_arguments(p)
        p.set_defaults(_run=sv.run)
