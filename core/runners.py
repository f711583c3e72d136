"""Where independent tasks run: in this process, or on a Dask cluster (Rocklin 2015,
"Dask: parallel computation with blocked algorithms and task scheduling", SciPy;
``distributed``'s futures interface).

Shared by the design sweeps (:func:`glossrig.core.design.placement.optimise`) and the
batch processing of captures (``glossrig batch``). A runner maps a function over a list
of items and returns the results in the items' order, whatever order they finish in, so
a result never depends on where it was computed:

* :class:`LocalRunner`: one item after another in this process;
* :class:`DaskRunner`: one Dask task per item, on a new local cluster (``workers``
  processes of one thread each; ``distributed`` sets each worker's BLAS/OpenMP threads
  to one) or on an existing scheduler at ``address``;
* :func:`make_runner`: the CLI convention (``--scheduler ADDRESS`` for an existing
  cluster, ``--workers 0`` for one process, else a local cluster).

A ``shared`` argument (the same for every item: a design sweep's set-up) is sent to the
workers once (``Client.scatter(broadcast=True)``) and passed as ``fn(shared, item)``.
"""
from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from typing import Any

from glossrig.core.errors import InputError
from glossrig.core.progress import progress_enabled

_NO_SHARED = object()


class LocalRunner:
    """Runs the items one after another in this process."""

    name = "one process"

    def map(self, fn: Callable, items: Sequence, shared: Any = _NO_SHARED, desc: str = "tasks",
            progress: bool = True, unit: str = "task") -> list:
        """``[fn(item) for item in items]`` (``fn(shared, item)`` with ``shared``), with a progress bar."""
        from tqdm import tqdm

        out = []
        for item in tqdm(items, desc=desc, unit=unit, disable=not progress_enabled(progress), file=sys.stderr):
            out.append(fn(item) if shared is _NO_SHARED else fn(shared, item))
        return out

    def close(self) -> None:
        pass


class DaskRunner:
    """Runs the items as Dask tasks on a new local cluster (``workers`` processes, one
    thread each) or on the scheduler at ``address``; results come back in item order."""

    def __init__(self, address: str | None = None, workers: int = 2, timeout_s: float = 20.0):
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise InputError("Dask is not installed: pip install -e '.[design]' (dask[distributed])") from None
        self._cluster = None
        if address:
            try:
                self.client = Client(address, timeout=f"{timeout_s}s")
            except (OSError, TimeoutError) as e:
                raise InputError(f"cannot reach the Dask scheduler at {address!r}: {e}") from None
            self.name = f"Dask scheduler {address}"
        else:
            if workers < 1:
                raise InputError(f"a local Dask cluster needs at least one worker, got {workers}")
            self._cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                         dashboard_address=None, silence_logs=40)
            self.client = Client(self._cluster)
            self.name = f"local Dask cluster, {workers} worker processes"

    def map(self, fn: Callable, items: Sequence, shared: Any = _NO_SHARED, desc: str = "tasks",
            progress: bool = True, unit: str = "task") -> list:
        """One task per item (``fn(item)``, or ``fn(shared, item)`` with ``shared`` scattered
        to every worker once); a task's exception is raised here."""
        from distributed import as_completed
        from tqdm import tqdm

        if shared is _NO_SHARED:
            futs = [self.client.submit(fn, item, pure=False) for item in items]
        else:
            fut_shared = self.client.scatter(shared, broadcast=True)
            futs = [self.client.submit(fn, fut_shared, item, pure=False) for item in items]
        index = {f.key: k for k, f in enumerate(futs)}
        out: list = [None] * len(futs)
        with tqdm(total=len(futs), desc=desc, unit=unit, disable=not progress_enabled(progress),
                  file=sys.stderr) as bar:
            for f in as_completed(futs):
                out[index[f.key]] = f.result()
                bar.update(1)
        return out

    def close(self) -> None:
        self.client.close()
        if self._cluster is not None:
            self._cluster.close()


def make_runner(scheduler: str | None = None, workers: int = 2) -> LocalRunner | DaskRunner:
    """An existing cluster at ``scheduler``; else one process for ``workers == 0``, else a
    new local Dask cluster of ``workers`` processes."""
    if workers < 0:
        raise InputError(f"--workers must be >= 0, got {workers}")
    if scheduler:
        return DaskRunner(address=scheduler)
    if workers == 0:
        return LocalRunner()
    return DaskRunner(workers=workers)
