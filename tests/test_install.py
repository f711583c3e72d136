"""glossrig installed from its wheel, run from a folder outside the checkout (issue #16,
"Install and paths"): the scenes ship with the package, ``glossrig --version`` and
``python -m glossrig`` work, and a newcomer's copy of the README's measuring commands
runs end to end. The wheel and its fresh virtual environment are built once per session
(``wheel_install`` in conftest.py)."""
from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest

from conftest import ROOT


def test_wheel_installs_glossrig_with_its_scenes(wheel_install, tmp_path):
    w = wheel_install
    # The fresh environment imports the wheel's copy, not the checkout.
    r = w.run(w.python, "-c", "import glossrig, glossrig.core, glossrig.core.resources as r; "
              "print(glossrig.core.__file__); print(r.scenes_dir()); print(glossrig.__version__)", cwd=tmp_path)
    core_file, scenes, version = r.stdout.split()
    assert Path(core_file).is_relative_to(w.site) and not Path(core_file).is_relative_to(ROOT), core_file
    assert Path(scenes) == w.site / "glossrig" / "scenes"
    data = ("*.toml", "*.xml")        # rigs, plans, materials; Mitsuba BSDF descriptions
    shipped = {p.relative_to(scenes).as_posix() for g in data for p in Path(scenes).rglob(g)}
    in_repo = {p.relative_to(ROOT / "scenes").as_posix() for g in data for p in (ROOT / "scenes").rglob(g)}
    assert shipped == in_repo and "materials/sample_2_6.toml" in shipped and "plans/twin_small.toml" in shipped
    assert "materials/aniso_roughconductor_ggx.xml" in shipped

    assert w.run("glossrig", "--version", cwd=tmp_path).stdout.strip() == f"glossrig {version}"
    assert w.run(w.python, "-m", "glossrig", "--version", cwd=tmp_path).stdout.strip() == f"glossrig {version}"
    help_text = w.run(w.python, "-m", "glossrig", "--help", cwd=tmp_path).stdout
    assert "simulate" in help_text and "calibrate" in help_text

    # Packaged plans, rigs and materials by the names the README uses, from a foreign folder.
    dry = w.run("glossrig", "capture", "--plan", "scenes/plans/twin_small.toml", "--lights", "twin", "--camera",
                "twin", "--out", "cap", "--dry-run", cwd=tmp_path)
    assert dry.returncode == 0 and not (tmp_path / "cap").exists()
    bad = w.run("glossrig", "simulate", "--material", "no_such_material", "--out", "x", cwd=tmp_path, check=False)
    assert bad.returncode == 2 and "sample_2_6" in bad.stderr and "transparency_sheet" in bad.stderr


#: what shrinks the README's measuring chain to a trial run - only options the README documents
#: ("Simulating captures": --scale, --leds, --views)
SHRINK = {"--scale": "0.1", "--leds": "9", "--views": "8"}
#: the verbs of the chain (diagnose and calibrate geometry are checks, not steps)
CHAIN = (("simulate",), ("calibrate", "camera"), ("calibrate", "lamps"), ("extract",), ("fit",))


def readme_commands(section: str) -> list[list[str]]:
    """The ``glossrig`` command lines of one README section's code blocks, as a reader
    copies them (``\\`` continuations joined, trailing ``# comments`` dropped)."""
    text = (ROOT / "README.md").read_text()
    m = re.search(rf"^## {re.escape(section)}.*?$(.*?)(?=^## )", text, re.S | re.M)
    assert m, f"README has no section {section!r}"
    cmds = []
    for block in re.findall(r"```\n(.*?)```", m.group(1), re.S):
        for line in block.replace("\\\n", " ").splitlines():
            words = shlex.split(line, comments=True)
            if words and words[0] == "glossrig":
                cmds.append(words)
    return cmds


def shrink(argv: list[str]) -> list[str]:
    out = list(argv)
    for i, a in enumerate(out[:-1]):
        if a in SHRINK:
            out[i + 1] = SHRINK[a]
    return out


@pytest.mark.mitsuba
def test_newcomer_runs_the_readme_measuring_chain_from_anywhere(wheel_install, tmp_path):
    """The README's twin captures, calibrations, extract and fit, as written (shrunk only
    through --scale, --leds and --views), from an empty folder outside the checkout
    against the wheel install: a fit of sample_2_6 comes out."""
    cmds = [c for c in readme_commands("Measuring (the same commands for twin and real captures)")
            if tuple(c[1:3]) in CHAIN or tuple(c[1:2]) in CHAIN]
    verbs = [c[1] if c[1] != "calibrate" else f"calibrate {c[2]}" for c in cmds]
    assert verbs == ["simulate"] * 4 + ["calibrate camera", "calibrate lamps", "extract", "fit"], verbs
    assert any("sample_2_6" in c for c in cmds) and any("scenes/thesis_rig.toml" in c for c in cmds)
    work = tmp_path / "newcomer"
    work.mkdir()
    for argv in cmds:
        wheel_install.run(*shrink(argv), cwd=work)

    fit = json.loads((work / "fit.json").read_text())
    assert fit["luminance"]["rho_s"] > 0 and 0 < fit["luminance"]["alpha_x"] <= 0.5
    assert json.loads((work / "cap_sample" / "truth.json").read_text())["material"]["label"] == "sample_2_6"
