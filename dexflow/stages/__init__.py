"""The pipeline's stages: one module per stage of ``dvc.yaml``, named like it, holding that
stage's math and its :class:`~dexflow.pipeline.runner.StageSpec` (``STAGE``).

``stages/<name>.py`` (the script DVC runs) imports ``dexflow.stages.<name>`` and nothing else
of dexflow. Stage modules never import each other: what two stages share lives below them
(:mod:`dexflow.measures`, :mod:`dexflow.sim`, :mod:`dexflow.io`, ...).
"""
