"""The top-level ``glossrig`` package (installed from ``cli/toplevel``, ``pyproject.toml``).

It holds only what belongs to the package as a whole: ``__version__`` and
``python -m glossrig`` (``__main__.py``). The code lives in the subpackages mapped from
the repository's top-level folders: ``glossrig.core``, ``glossrig.twin``,
``glossrig.hardware``, ``glossrig.cli`` and the data package ``glossrig.scenes``.
"""
from glossrig.core.resources import package_version as _package_version

__version__ = _package_version()
