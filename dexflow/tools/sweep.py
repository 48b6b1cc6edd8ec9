"""Hydra multirun over ``conf/`` without DVC experiments: one pipeline run per Hydra job.

``python -m dexflow.tools.sweep -m contact.dis_min_m=0.008,0.010,0.012`` (or ``dexflow-sweep``)
composes ``conf/`` once per job, exactly as ``dvc exp run -S`` would, and runs the stages of
``dvc.yaml`` in dependency order (file order, a stage after those whose outputs it reads) inside
the job's directory (``multirun/<date>/<time>/<job>/``). Whether a stage's outputs can be
used without running it is decided by one key (:mod:`dexflow.pipeline.validity`: the stage's
command, its declared params' values and the bytes of its deps, what DVC's lock records): the
key the stage has in the job, computed before it would run, against the key recorded with the
outputs in ``reports/timing/<tag>.json``. A stage is

- **kept** when the job already holds its own outputs made with that key (an ablation
  experiment run before in the same folder);
- **reused** when the project's outputs were made with that key and all exist, and
  (``dexflow-sweep`` and the ablation suite: :func:`run_job`'s ``machine``) this machine made
  them, as the project's ``reports/timing/<tag>.json`` records
  (:mod:`dexflow.pipeline.provenance`), so that the jobs compared with each other come from one
  machine. Outputs without a recorded key or machine (restored from git or the DVC cache) are
  made again;
- **run** otherwise, by :func:`dexflow.pipeline.executor.run_command`, which records the key
  with the outputs. An upstream stage that ran in the job changes the key of what reads its
  outputs unless it wrote the same bytes.

A reused stage's cached outputs are symlinked into the job (``job/data/x -> project/data/x``);
its ``cache: false`` outputs (``reports/...``) are copied, so that each job has its own
``reports/metrics/*.json``, and so is its ``reports/timing`` record (where it ran). Reuse trusts
the project's outputs: run ``dvc repro`` (or check ``dvc status``) in the project first.

Each job directory ends up holding ``.hydra/`` (config, overrides), ``params.yaml``,
``reports/metrics/*.json``, the job's log and ``sweep_status.json``::

    {"status": "ok" | "failed", "stage": <failed stage or null>, "error": <reason or null>,
     "kept": [<stage>, ...], "reused": [<stage>, ...], "ran": [<stage>, ...]}

which ``dexflow report ablation --multirun <dir>`` reads. ``stage`` is ``"params"`` when the
composed config fails validation and ``"dvc.yaml"`` when the pipeline cannot be read; a job
killed midway is left ``failed`` in the stage it was running. A failing stage fails only its
job: the job records it and returns, the other jobs go on. Hydra launchers fan the jobs out:
``hydra/launcher=joblib`` (local processes), ``ray`` or ``submitit_slurm``.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dvc.utils.serialize import load_yaml  # YAML 1.2 as DVC reads it: `1e-05` is a float
from omegaconf import DictConfig, OmegaConf

from dexflow.config import load_params, project_root
from dexflow.errors import ConfigError
from dexflow.pipeline import provenance
from dexflow.pipeline.executor import TIMING_DIR, recorded_key, remove_path, run_command
from dexflow.pipeline.registry import (
    METRICS_DIR,
    Stage,
    load_stages,
    lookup,
    overlaps,
)
from dexflow.pipeline.validity import params_values, stage_key

__all__ = ["main", "run_job"]
log = logging.getLogger(__name__)

STATUS_FILE = "sweep_status.json"
UNFINISHED = "did not finish (interrupted?)"  # the status a job holds while a stage runs
APP_CONFIG = "dexflow_sweep"
# Symlinked into every job so that stage commands (`python stages/x.py`) and
# `dexflow.config.project_root()` (conf/hand) work wherever the sweep directory is.
PROJECT_LINKS = ("conf", "stages")
INPUT_DIR = ("data",)  # raw inputs that no stage writes live here (data.root)
HELP_HEADER = """dexflow-sweep: the pipeline of dvc.yaml once per Hydra job, in the job's directory,
reusing the project's outputs where a job's params leave a stage unchanged.

  dexflow-sweep -m contact.dis_min_m=0.008,0.010,0.012
  dexflow-sweep -m hydra/launcher=joblib hydra.launcher.n_jobs=2 hand=shadow,allegro

Results: multirun/<date>/<time>/<job>/ (params.yaml, reports/metrics, sweep_status.json);
summarise them with `dexflow report ablation --multirun multirun/<date>/<time>`.
"""
_PYTHON = ("python", "python3")


@dataclass
class _Status:
    status: str = "ok"
    stage: str | None = None
    error: str | None = None
    kept: list[str] = field(default_factory=list)
    reused: list[str] = field(default_factory=list)
    ran: list[str] = field(default_factory=list)

    def write(self, job_dir: Path) -> None:
        path = job_dir / STATUS_FILE
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(self.__dict__, indent=2) + "\n")
        os.replace(tmp, path)


def _difference(a: Any, b: Any, key: str) -> str | None:
    """The first dotted key at or under ``key`` where ``a`` and ``b`` differ, or None."""
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        for sub in (*a, *(k for k in b if k not in a)):
            found = _difference(a.get(sub), b.get(sub), f"{key}.{sub}")
            if found:
                return found
        return None
    return None if a == b else key


def _get(params: Mapping[str, Any], key: str) -> Any:
    try:
        return lookup(params, key)
    except KeyError:
        return None


def _why_differs(stage: Stage, job_params: Mapping[str, Any], project_params: Any) -> str:
    """Which of the stage's params differs from the project's ``params.yaml``, to say why the
    keys differ (the decision is the key's, not this)."""
    for key in stage.params:
        differs = _difference(_get(job_params, key), _get(project_params or {}, key), key)
        if differs:
            return f"{differs} differs from the project's"
    return (
        "its command or the bytes of a dep differ from those the project's outputs were made from"
    )


def _why_not_reused(
    stage: Stage,
    key: str,
    job_params: Mapping[str, Any],
    project_params: Any,
    root: Path,
    machine: str | None = None,
) -> str | None:
    """Why ``stage``, whose key in the job is ``key``, must run in the job, or None if the
    project's outputs can be reused: they exist and were made with the same key (and, with
    ``machine``, by this machine)."""
    recorded = recorded_key(stage, root)
    if recorded is None:
        return f"no key recorded with the project's outputs ({TIMING_DIR}/{stage.tag}.json)"
    if recorded != key:
        return _why_differs(stage, job_params, project_params)
    missing = [p for p in stage.outputs if not (root / p).exists()]
    if missing:
        return f"the project has no {', '.join(missing)}"
    if machine is not None:
        made = _made_by(stage, root)
        if made is None:
            return (
                f"no record of the machine that made the project's outputs "
                f"({TIMING_DIR}/{stage.tag}.json)"
            )
        if made.get("machine_id") != machine:
            return f"the project's outputs were made on machine {made.get('machine_id')}"
    return None


def _kept(stage: Stage, key: str, job_dir: Path, machine: str | None) -> bool:
    """Whether the job holds its own outputs of ``stage`` made with ``key`` (an experiment run
    before in the same folder; with ``machine``, made by that machine), which it keeps."""
    if recorded_key(stage, job_dir) != key:
        return False
    if not all((job_dir / p).exists() and not (job_dir / p).is_symlink() for p in stage.outputs):
        return False
    return machine is None or (_made_by(stage, job_dir) or {}).get("machine_id") == machine


def _made_by(stage: Stage, root: Path) -> dict[str, Any] | None:
    """Who made the project's outputs of ``stage`` (:func:`dexflow.pipeline.provenance.made_by`)."""
    record = provenance.read_records(root / TIMING_DIR).get(stage.tag)
    metrics_file = root / METRICS_DIR / f"{stage.tag}.json"
    metrics = None
    if f"{METRICS_DIR}/{stage.tag}.json" in stage.copies:
        try:
            metrics = json.loads(metrics_file.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
    return provenance.made_by(metrics, record)


def _reuse(stage: Stage, root: Path, job_dir: Path) -> None:
    """Link (cached) or copy (``cache: false``) the project's outputs of ``stage`` into the
    job, with its ``reports/timing`` record, which says where they were made."""
    for rel in stage.outputs:
        src, dst = root / rel, job_dir / rel
        remove_path(dst)
        dst.parent.mkdir(parents=True, exist_ok=True)
        if rel in stage.outs:
            dst.symlink_to(src, target_is_directory=src.is_dir())
        elif src.is_dir():
            shutil.copytree(src, dst, symlinks=True)
        else:
            shutil.copy2(src, dst)
    record = Path(TIMING_DIR) / f"{stage.tag}.json"
    remove_path(job_dir / record)
    if (root / record).is_file():
        (job_dir / record).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(root / record, job_dir / record)


def _link_inputs(stage: Stage, stages: list[Stage], root: Path, job_dir: Path) -> None:
    """Symlink the stage's raw inputs (deps under ``data/`` that no stage writes, such as a
    converted dataset at ``data.root``) from the project into the job."""
    for dep in stage.deps:
        rel = Path(dep)
        if (
            rel.is_absolute()
            or rel.parts[:1] != INPUT_DIR
            or any(overlaps(dep, out) for s in stages for out in s.outputs)
        ):
            continue
        src, dst = root / rel, job_dir / rel
        if src.exists() and not (dst.exists() or dst.is_symlink()):
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.symlink_to(src, target_is_directory=src.is_dir())


def _load_yaml(path: Path) -> Any:
    return load_yaml(path) if path.is_file() else None


def run_job(
    cfg: DictConfig, root: str | Path, job_dir: str | Path, machine: str | None = None
) -> dict:
    """Run the pipeline for one composed config in ``job_dir``, reusing the project's outputs.

    Args:
        cfg: The composed config (no ``hydra`` node), as the Hydra task function receives it.
        root: The project: ``conf/``, ``stages/``, ``dvc.yaml``, ``params.yaml``, ``data/``.
        job_dir: Where to write (Hydra's ``hydra.runtime.output_dir``); not the project.
        machine: Reuse only the project's outputs that this machine id made
            (:func:`dexflow.pipeline.provenance.machine_id`); None: wherever they were made.

    Returns:
        The status written to ``job_dir/sweep_status.json``. Never raises for a failing stage
        or an invalid config: those are recorded, so that the other jobs of a sweep go on.
    """
    root, job_dir = Path(root).resolve(), Path(job_dir).resolve()
    if job_dir == root:
        raise ConfigError(f"the sweep job directory is the project itself ({root})")
    job_dir.mkdir(parents=True, exist_ok=True)
    status = _Status()
    try:
        status.stage = "params"
        params_file = job_dir / "params.yaml"
        params_file.write_text(OmegaConf.to_yaml(cfg, resolve=True), encoding="utf-8")
        load_params(params_file)
        for name in PROJECT_LINKS:
            link = job_dir / name
            if not link.exists() and (root / name).is_dir():
                link.symlink_to(root / name, target_is_directory=True)

        status.stage = "dvc.yaml"
        job_params = _load_yaml(params_file) or {}
        project_params = _load_yaml(root / "params.yaml")
        stages = load_stages(root / "dvc.yaml", job_params)
        key_params = params_values(params_file)
        for stage in stages:
            status.stage = stage.name
            _link_inputs(stage, stages, root, job_dir)  # raw inputs, which the key reads
            key = stage_key(stage, key_params, job_dir)
            if _kept(stage, key, job_dir, machine):
                status.kept.append(stage.name)
                log.info("stage %s: kept the job's own outputs (same key)", stage.name)
                continue
            reason = _why_not_reused(stage, key, job_params, project_params, root, machine)
            if reason is None:
                _reuse(stage, root, job_dir)
                status.reused.append(stage.name)
                log.info("stage %s: reused the project's outputs", stage.name)
                continue
            log.info("stage %s: running (%s)", stage.name, reason)
            status.status, status.error = "failed", UNFINISHED
            status.write(job_dir)  # what a killed job leaves behind
            error = run_command(stage, job_dir, key)
            if error is not None:
                status.error = error
                break
            status.ran.append(stage.name)
            status.status, status.error = "ok", None
        else:
            status.stage = None
    except Exception as exc:  # a broken job must not stop the sweep's other jobs
        status.status, status.error = "failed", f"{type(exc).__name__}: {exc}"
        if not isinstance(exc, ConfigError):
            log.exception("job failed at %s", status.stage)
    if status.status == "failed":
        log.error("job failed at %s: %s", status.stage, status.error)
    else:
        log.info("job done: reused %s; ran %s", status.reused, status.ran)
    status.write(job_dir)
    return dict(status.__dict__)


def _register_app_config(root: Path) -> None:
    """The app's primary config: the project's ``config`` plus where Hydra writes the jobs."""
    from hydra.core.config_store import ConfigStore

    base = root.as_posix()
    stamp = "${now:%Y-%m-%d}/${now:%H-%M-%S}"
    ConfigStore.instance().store(
        name=APP_CONFIG,
        node={
            "defaults": ["config", "_self_"],
            "hydra": {
                "run": {"dir": f"{base}/outputs/{stamp}"},
                "sweep": {"dir": f"{base}/multirun/{stamp}", "subdir": "${hydra.job.num}"},
                "job": {"chdir": True},
                "help": {"app_name": "dexflow-sweep", "header": HELP_HEADER},
            },
        },
    )


def main() -> None:
    """``dexflow-sweep`` / ``python -m dexflow.tools.sweep``: Hydra's command line (``-m`` for a
    multirun, ``--help``, ``--cfg job``, overrides, ``hydra/launcher=...``)."""
    import hydra

    try:
        root = project_root()
    except ConfigError as exc:
        sys.exit(f"dexflow-sweep: {exc}")
    _register_app_config(root)

    def sweep_job(cfg: DictConfig) -> dict:
        from hydra.core.hydra_config import HydraConfig

        return run_job(cfg, root, HydraConfig.get().runtime.output_dir, provenance.machine_id())

    app = hydra.main(config_path=str(root / "conf"), config_name=APP_CONFIG, version_base="1.3")
    app(sweep_job)()


if __name__ == "__main__":
    main()
