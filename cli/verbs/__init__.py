"""One module per ``glossrig`` verb, discovered automatically.

A verb module defines ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``. Verbs with sub-verbs (``calibrate camera``) add their own
sub-parsers in ``add_arguments`` and set ``func`` defaults; ``run`` then
dispatches to ``args.func``. The verb's name is the module name (``_`` -> ``-``).
"""
