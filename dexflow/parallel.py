"""Map a function over independent items (sequences, objects) with per-item error capture.

Backends: ``sequential`` (n_jobs = 1) or local processes through joblib (n_jobs > 1 or -1).
Results come back in input order whatever the backend, so outputs are deterministic. An item
that raises does not stop the others: its error is returned in its :class:`ItemResult`.
"""

from __future__ import annotations

import logging
import traceback
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from joblib import Parallel, delayed
from tqdm.auto import tqdm

__all__ = ["ItemResult", "map_items", "raise_first_error"]

T = TypeVar("T")
log = logging.getLogger(__name__)


@dataclass
class ItemResult(Generic[T]):
    """Outcome of one item: ``value`` if it succeeded, else ``error`` (a one-line reason)."""

    item: Any
    value: T | None = None
    error: str | None = None
    details: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None

    def entry(self) -> dict:
        """Summary entry: ``{"status": "ok", **value}`` or ``{"status": "failed", "error": ...}``."""
        if self.ok:
            return {"status": "ok", **(self.value or {})}
        return {"status": "failed", "error": self.error}


def _run(func: Callable[[Any], T], item: Any) -> ItemResult[T]:
    try:
        return ItemResult(item, value=func(item))
    except Exception as exc:  # one bad item must not take the others down (DESIGN §8)
        return ItemResult(
            item, error=f"{type(exc).__name__}: {exc}", details=traceback.format_exc()
        )


def map_items(
    func: Callable[[Any], T],
    items: Iterable[Any],
    n_jobs: int = 1,
    desc: str = "items",
    progress: bool = True,
) -> list[ItemResult[T]]:
    """Apply ``func`` to every item; never raises for an item's own error.

    Args:
        func: Function of one item. With ``n_jobs != 1`` it is pickled (cloudpickle) to workers.
        items: The items.
        n_jobs: 1 runs in this process; more (or -1 for all cores) uses joblib processes.
        desc: Label of the progress bar.
        progress: Show a tqdm progress bar.

    Returns:
        One :class:`ItemResult` per item, in input order.
    """
    items = list(items)
    if n_jobs == 1 or len(items) <= 1:
        results = [_run(func, item) for item in tqdm(items, desc=desc, disable=not progress)]
    else:
        runner = Parallel(n_jobs=n_jobs, return_as="generator")
        stream = runner(delayed(_run)(func, item) for item in items)
        results = list(tqdm(stream, total=len(items), desc=desc, disable=not progress))
    for result in results:
        if not result.ok:
            log.error("%s %s failed: %s", desc, result.item, result.error)
    return results


def raise_first_error(results: list[ItemResult]) -> None:
    """Raise a RuntimeError naming every failed item, if any failed."""
    failed = [r for r in results if not r.ok]
    if failed:
        lines = "\n".join(f"  {r.item}: {r.error}" for r in failed)
        raise RuntimeError(
            f"{len(failed)} of {len(results)} items failed:\n{lines}\n\n{failed[0].details}"
        )
