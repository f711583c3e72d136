"""Reproducible studies and benchmarks (not shipped with the package).

A package so that studies share their small library by normal imports
(:mod:`validation.common`: the ``glossrig`` command runner and the calibrated-twin
chain; :mod:`validation.provenance`; :mod:`validation.paths`): run a study from the
repository root as a module, e.g. ``python -m validation.diagnose.rgl_study --work W``.
"""
