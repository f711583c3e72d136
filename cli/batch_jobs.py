"""The jobs of ``glossrig batch``: the job file, and one job (extract, then fit, one sample
capture) as it runs on a Dask worker or in this process.

A job runs the verbs themselves (``glossrig extract``, ``glossrig fit``) on its capture,
in its own folder ``OUT/NAME/``, as steps of a :class:`glossrig.cli.steps.StepRunner`:
each step records its inputs (captures by their manifests, files by sha256, options, the
glossrig version) and is reused on ``--resume`` only when they match, and an interrupted
extraction continues with the LEDs it had finished (``glossrig extract --resume``). So
a job's outputs do not depend on where it ran: the same tables and fits on a cluster as
in one process.
"""
from __future__ import annotations

import contextlib
import io
import re
from dataclasses import dataclass
from pathlib import Path

from glossrig.core.errors import GlossrigError, InputError

#: the job file's format (also in ``glossrig batch --help``)
JOB_FORMAT = """\
[defaults]                       # optional: every job takes these unless it sets its own
reference = "cap_reference"      # REF_DIR of glossrig extract (paths relative to this file)
camera = "camera.json"
lamps = "lamps.json"
reference_albedo = 0.8           # glossrig extract --reference-albedo (default 0.8)
estimator = "ml"                 # glossrig extract --estimator: "ml" (default) or "thesis"
fit = true                       # also fit each table with glossrig fit (default true)
fit_options = ["--calibration-draws", "0"]   # further glossrig fit options (default none)

[jobs.sample_2_6]                # one table per sample capture; results in DIR/sample_2_6/
sample = "cap_sample"            # SAMPLE_DIR (required)

[jobs.brushed]
sample = "cap_brushed"
reference = "cap_reference_2"    # any default can be given per job
"""

#: what a job writes in its folder
SAMPLES, FIT = "samples.parquet", "fit.json"
_KEYS = {"sample", "reference", "camera", "lamps", "reference_albedo", "estimator", "fit", "fit_options"}
_BUILTIN = {"reference_albedo": 0.8, "estimator": "ml", "fit": True, "fit_options": []}
_OWN_OUTPUTS = ("--out", "--plots", "--mitsuba", "--force")      # a job's outputs are the batch's to name
_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.=+-]*")


@dataclass(frozen=True)
class Job:
    """One sample capture to extract (and fit); paths are absolute."""

    name: str
    sample: Path
    reference: Path
    camera: Path
    lamps: Path
    reference_albedo: float
    estimator: str
    fit: bool
    fit_options: tuple[str, ...]

    def extract_argv(self, out: Path, resume: bool, workers: int | None = None) -> list[str]:
        return ["extract", str(self.sample), "--reference", str(self.reference), "--camera", str(self.camera),
                "--lamps", str(self.lamps), "--out", str(out), "--reference-albedo", repr(self.reference_albedo),
                "--estimator", self.estimator, "--no-progress", *(["--resume"] if resume else []),
                *([] if workers is None else ["--workers", str(workers)])]

    def fit_argv(self, samples: Path, out: Path) -> list[str]:
        return ["fit", str(samples), "--out", str(out), *self.fit_options]


def _parse(argv: list[str]):
    """``glossrig ARGV`` parsed; an argparse error becomes an InputError with its message."""
    from glossrig.cli.main import build_parser

    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            return build_parser().parse_args(argv)
    except SystemExit:
        lines = [ln for ln in err.getvalue().splitlines() if ln.strip()]
        raise InputError(lines[-1] if lines else f"cannot parse glossrig {' '.join(argv)}") from None


def run_verb(argv: list[str]) -> str:
    """Run ``glossrig ARGV`` in this process and return what it printed on stdout; its
    warnings go to stderr (progress messages off, as with ``-q``); a bad input raises."""
    from glossrig.cli import logs

    args = _parse(argv)
    out = io.StringIO()
    with logs.configured(args.verb, quiet=True), contextlib.redirect_stdout(out):
        args._run(args)
    return out.getvalue()


def read_jobs(path) -> list[Job]:
    """The jobs of a job file (:data:`JOB_FORMAT`), in file order, every input checked
    before any work: errors name the file and the key (``jobs.NAME.sample``)."""
    from glossrig.core.capture import capture_complete
    from glossrig.core.toml_input import check_number, read_toml

    path = Path(path)
    doc = read_toml(path, "batch job file")
    extra = sorted(set(doc) - {"defaults", "jobs"})
    if extra:
        raise InputError(f"unknown key(s) {', '.join(extra)} (expected [defaults] and [jobs.NAME] tables)", path=path)
    defaults = doc.get("defaults", {})
    if not isinstance(defaults, dict):
        raise InputError("defaults must be a table", path=path)
    jobs = doc.get("jobs")
    if not isinstance(jobs, dict) or not jobs:
        raise InputError("no jobs: add a [jobs.NAME] table with sample = \"CAPTURE_DIR\" per capture", path=path)
    base = path.resolve().parent
    bad = sorted(set(defaults) - (_KEYS - {"sample"}))
    if bad:
        raise InputError(f"defaults: unknown key(s) {', '.join(bad)} (known: {', '.join(sorted(_KEYS - {'sample'}))})",
                         path=path)
    out = []
    for name, spec in jobs.items():
        if not isinstance(spec, dict):
            raise InputError(f"jobs.{name} must be a table", path=path)
        if not _NAME.fullmatch(name):
            raise InputError(f"jobs.{name}: a job name is its output folder's name: letters, digits and _ . = + - "
                             "only", path=path)
        bad = sorted(set(spec) - _KEYS)
        if bad:
            raise InputError(f"jobs.{name}: unknown key(s) {', '.join(bad)} (known: {', '.join(sorted(_KEYS))})",
                             path=path)
        val = {**_BUILTIN, **defaults, **spec}

        def key(k: str, name: str = name, spec: dict = spec) -> str:
            return f"jobs.{name}.{k}" if k in spec else f"defaults.{k}"

        paths = {}
        for k in ("sample", "reference", "camera", "lamps"):
            if k not in val:
                raise InputError(f"jobs.{name}: {k} is required (in the job or in [defaults])", path=path)
            if not isinstance(val[k], str) or not val[k]:
                raise InputError(f"{key(k)} must be a path (a string), got {val[k]!r}", path=path)
            p = Path(val[k]).expanduser()
            p = (p if p.is_absolute() else base / p).resolve()
            if k in ("sample", "reference"):
                if not (p / "capture.json").is_file():
                    raise InputError(f"{key(k)}: {p} is not a capture folder (no capture.json)", path=path)
                if not capture_complete(p):
                    raise InputError(f"{key(k)}: the capture {p} is not complete (resume it first)", path=path)
            elif not p.is_file():
                raise InputError(f"{key(k)}: file {p} not found", path=path)
            paths[k] = p
        albedo = check_number(val["reference_albedo"], key("reference_albedo"), path, lo=0.0, hi=1.0, lo_open=True)
        if val["estimator"] not in ("ml", "thesis"):
            raise InputError(f"{key('estimator')} must be \"ml\" or \"thesis\", got {val['estimator']!r}", path=path)
        if not isinstance(val["fit"], bool):
            raise InputError(f"{key('fit')} must be true or false, got {val['fit']!r}", path=path)
        opts = val["fit_options"]
        if not isinstance(opts, list) or not all(isinstance(o, str) for o in opts):
            raise InputError(f"{key('fit_options')} must be a list of strings, got {opts!r}", path=path)
        own = [o for o in opts if o.split("=", 1)[0] in _OWN_OUTPUTS]
        if own:
            raise InputError(f"{key('fit_options')}: {', '.join(own)} not allowed (the batch names each job's "
                             "outputs)", path=path)
        job = Job(name=name, reference_albedo=albedo, estimator=val["estimator"], fit=val["fit"],
                  fit_options=tuple(opts), **paths)
        try:                   # the fit options checked now, not on a worker after the extraction
            _parse(job.fit_argv(Path(SAMPLES), Path(FIT)))
        except InputError as e:
            raise InputError(f"{key('fit_options')}: {e}", path=path) from None
        out.append(job)
    return out


@dataclass(frozen=True)
class BatchRun:
    """What every job of one batch shares: the output folder, whether to resume, and the
    processes each extraction may start (``glossrig extract --workers``; None: every core).
    A Dask worker is a daemon process, which may not start processes of its own, so jobs on
    Dask extract with 1: the batch's parallelism is one task per capture."""

    out: Path
    resume: bool
    extract_workers: int | None = None


def run_job(run: BatchRun, job: Job) -> dict:
    """Extract (and fit) one job in ``run.out / job.name`` (module docstring); a Dask
    task. Returns the job's record: the steps run and reused, its outputs' sha256, what
    the verbs printed, and the error (None when it succeeded)."""
    from glossrig.cli.steps import StepRunner
    from glossrig.core.capture import load_manifest, sha256_file

    folder = run.out / job.name
    steps = StepRunner(folder, resume=run.resume, total=1 + job.fit)
    samples, fit = folder / SAMPLES, folder / FIT
    printed: list[str] = []
    error = None

    def extract(resume: bool) -> None:
        printed.append(run_verb(job.extract_argv(samples, resume, run.extract_workers)))

    try:
        folder.mkdir(parents=True, exist_ok=True)
        steps.run("extract", samples, extract,
                  files={"camera": job.camera, "lamps": job.lamps,
                         "sample_rig": load_manifest(job.sample).rig_path(),
                         "reference_rig": load_manifest(job.reference).rig_path()},
                  captures={"sample": job.sample, "reference": job.reference},
                  options={"reference_albedo": job.reference_albedo, "estimator": job.estimator}, resumable=True)
        if job.fit:
            steps.run("fit", fit, lambda resume: printed.append(run_verb(job.fit_argv(samples, fit))),
                      files={"samples": samples}, options={"fit_options": list(job.fit_options)})
    except (GlossrigError, OSError) as e:
        error = str(e)
    outputs = {p.name: sha256_file(p) for p in (samples, fit) if p.is_file()}
    return {"name": job.name, "sample": str(job.sample), "reference": str(job.reference), "run": steps.done,
            "reused": steps.reused, "outputs": outputs, "printed": "".join(printed), "error": error}
