"""The dependency rule of design.md, enforced: ``core`` imports neither ``twin`` nor
``hardware`` nor ``cli``; ``twin`` and ``hardware`` do not import ``cli``.

Every ``import``/``from`` statement is read from the source with :mod:`ast`, so
imports inside functions (the usual way round such a rule) count too. Relative
imports are resolved against the module's own package.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = {"core": "glossrig.core", "twin": "glossrig.twin", "hardware": "glossrig.hardware", "cli": "glossrig.cli"}
FORBIDDEN = {"core": ("glossrig.twin", "glossrig.hardware", "glossrig.cli"),
             "twin": ("glossrig.cli",), "hardware": ("glossrig.cli",)}


def _imports(path: Path, top: str):
    rel = path.relative_to(ROOT / top).with_suffix("")
    parts = [PACKAGE[top]] + list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    package = parts if path.name == "__init__.py" else parts[:-1]
    package = ".".join(package).split(".")
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node.lineno, a.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            yield node.lineno, name
            for a in node.names:                       # `from glossrig import twin`
                yield node.lineno, f"{name}.{a.name}"


def _violations(top: str) -> list[str]:
    bad = []
    for path in sorted((ROOT / top).rglob("*.py")):
        for line, name in _imports(path, top):
            if any(name == f or name.startswith(f + ".") for f in FORBIDDEN[top]):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    return bad


@pytest.mark.parametrize("top", sorted(FORBIDDEN))
def test_layer_imports_only_downwards(top):
    assert _violations(top) == []


def test_the_checker_sees_a_violation(tmp_path, monkeypatch):
    """The rule would catch a function-level and a relative import of the twin."""
    fake = tmp_path / "core"
    (fake / "sub").mkdir(parents=True)
    (fake / "ok.py").write_text("from glossrig.core.models.ward import ward\n")
    (fake / "sub" / "bad.py").write_text("def f():\n    from ...twin import dng\n    import glossrig.hardware.lights\n")
    monkeypatch.setattr(__import__(__name__), "ROOT", tmp_path)
    found = _violations("core")
    assert found == ["core/sub/bad.py:2 imports glossrig.twin",
                     "core/sub/bad.py:2 imports glossrig.twin.dng",
                     "core/sub/bad.py:3 imports glossrig.hardware.lights"]


#: what no study may contain, spelled so this file does not contain it itself: path edits, and
#: a machine's folder as a quoted string
FORBIDDEN_IN_VALIDATION = tuple("sys.path." + verb for verb in ("insert", "append")) + tuple(
    q + "/" + "work/" for q in ('"', "'"))


def test_studies_import_normally_and_name_no_machine_paths():
    """validation/ is a package (python -m validation.X): no study edits sys.path, and none
    names a folder of one machine (the shared data is found through validation.paths)."""
    bad = []
    for path in sorted((ROOT / "validation").rglob("*.py")):
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if any(s in line for s in FORBIDDEN_IN_VALIDATION):
                bad.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    assert bad == []
