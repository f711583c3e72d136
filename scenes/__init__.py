"""The rig, material, plan and engraver descriptions as package data (``glossrig.scenes``).

This folder holds data, not code: the file only makes it a package, so that an installed
glossrig ships these TOML files and finds them through :mod:`importlib.resources`
(:func:`glossrig.core.resources.scenes_dir`).
"""
