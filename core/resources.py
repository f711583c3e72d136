"""Where glossrig's own data files are, and how a path option finds one (design.md:
"scenes ship as package data; a path option resolves against the current folder first,
then the packaged scenes").

The repository's ``scenes/`` folder (rig descriptions, ``materials/``, ``plans/``, the
engraver) is installed as the package ``glossrig.scenes`` (``pyproject.toml``), so an
installed glossrig - a wheel, not only the editable checkout - has them, and
:func:`scenes_dir` finds them through :mod:`importlib.resources` wherever the package
lives. :func:`resolve_input` is the one rule every rig, plan and machine-file option
follows, so ``--rig scenes/thesis_rig.toml``, ``--rig thesis_rig.toml`` and
``--plan plans/twin_small.toml`` work from any folder, and a user's own file of the same
name in the current folder wins.
"""
from __future__ import annotations

from importlib import resources
from pathlib import Path

from glossrig.core.errors import InputError

#: the package the ``scenes/`` folder is installed as
SCENES_PACKAGE = "glossrig.scenes"


def scenes_dir() -> Path:
    """The folder of the packaged scenes (``scenes/`` of the checkout in an editable
    install, ``site-packages/glossrig/scenes`` in a wheel install)."""
    try:
        root = resources.files(SCENES_PACKAGE)
    except ModuleNotFoundError:          # running from a checkout that is not installed
        return Path(__file__).resolve().parent.parent / "scenes"
    # glossrig is installed as plain files (never zipped), so the traversable is a folder.
    return Path(str(root))


def _packaged_candidates(p: Path) -> list[Path]:
    """Where a relative path may lie among the packaged scenes: under the scenes folder
    as given (``thesis_rig.toml``, ``plans/twin_small.toml``), and ``scenes/REL`` as
    written in the README and in the plans, with the checkout's ``scenes/`` prefix dropped."""
    base = scenes_dir()
    out = [base / p]
    if p.parts and p.parts[0] == "scenes" and len(p.parts) > 1:
        out.append(base / Path(*p.parts[1:]))
    return out


def resolve_input(value: str | Path, what: str, *, first: list[Path] | tuple[Path, ...] = (),
                  named: str | Path | None = None) -> Path:
    """The existing file a user's path option names, resolved.

    An absolute path is taken as it is. A relative one is looked for in the folders of
    ``first`` (e.g. next to the plan file that names a rig), then in the current folder,
    then among the packaged scenes (:func:`scenes_dir`; ``scenes/NAME`` also matches the
    packaged ``NAME``). When none exists: ``InputError`` naming ``named`` (default: the
    value; e.g. the plan file that names a rig), ``what`` (e.g. ``"rig file"``) and every
    place looked in. An absolute path that does not exist is returned unchanged, so the
    reader reports it as missing with its own message."""
    p = Path(value).expanduser()
    if p.is_absolute():
        return p
    looked = [Path(b) / p for b in first] + [Path.cwd() / p] + _packaged_candidates(p)
    for c in looked:
        if c.is_file():
            return c.resolve()
    places = ", ".join(str(c) for c in dict.fromkeys(looked))
    raise InputError(f"{what} not found (looked in: {places})", path=value if named is None else named)


def packaged_reference(path: str | Path) -> str | None:
    """``scenes/REL`` when ``path`` is a packaged scene file, else None: a reference to it
    that :func:`resolve_input` finds from any folder, in the checkout and installed alike."""
    try:
        rel = Path(path).resolve().relative_to(scenes_dir().resolve())
    except ValueError:
        return None
    return str(Path("scenes") / rel)


def package_version() -> str:
    """glossrig's version: the installed distribution's (:mod:`importlib.metadata`), or,
    for a checkout run without installing, the ``version`` of its ``pyproject.toml``;
    ``"unknown"`` when neither can be read."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("glossrig")
    except PackageNotFoundError:
        pass
    import tomllib

    try:
        with open(Path(__file__).resolve().parent.parent / "pyproject.toml", "rb") as f:
            return str(tomllib.load(f)["project"]["version"])
    except (OSError, KeyError, tomllib.TOMLDecodeError):
        return "unknown"
