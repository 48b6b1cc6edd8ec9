"""Items for the map tests that a worker process imports cheaply (numpy only, not a test module
with the stages behind it), so that a worker is ready in about a second."""

from __future__ import annotations

import multiprocessing
import os
import time
from pathlib import Path

import numpy as np

KEPT: list[np.ndarray] = []  # a per-process cache, like the hand model a stage builds once


def cache_then_work(item: tuple[int, Path]) -> int:
    """The worker's first item fills a 400 MB cache; this process leaves the items to the worker
    until it has done two. Returns the pid that ran the item."""
    x, done = item
    if multiprocessing.parent_process() is None:
        for _ in range(400):
            if len(list(done.iterdir())) >= 2:
                break
            time.sleep(0.05)
    elif not KEPT:
        KEPT.append(np.ones(50_000_000))  # pages touched: in the worker's resident size
    time.sleep(1.05)  # loky measures a worker's size at most once a second
    (done / f"{x}-{os.getpid()}").touch()
    return os.getpid()
