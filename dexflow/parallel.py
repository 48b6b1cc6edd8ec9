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
import traceback
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Generic, TypeVar

from joblib import Parallel, delayed
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
            process, more (or -1 for all cores) uses joblib processes.
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


def _map_joblib(func: Callable, items: list, n_jobs: int, bar: tqdm) -> list[ItemResult]:
    """joblib processes. A worker that dies (killed by the OS for memory, a crash in native
    code) breaks the pool: the items without a result then fail with ``retry``."""
    runner = Parallel(n_jobs=n_jobs, return_as="generator")  # in input order, as they come
    results: list[ItemResult] = []
    try:
        for result in runner(delayed(_run)(func, item) for item in items):
            results.append(result)
            bar.update()
    except Exception as exc:  # only the pool itself raises here (_run catches the items')
        reason = _reason(exc).splitlines()[0].split(". ")[0]
        log.error("worker pool failed after %d of %d items: %s", len(results), len(items), reason)
        results += [
            ItemResult(item, error=f"no result, the worker pool failed ({reason})",
                       details=traceback.format_exc(), retry=True)
            for item in items[len(results):]
        ]  # fmt: skip
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
