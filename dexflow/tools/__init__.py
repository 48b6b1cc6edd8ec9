"""Tools around the pipeline: the ``dexflow`` command line, benchmarks, Hydra sweeps, the
ablation suite and the rerun viewer. Nothing in the pipeline imports them."""
