"""``glossrig <verb>``: every module of :mod:`glossrig.cli.verbs` is a verb (its docstring
says what a verb module defines, sub-verbs included)."""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from glossrig.core.errors import GlossrigError
from glossrig.core.resources import package_version

from . import logs, verbs
from .logs import add_verbosity_options


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Every ``--help``: descriptions and examples as written (their line breaks kept), and
    each option's default shown, ``(default: ...)``, unless its help already names it or
    there is none to show (``None``, or ``False`` for a flag)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if action.default is None or action.default is False or "default" in text.lower():
            return text
        return super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="glossrig", formatter_class=HelpFormatter,
        description="Image-based gloss measurement on a cylinder rig, its Mitsuba twin, and gloss fabrication.")
    parser.add_argument("--version", action="version", version=f"glossrig {package_version()}")
    sub = parser.add_subparsers(dest="verb", metavar="VERB", required=True)
    for info in sorted(pkgutil.iter_modules(verbs.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{verbs.__name__}.{info.name}")
        p = sub.add_parser(info.name.replace("_", "-"), help=mod.HELP, description=mod.__doc__,
                           formatter_class=HelpFormatter)
        if hasattr(mod, "SUBVERBS"):
            verbs.add_subverbs(p, mod.SUBVERBS, metavar=getattr(mod, "SUBVERB_METAVAR", "SUBVERB"))
        else:
            mod.add_arguments(p)
            p.set_defaults(_run=mod.run)
        _add_verbosity(p)
        _set_formatter(p)
    return parser


def _set_formatter(p: argparse.ArgumentParser) -> None:
    """:class:`HelpFormatter` on every sub-verb's parser below ``p`` too (``calibrate
    camera``, ``model fit``, ``design ...``): the parsers of
    :func:`glossrig.cli.verbs.add_subverbs` do not inherit their parent's formatter."""
    p.formatter_class = HelpFormatter
    for action in p._actions:
        if (action.help is None and action.option_strings and action.default is not None
                and action.default is not False and action.default is not argparse.SUPPRESS):
            action.help = "default: %(default)s"     # argparse shows nothing for an option without help
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):
                _set_formatter(child)


def _add_verbosity(p: argparse.ArgumentParser, nested: bool = False) -> None:
    """``-v``/``-q`` on a verb's parser and on every sub-verb's below it."""
    add_verbosity_options(p, nested=nested)
    for action in p._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):
                _add_verbosity(child, nested=True)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        with logs.configured(args.verb, verbose=getattr(args, "verbose", False), quiet=getattr(args, "quiet", False)):
            return int(args._run(args) or 0)
    except GlossrigError as e:
        print(f"glossrig {args.verb}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        # An output the up-front checks (glossrig.cli.outputs) could not foresee: one line, not a traceback.
        where = f"{e.filename}: " if e.filename else ""
        print(f"glossrig {args.verb}: error: {where}{e.strerror or e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"glossrig {args.verb}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
