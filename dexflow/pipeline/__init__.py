"""Pipeline plumbing, independent of what any stage computes.

- :mod:`dexflow.pipeline.registry`: the stages of ``dvc.yaml`` (deps, params, outputs, order)
  as one list that every runner reads;
- :mod:`dexflow.pipeline.executor`: runs a stage of the registry in a project or job folder;
- :mod:`dexflow.pipeline.validity`: the one key that says whether a stage's outputs are still
  valid;
- :mod:`dexflow.pipeline.runner`: the skeleton every stage script runs;
- :mod:`dexflow.pipeline.resume`: resumable per-sequence outputs;
- :mod:`dexflow.pipeline.parallel`: mapping items over processes, Ray or a cluster;
- :mod:`dexflow.pipeline.labelled`: inputs of the stages run per trajectory label;
- :mod:`dexflow.pipeline.provenance`: where and from what an output was made.
"""
