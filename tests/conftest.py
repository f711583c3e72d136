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


SHARED_FOLDER_WAIT_S = 1800     # pyproject's per-test timeout: no capture fixture takes longer


def run_shared_folder(tmp_path_factory, name: str, inputs, make, *, wait_s: float = SHARED_FOLDER_WAIT_S,
                      poll_s: float = 0.2) -> Path:
    """A folder made once per test run by ``make(folder)``, not once per pytest-xdist
    worker (``--dist loadfile`` gives each worker its own session, so a session fixture
    alone is made by every worker whose modules use it).

    The folder lies in the run's base temporary folder, which the workers share (each
    worker's own base is a sub-folder of it), named by NAME and a hash of INPUTS (what
    ``make`` depends on: two fixtures with other inputs never share a folder). The first
    worker to take the folder's lock makes it under a temporary name and renames it into
    place, so a folder that exists is complete; the others wait for the lock (polling, at
    most ``wait_s`` seconds, then TimeoutError naming the lock) and use it. A ``make``
    that fails leaves nothing: the next worker tries again and fails its own tests the
    same way. Users must not change the folder (copy what they edit)."""
    import fcntl
    import hashlib
    import json
    import shutil
    import time

    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent           # the controller's base: xdist puts each worker's in it
    digest = hashlib.sha256(json.dumps(inputs, sort_keys=True, default=str).encode()).hexdigest()[:16]
    folder = base / f"shared-{name}-{digest}"
    lock_path = base / f".{folder.name}.lock"
    with open(lock_path, "a") as lock:
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"{lock_path}: still locked after {wait_s:.0f} s (another pytest worker "
                                       f"making {folder.name})") from None
                time.sleep(poll_s)
        try:
            if not folder.is_dir():
                part = base / f".{folder.name}.{os.getpid()}.part"
                shutil.rmtree(part, ignore_errors=True)
                part.mkdir()
                try:
                    make(part)
                except BaseException:
                    shutil.rmtree(part, ignore_errors=True)
                    raise
                part.rename(folder)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    return folder


#: the tiny captures' simulate options (their seeds: reference 6, sample 7)
TINY_SIM = ("--rig", RIG, "--repeats", 1, "--scale", 0.12, "--spp", 1, "--rotations", 0, "--leds", "9",
            "--no-progress")


def make_twin_captures(d: Path, sim=TINY_SIM, leds=("9",)) -> None:
    """A lambert:0.8 reference (``ref/``, seed 6) and a sample_2_6 sample (``sample/``, seed 7)
    simulated with ``sim``, with ``camera.json`` and ``lamps.json`` (``leds``) from the truth."""
    import json

    glossrig_cli("simulate", *sim, "--material", "lambert:0.8", "--seed", 6, "--out", d / "ref")
    glossrig_cli("simulate", *sim, "--material", "sample_2_6", "--seed", 7, "--out", d / "sample")
    t = json.loads((d / "sample" / "truth.json").read_text())
    (d / "camera.json").write_text(json.dumps(camera_json_from_truth(t)))
    (d / "lamps.json").write_text(json.dumps(lamps_json_from_truth(t, leds=leds)))


def _make_tiny_captures(d: Path) -> None:
    make_twin_captures(d)


@pytest.fixture(scope="session")
def tiny_captures(tmp_path_factory):
    """The smallest twin measurement: one-LED (LED 9) sample (sample_2_6) and lambert:0.8
    reference captures at scale 0.12, one rotation, one repeat, 1 spp, with ``camera.json``
    and ``lamps.json`` written from the twin's truth, so no calibration capture is rendered.
    Folder layout: ``sample/``, ``ref/``, ``camera.json``, ``lamps.json``. Made once per run
    and shared by every worker (:func:`run_shared_folder`): tests must not change it (copy
    what they edit)."""
    inputs = {"sim": TINY_SIM, "rig": RIG.read_text(), "ref": ("lambert:0.8", 6), "sample": ("sample_2_6", 7)}
    return run_shared_folder(tmp_path_factory, "tiny_captures", inputs, _make_tiny_captures)
