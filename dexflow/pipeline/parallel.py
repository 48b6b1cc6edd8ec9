"""Map a function over independent items (sequences, objects) with per-item error capture.

Backends (``run.backend``, ``conf/run/*.yaml``): ``sequential`` (this process), ``local``
(joblib processes, ``run.n_jobs``) and ``ray`` (Ray tasks on a local Ray or a cluster at
``run.address``; the optional ``ray`` extra, imported only when chosen). Results come back in
input order whatever the backend, so outputs are deterministic. An item that raises does not
stop the others: its error is returned in its :class:`ItemResult`, the same way for every
backend. Every backend drives a tqdm progress bar as items complete.

Errors are of two kinds. A :class:`~dexflow.errors.DexflowError` says the item's input is bad
(a malformed sequence, a degenerate mesh): rerunning cannot help, so the item is reported and
skipped. Anything else (the machine: ``OSError`` such as a full disk, ``MemoryError``, a worker
killed by the OS or a lost Ray node; or an unexpected error) is marked ``retry``: the stage must
fail, so that DVC does not cache a partial output and a rerun retries the item.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import traceback
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Generic, TypeVar

from tqdm.auto import tqdm

from dexflow.errors import ConfigError, DexflowError

if TYPE_CHECKING:
    from dexflow.params import RunParams

__all__ = ["ItemResult", "map_items", "raise_first_error"]

T = TypeVar("T")
log = logging.getLogger(__name__)

RAY_MISSING = "run.backend 'ray' needs Ray: install the ray extra: pip install -e '.[ray]'"


@dataclass
class ItemResult(Generic[T]):
    """Outcome of one item: ``value`` if it succeeded, else ``error`` (a one-line reason).

    ``retry`` is True when the error is not the input's (I/O, memory, a killed worker, an
    unexpected exception): such an item must fail its stage, not be skipped.
    """

    item: Any
    value: T | None = None
    error: str | None = None
    details: str | None = None
    retry: bool = False

    @property
    def ok(self) -> bool:
        return self.error is None

    def entry(self) -> dict:
        """Summary entry: ``{"status": "ok", **value}`` or ``{"status": "failed", "error": ...}``."""
        if self.ok:
            return {"status": "ok", **(self.value or {})}
        return {"status": "failed", "error": self.error}


def _reason(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}"


def _run(func: Callable[[Any], T], item: Any) -> ItemResult[T]:
    try:
        return ItemResult(item, value=func(item))
    except DexflowError as exc:  # the item's input is bad: reported, the others go on
        return ItemResult(item, error=_reason(exc), details=traceback.format_exc())
    except Exception as exc:  # the machine or a bug: the others go on, the stage will fail
        return ItemResult(item, error=_reason(exc), details=traceback.format_exc(), retry=True)


def _run_in(cwd: str, func: Callable[[Any], T], item: Any) -> ItemResult[T]:
    """A Ray task: run in the driver's working directory, so that relative paths hold."""
    try:
        os.chdir(cwd)
    except OSError as exc:
        return ItemResult(
            item,
            error=f"RuntimeError: the driver's directory {cwd} does not exist on this Ray node "
            f"({exc}); run dexflow from a filesystem shared by every node",
            retry=True,
        )
    return _run(func, item)


def _settings(run: int | RunParams) -> tuple[str, int, str | None]:
    """(backend, n_jobs, address) from an int (n_jobs, as before) or :class:`RunParams`."""
    if hasattr(run, "backend"):
        return run.backend, run.n_jobs, run.address
    n_jobs = int(run)
    return ("sequential" if n_jobs == 1 else "local"), n_jobs, None


def map_items(
    func: Callable[[Any], T],
    items: Iterable[Any],
    run: int | RunParams = 1,
    desc: str = "items",
    progress: bool = True,
) -> list[ItemResult[T]]:
    """Apply ``func`` to every item; never raises for an item's own error.

    Args:
        func: Function of one item. Except in this process it is pickled (cloudpickle) to the
            workers, so closures work; the items and results must be picklable.
        items: The items.
        run: The ``run`` params (backend, n_jobs, address), or an int n_jobs: 1 runs in this
            process; more (or -1 for all cores) runs in this process and ``n_jobs - 1`` joblib
            worker processes.
        desc: Label of the progress bar and of the error log lines.
        progress: Show a tqdm progress bar.

    Returns:
        One :class:`ItemResult` per item, in input order. With fewer than two items every
        backend runs the item in this process.
    """
    items = list(items)
    backend, n_jobs, address = _settings(run)
    bar = tqdm(total=len(items), desc=desc, disable=not progress)
    with bar:
        if backend == "sequential" or len(items) <= 1 or (backend == "local" and n_jobs == 1):
            results = []
            for item in items:
                results.append(_run(func, item))
                bar.update()
        elif backend == "local":
            results = _map_joblib(func, items, n_jobs, bar)
        elif backend == "ray":
            results = _map_ray(func, items, n_jobs, address, bar)
        else:
            raise ConfigError(
                f"run.backend: expected 'sequential', 'local' or 'ray', found {backend!r}"
            )
    for result in results:
        if not result.ok:
            log.error("%s %s failed: %s", desc, result.item, result.error)
    return results


# Thread-pool variables a worker process reads at start-up: one thread per item everywhere.
_ONE_THREAD = {
    var: "1"
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")
}  # fmt: skip


def _init_worker() -> None:
    """Turn off loky's memory-leak guard in this worker process.

    loky measures a worker's size after its first task and replaces the worker once it has
    grown 300 MB past it. Here the first task is :func:`_ready`, before any item: the caches a
    stage fills once per process (the hand model with its meshes, torch's) and an item's working
    set read as a leak, and the worker was replaced in the middle of the refine stage, with
    "UserWarning: A worker stopped while some jobs were given to the executor", costing a new
    worker's start (torch, the stage, the caches again). A worker that really runs out of memory
    is killed by the OS, and its item fails with ``retry`` (:func:`_map_joblib`).
    """
    from joblib.externals.loky import process_executor

    process_executor._USE_PSUTIL = False  # read by the worker's loop after every task


def _ready(func: Callable) -> int:
    """Nothing: unpickling ``func`` in a worker imports what it needs (torch, the stage)."""
    return os.getpid()


def _map_joblib(func: Callable, items: list, n_jobs: int, bar: tqdm) -> list[ItemResult]:
    """``n_jobs`` at once: this process and ``n_jobs - 1`` joblib (loky) worker processes.

    A worker first has to start and import torch and the stage (3-5 s). Handing it items
    straight away made small stages slower than one process: the contact stage of the demo
    took 11.5 s with two workers against 7.6 s in the stage's own process. So this process
    works on the items from the start, while the workers get ready on a first task that only
    loads ``func``; from then on items go one at a time to whoever is free. If this process
    has done every item before a worker is ready, the worker is not waited for. Every item runs
    with one thread (BLAS, OpenMP, torch's intra-op pool) wherever it runs, so that its result
    does not depend on where it ran.

    A worker that dies (killed by the OS for memory, a crash in native code) breaks the pool:
    its item fails with ``retry`` and this process does the rest. An item that kills this
    process ends the stage, as without workers; the items done before are recorded.
    """
    from joblib import cpu_count
    from joblib.externals.loky import get_reusable_executor
    from threadpoolctl import threadpool_limits

    processes = n_jobs if n_jobs > 0 else max(cpu_count() + 1 + n_jobs, 1)  # -1: every core
    results: list[ItemResult | None] = [None] * len(items)
    order = iter(range(len(items)))
    lock = threading.Lock()

    stop = threading.Event()  # set on an interrupt: the thread below takes no more items

    def take() -> int | None:
        with lock:
            return None if stop.is_set() else next(order, None)

    def work_here() -> None:
        torch = sys.modules.get("torch")  # loaded by every stage that computes with it
        threads = torch.get_num_threads() if torch else 0
        try:
            if torch:
                torch.set_num_threads(1)
            with threadpool_limits(limits=1):
                while (i := take()) is not None:
                    results[i] = _run(func, items[i])
                    bar.update()
        finally:
            if torch:
                torch.set_num_threads(threads)

    workers, ready = None, None
    if processes > 1:
        workers = get_reusable_executor(
            max_workers=processes - 1, env=_ONE_THREAD, initializer=_init_worker
        )
        ready = workers.submit(_ready, func)

    def pool_failed(i: int, exc: Exception) -> None:
        reason = _reason(exc).splitlines()[0].split(". ")[0]
        log.error("worker pool failed on %s: %s; the rest run here", items[i], reason)
        error = f"no result, the worker pool failed ({reason})"
        results[i] = ItemResult(items[i], error=error, details=traceback.format_exc(), retry=True)

    with ThreadPoolExecutor(1, thread_name_prefix="dexflow-map") as here_pool:
        here = here_pool.submit(work_here)
        pending: dict[Any, int] = {}
        try:
            while True:
                if ready is not None and ready.done():
                    if ready.exception() is not None:
                        log.error("worker pool failed to start: %s; all items run here",
                                  _reason(ready.exception()))  # fmt: skip
                        processes = 1
                    ready = None
                while ready is None and len(pending) < processes - 1 and (i := take()) is not None:
                    pending[workers.submit(_run, func, items[i])] = i
                if here.done() and not pending:
                    break  # every item has its result (a worker still starting is not waited for)
                waiting = [*pending, *[f for f in (here, ready) if f and not f.done()]]
                for future in wait(waiting, return_when=FIRST_COMPLETED)[0]:
                    if future in pending:
                        i = pending.pop(future)
                        try:
                            results[i] = future.result()
                        except Exception as exc:  # the pool's own (_run catches the items')
                            pool_failed(i, exc)
                            processes = 1  # nothing more to the pool
                        bar.update()
        except BaseException:  # Ctrl-C, or the stage stopped: end with the item this process is on
            stop.set()
            if workers is not None:  # no worker outlives an interrupted stage
                workers.shutdown(wait=False, kill_workers=True)
            raise
        here.result()  # re-raises what _run does not catch
    if ready is not None:  # still starting: of no use now
        workers.shutdown(wait=False, kill_workers=True)
    return results


def _import_ray():
    try:
        import ray
    except ImportError as exc:
        raise ImportError(RAY_MISSING) from exc
    return ray


def _map_ray(
    func: Callable, items: list, n_jobs: int, address: str | None, bar: tqdm
) -> list[ItemResult]:
    """Ray tasks, at most ``n_jobs`` in flight (-1: all at once), one CPU each.

    Joins the Ray this process already has, or starts one: a local Ray with ``n_jobs`` CPUs
    (``address`` None) or a connection to a cluster (``"auto"``, ``"ray://host:10001"``).
    """
    ray = _import_ray()
    if not ray.is_initialized():
        local = address is None and not os.environ.get("RAY_ADDRESS")
        ray.init(
            address=address,
            num_cpus=n_jobs if local and n_jobs > 0 else None,
            include_dashboard=False if local else None,
            logging_level=logging.WARNING,
        )
    task = ray.remote(num_cpus=1)(_run_in)
    func_ref = ray.put(func)  # shipped once, not once per item
    cwd = os.getcwd()
    limit = n_jobs if n_jobs > 0 else len(items)
    results: list[ItemResult | None] = [None] * len(items)
    queue = list(enumerate(items))[::-1]
    pending: dict[Any, int] = {}
    while queue or pending:
        while queue and len(pending) < limit:
            index, item = queue.pop()
            pending[task.remote(cwd, func_ref, item)] = index
        done, _ = ray.wait(list(pending), num_returns=1)
        for ref in done:
            index = pending.pop(ref)
            try:
                results[index] = ray.get(ref)
            except ray.exceptions.RayError as exc:  # the worker died (crash, memory, node lost)
                results[index] = ItemResult(
                    items[index], error=_reason(exc).splitlines()[0], details=str(exc),
                    retry=True,
                )  # fmt: skip
            bar.update()
    return results  # type: ignore[return-value]


def raise_first_error(results: list[ItemResult]) -> None:
    """Raise a RuntimeError naming every failed item, if any failed."""
    failed = [r for r in results if not r.ok]
    if failed:
        lines = "\n".join(f"  {r.item}: {r.error}" for r in failed)
        raise RuntimeError(
            f"{len(failed)} of {len(results)} items failed:\n{lines}\n\n{failed[0].details}"
        )
