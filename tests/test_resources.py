"""Path options resolve against the current folder first, then the packaged scenes, from
any folder (issue #16, "Install and paths"; glossrig.core.resources); every ``--help``
shows defaults; ``--version``; plain pytest needs no pytest-benchmark."""
from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import ROOT
from glossrig.cli.main import main
from glossrig.core.errors import InputError
from glossrig.core.fabrication.machine import load_machine
from glossrig.core.models.materials import material_names, parse_material
from glossrig.core.resources import packaged_reference, resolve_input, scenes_dir
from glossrig.core.rig import load_rig
from glossrig.hardware.plan import load_plan
from glossrig.hardware.toolpath_check import load_machine_limits


@pytest.fixture
def elsewhere(tmp_path, monkeypatch):
    """An empty working folder outside the checkout."""
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.mark.parametrize("name", ["scenes/thesis_rig.toml", "thesis_rig.toml"])
def test_rig_option_loads_from_any_folder(elsewhere, name):
    rig = load_rig(name)
    assert len(rig.leds) == 16 and rig.path == str(scenes_dir() / "thesis_rig.toml")


def test_a_file_in_the_current_folder_wins(elsewhere):
    text = (ROOT / "scenes" / "thesis_rig.toml").read_text()
    (elsewhere / "thesis_rig.toml").write_text(text.replace('name = "', 'name = "mine ', 1))
    rig = load_rig("thesis_rig.toml")
    assert rig.path == str(elsewhere / "thesis_rig.toml") and rig.name.startswith("mine ")


def test_missing_file_names_every_place_looked(elsewhere):
    with pytest.raises(InputError) as ei:
        load_rig("nope.toml")
    msg = str(ei.value)
    assert msg.startswith("nope.toml: rig file not found (looked in: ")
    assert str(elsewhere / "nope.toml") in msg and str(scenes_dir() / "nope.toml") in msg


def test_cli_reports_a_missing_rig_with_exit_2(elsewhere, capsys):
    assert main(["design", "coverage", "--rig", "nope.toml", "--out", "o"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("glossrig design: error: nope.toml: rig file not found (looked in: ") and "\n" not in err


@pytest.mark.parametrize("name", ["scenes/plans/twin_small.toml", "plans/twin_small.toml"])
def test_plan_option_and_its_rig_load_from_any_folder(elsewhere, name):
    plan = load_plan(name)                      # the plan names its rig as scenes/thesis_rig.toml
    assert plan.rig_path == scenes_dir() / "thesis_rig.toml"
    assert packaged_reference(plan.rig_path) == "scenes/thesis_rig.toml"


def test_capture_dry_run_of_a_packaged_plan_from_any_folder(elsewhere, capsys):
    rc = main(["capture", "--plan", "plans/twin_small.toml", "--lights", "twin", "--camera", "twin",
               "--out", "cap", "--dry-run"])
    assert rc == 0 and not (elsewhere / "cap").exists()


def test_missing_plan_names_every_place_looked(elsewhere):
    with pytest.raises(InputError, match=r"^plans/none\.toml: capture plan not found \(looked in: "):
        load_plan("plans/none.toml")


def test_machine_files_load_from_any_folder(elsewhere):
    assert load_machine("engraver_roland.toml").bed_mm == load_machine().bed_mm
    assert load_machine_limits("scenes/engraver_roland.toml").bed_mm == (305.0, 230.0)
    with pytest.raises(InputError, match="machine description not found"):
        load_machine("no_engraver.toml")


def test_material_names_come_from_the_packaged_scenes(elsewhere):
    assert parse_material("sample_2_6").ward is not None
    assert "transparency_sheet" in material_names()
    assert resolve_input("materials/sample_2_6.toml", "material file") == scenes_dir() / "materials/sample_2_6.toml"


def _help(argv, capsys) -> str:
    with pytest.raises(SystemExit) as ei:
        main([*argv, "--help"])
    assert ei.value.code == 0
    return capsys.readouterr().out


def test_every_help_shows_defaults(capsys):
    raw = _help(["simulate"], capsys)
    simulate = " ".join(raw.split())                  # argparse wraps to the terminal's width
    assert "(default: 0.25)" in simulate and "(default: sample_2_6)" in simulate
    assert "\n  glossrig simulate --rig scenes/thesis_rig.toml" in raw   # examples keep their lines
    assert "(default: None)" not in simulate and "(default: False)" not in simulate
    # nested sub-verbs (their parsers are made by the verb modules)
    assert "(default: " in _help(["design", "coverage"], capsys)
    assert "(default: " in _help(["model", "crossval"], capsys)


def test_every_option_with_a_default_shows_it():
    """Options without help text too: argparse prints nothing for them unless told to."""
    import argparse

    from glossrig.cli.main import build_parser

    def parsers(p):
        yield p
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for child in dict.fromkeys(a.choices.values()):
                    yield from parsers(child)

    missing = []
    for p in parsers(build_parser()):
        text = " ".join(p.format_help().split())
        for a in p._actions:
            if (a.option_strings and a.default not in (None, False, argparse.SUPPRESS)
                    and not isinstance(a, argparse._VersionAction) and a.help != argparse.SUPPRESS):
                if f"default: {a.default}" not in text and "default" not in (a.help or "").lower():
                    missing.append(f"{p.prog} {a.option_strings[-1]}")
    assert missing == []


def test_version(capsys):
    from glossrig.core.resources import package_version

    with pytest.raises(SystemExit) as ei:
        main(["--version"])
    assert ei.value.code == 0 and capsys.readouterr().out.strip() == f"glossrig {package_version()}"
    r = subprocess.run([sys.executable, "-m", "glossrig", "--version"], capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.strip() == f"glossrig {package_version()}"


def test_pytest_runs_without_pytest_benchmark():
    """pyproject's addopts used to carry --benchmark-disable: an error without the plugin."""
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:benchmark", "-p", "no:cacheprovider",
                        "tests/test_resources.py", "-k", "test_version"], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0 and "1 passed" in r.stdout, r.stdout[-2000:] + r.stderr[-2000:]
