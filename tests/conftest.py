"""Shared fixtures. Mitsuba is imported through glossrig.twin.mitsuba_env, which picks
the LLVM variant when libLLVM 19 is present and falls back to scalar_rgb otherwise."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# The shared data (thesis tables, RGL measured BRDFs), found as validation/paths.py finds
# it: GLOSSRIG_SHARED, else shared/ beside the checkout. Tests that read it say so with
# @pytest.mark.needs_shared("data/...") or, in a fixture or at import, require_shared().
SHARED = Path(os.environ.get("GLOSSRIG_SHARED", ROOT.parent / "shared"))
RIG = ROOT / "scenes" / "thesis_rig.toml"


@pytest.hookimpl(tryfirst=True)
def pytest_configure(config):
    """Benchmarks off by default (as ``--benchmark-disable``; ``--benchmark-enable`` turns
    them on), set here rather than in pyproject's ``addopts``, where the option is an
    error unless pytest-benchmark is installed: plain ``pytest`` runs the suite too."""
    if config.pluginmanager.hasplugin("benchmark"):
        config.option.benchmark_disable = True


def missing_shared(*paths: str) -> str | None:
    """The skip reason when one of ``paths`` (relative to SHARED) is absent, else None."""
    for rel in paths or (".",):
        if not (SHARED / rel).exists():
            return f"shared data not found: {SHARED / rel} (set GLOSSRIG_SHARED to the shared/ folder)"
    return None


def require_shared(*paths: str) -> Path:
    """SHARED / paths[0], skipping the calling test (from a test or fixture) when one of
    ``paths`` is absent - the way for fixtures to say what @pytest.mark.needs_shared says."""
    reason = missing_shared(*paths)
    if reason:
        pytest.skip(reason)
    return SHARED / (paths[0] if paths else ".")


SLOW_TIMEOUT_S = 7200    # tests marked slow (pyproject's timeout = 1800 is for the default suite)


def pytest_collection_modifyitems(config, items):
    """``needs_shared`` tests skip with the missing path as the reason; slow tests get
    SLOW_TIMEOUT_S unless they carry their own ``timeout`` mark."""
    timeouts = config.pluginmanager.hasplugin("timeout")
    for item in items:
        for m in item.iter_markers("needs_shared"):
            reason = missing_shared(*m.args)
            if reason:
                item.add_marker(pytest.mark.skip(reason=reason))
                break
        if timeouts and item.get_closest_marker("slow") and not item.get_closest_marker("timeout"):
            item.add_marker(pytest.mark.timeout(SLOW_TIMEOUT_S))


@pytest.fixture(scope="session")
def rig():
    from glossrig.core.rig import load_rig

    return load_rig(RIG)


class WheelInstall:
    """glossrig installed from its wheel into a fresh virtual environment (not the
    editable one): ``run(*argv, cwd=...)`` runs a command there with that environment's
    ``bin`` first on PATH."""

    def __init__(self, venv: Path, site: Path, wheel: Path):
        import os

        self.venv, self.site, self.wheel = venv, site, wheel
        self.python = venv / "bin" / "python"
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME")}
        env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
        env["VIRTUAL_ENV"] = str(venv)
        self.env = env

    def run(self, *argv, cwd: Path, check: bool = True, timeout: float = 300):
        import subprocess

        r = subprocess.run([str(a) for a in argv], cwd=cwd, env=self.env, capture_output=True, text=True,
                           timeout=timeout)
        if check and r.returncode != 0:
            raise AssertionError(f"{' '.join(map(str, argv))} (in {cwd}) exited {r.returncode}:\n"
                                 f"{r.stdout[-2000:]}\n{r.stderr[-3000:]}")
        return r


@pytest.fixture(scope="session")
def wheel_install(tmp_path_factory) -> WheelInstall:
    """Build glossrig's wheel from this checkout and install it into a fresh virtual
    environment, once per session (tests/test_install.py).

    The sources are copied to a temporary folder first, so the build leaves nothing in
    the checkout. The build runs offline (``--no-build-isolation``: setuptools and wheel
    come with the ``test`` extra). The fresh environment is made with the running
    interpreter and gets the heavy dependencies (Mitsuba, OpenCV, ...) through a ``.pth``
    line naming this environment's site-packages - a path line, so that folder's own
    ``.pth`` files, the editable install's finder among them, are not run - and then
    glossrig itself from the wheel with ``--no-deps``."""
    import shutil
    import subprocess
    import sys
    import sysconfig

    base = tmp_path_factory.mktemp("wheel_install")
    src = base / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    for name in ("core", "twin", "hardware", "cli", "scenes"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    dist = base / "dist"

    def sh(*argv):
        r = subprocess.run([str(a) for a in argv], capture_output=True, text=True, timeout=300)
        if r.returncode != 0:
            raise AssertionError(f"{' '.join(map(str, argv))} exited {r.returncode}:\n{r.stdout[-2000:]}\n"
                                 f"{r.stderr[-3000:]}")
        return r

    sh(sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", dist, src)
    wheel = next(dist.glob("glossrig-*.whl"))
    venv = base / "venv"
    sh(sys.executable, "-m", "venv", "--without-pip", venv)
    site = Path(sh(venv / "bin" / "python", "-c",
                   "import sysconfig; print(sysconfig.get_paths()['purelib'])").stdout.strip())
    (site / "_glossrig_test_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    # pip itself comes through the .pth line; it installs into the fresh environment (sys.prefix).
    sh(venv / "bin" / "python", "-m", "pip", "install", "-q", "--no-deps", "--no-index", wheel)
    return WheelInstall(venv, site, wheel)


def glossrig_cli(*args, timeout: float = 600):
    """Run ``glossrig ARGS`` in a subprocess (a fresh interpreter, as a user would); fails the
    test with the end of stderr when it exits non-zero."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "glossrig.cli.main", *map(str, args)], capture_output=True, text=True,
                       timeout=timeout)
    assert r.returncode == 0, r.stderr[-3000:]
    return r


def camera_json_from_truth(truth: dict) -> dict:
    """A camera calibration file (glossrig.core.calibration.intrinsics format) holding the twin's true intrinsics."""
    K = truth["camera_matrix"]
    return {"format": "glossrig camera calibration", "version": 1, "fx": K[0][0], "fy": K[1][1], "cx": K[0][2],
            "cy": K[1][2], "distortion": truth["distortion"], "image_size": truth["image_size"]}


def lamps_json_from_truth(truth: dict, leds=("9",)) -> dict:
    """A lamp calibration file (glossrig.core.calibration.lamps format) holding the twin's true positions of ``leds``."""
    return {"kind": "glossrig.lamps", "lamps_mm": {k: v for k, v in truth["led_positions_mm"].items() if k in leds}}


@pytest.fixture(scope="session")
def tiny_captures(tmp_path_factory):
    """The smallest twin measurement: one-LED (LED 9) sample (sample_2_6) and lambert:0.8
    reference captures at scale 0.12, one rotation, one repeat, 1 spp, with ``camera.json``
    and ``lamps.json`` written from the twin's truth, so no calibration capture is rendered.
    Folder layout: ``sample/``, ``ref/``, ``camera.json``, ``lamps.json``. Shared by the
    session: tests must not change it (copy what they edit)."""
    import json

    d = tmp_path_factory.mktemp("tiny_captures")
    sim = ("--rig", RIG, "--repeats", 1, "--scale", 0.12, "--spp", 1, "--rotations", 0, "--leds", "9",
           "--no-progress")
    glossrig_cli("simulate", *sim, "--material", "lambert:0.8", "--seed", 6, "--out", d / "ref")
    glossrig_cli("simulate", *sim, "--material", "sample_2_6", "--seed", 7, "--out", d / "sample")
    t = json.loads((d / "sample" / "truth.json").read_text())
    (d / "camera.json").write_text(json.dumps(camera_json_from_truth(t)))
    (d / "lamps.json").write_text(json.dumps(lamps_json_from_truth(t)))
    return d
