"""Benchmarks that print frames/s with ratios against a baseline measured in the same run.

- :mod:`~dexflow.tools.bench.kernels`: ``dexflow bench fk|retarget|refine|simulate``;
- :mod:`~dexflow.tools.bench.pipeline`: ``dexflow bench pipeline`` (every stage, worker counts);
- :mod:`~dexflow.tools.bench.long`: ``dexflow bench long`` (cost per frame on long sequences);
- :mod:`~dexflow.tools.bench.real`: ``dexflow bench real`` (real captures).
"""

from dexflow.tools.bench.kernels import bench_fk, bench_refine, bench_retarget, bench_simulate
from dexflow.tools.bench.long import bench_long
from dexflow.tools.bench.pipeline import bench_pipeline
from dexflow.tools.bench.real import bench_real, grasp_breakdown, refine_motion

__all__ = [
    "bench_fk",
    "bench_long",
    "bench_pipeline",
    "bench_real",
    "bench_refine",
    "bench_retarget",
    "bench_simulate",
    "grasp_breakdown",
    "refine_motion",
]
