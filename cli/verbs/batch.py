"""Extract (and fit) many sample captures, one Dask task per capture (issue 19).

  glossrig batch JOBS.toml --out DIR [--scheduler ADDRESS | --workers N] [--resume | --force]

Each job of JOBS.toml names a sample capture and its reference, camera and lamp files
(format below); the job runs `glossrig extract` and then `glossrig fit` on it, writing
DIR/NAME/samples.parquet and DIR/NAME/fit.json, each with its own provenance, exactly as
those verbs run by hand would. Jobs run on a new local Dask cluster of --workers
processes (default 2; one thread each), on an existing cluster with --scheduler ADDRESS
(its workers must see the captures at the same paths), or one after another in this
process with --workers 0, as the design sweeps do (glossrig.core.runners); the results
are the same in every case.

DIR/batch.json lists every job: its steps run and reused, the sha256 of its outputs and
its error, if any, with the batch's provenance (the job file's sha256, the options, the
glossrig version and commit). A job that fails does not stop the others; the verb ends
with exit status 2 naming the failed jobs.

Each job's steps record their inputs in DIR/NAME/.steps/: with --resume a finished step
whose inputs still match is reused, an interrupted extraction continues with the LEDs it
had finished, and the rest is redone. --force redoes every job. With neither, an existing
non-empty DIR is refused before any work.

Job file (TOML; paths relative to the job file's folder):

"""
from __future__ import annotations

import argparse
import textwrap

from glossrig.cli.batch_jobs import JOB_FORMAT
from glossrig.cli.outputs import add_force_option, prepare_output

__doc__ = (__doc__ or "") + textwrap.indent(JOB_FORMAT, "  ")

HELP = "extract and fit many sample captures on Dask (a local cluster, an existing one, or one process)"

#: the summary the verb writes in its output folder
SUMMARY = "batch.json"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("jobs", metavar="JOBS.toml", help="the job file (format above)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for the jobs' results (DIR/NAME/)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="an existing Dask scheduler (tcp://host:8786) instead of a new local cluster")
    p.add_argument("--workers", type=int, default=2,
                   help="worker processes of the local Dask cluster; 0: run the jobs one after another in this process")
    add_force_option(p, "the results in an existing --out: redo every job")
    p.add_argument("--resume", action="store_true",
                   help="continue in --out: reuse each job's finished steps whose recorded inputs match, complete "
                        "an interrupted extraction, redo the rest")
    p.add_argument("--no-progress", action="store_true")


def run(args) -> int:
    import logging

    from glossrig.cli.batch_jobs import BatchRun, read_jobs, run_job
    from glossrig.core.atomic import atomic_write_json
    from glossrig.core.errors import InputError
    from glossrig.core.provenance import provenance
    from glossrig.core.runners import LocalRunner, make_runner

    log = logging.getLogger(__name__)
    if args.force and args.resume:
        raise InputError("--resume continues the jobs in --out, --force redoes them: give one of them")
    runner = make_runner(args.scheduler, args.workers)        # checks --workers, before anything is written
    try:
        out = prepare_output(args.out, args.force, kind="folder", resume=args.resume,
                             hint="use --resume to continue it (finished steps whose inputs match are reused) "
                                  "or --force to redo every job")
        jobs = read_jobs(args.jobs)
        out = out.resolve()
        out.mkdir(parents=True, exist_ok=True)
        log.info(f"{len(jobs)} job(s) on {runner.name}")
        shared = BatchRun(out, args.resume, extract_workers=None if isinstance(runner, LocalRunner) else 1)
        results = runner.map(run_job, jobs, shared=shared, desc="batch", progress=not args.no_progress, unit="job")
    finally:
        runner.close()
    failed = [r for r in results if r["error"]]
    summary = {"kind": "glossrig.batch", "runner": runner.name, "jobs": results,
               "provenance": provenance({"jobs": args.jobs}, {"resume": args.resume, "force": args.force},
                                        tool="glossrig batch")}
    atomic_write_json(out / SUMMARY, summary)
    for r in results:
        print(f"== {r['name']}: {len(r['run'])} step(s) run, {len(r['reused'])} reused"
              + (f"; FAILED: {r['error']}" if r["error"] else ""))
        if r["printed"]:
            print(r["printed"].rstrip())
    if failed:
        raise InputError(f"{len(failed)} of {len(results)} job(s) failed: "
                         + "; ".join(f"{r['name']}: {r['error']}" for r in failed) + f" (see {out / SUMMARY})")
    print(f"{len(results)} job(s) done; summary: {out / SUMMARY}")
    return 0
