"""Hydra multirun over ``conf/`` without DVC experiments: one pipeline run per Hydra job.

``python -m dexflow.sweep -m contact.dis_min_m=0.008,0.010,0.012`` (or ``dexflow-sweep``)
composes ``conf/`` once per job, exactly as ``dvc exp run -S`` would, and runs the stages of
``dvc.yaml`` in dependency order (file order, a stage after those whose outputs it reads) inside
the job's directory (``multirun/<date>/<time>/<job>/``). A stage is
reused instead of run when

- its declared ``params`` have the same values in the job as in the project's ``params.yaml``
  (and in ``dvc.lock``, where the project has one: what its outputs were made with),
- its command, deps and outs interpolate to the same strings with the job's params (so a new
  ``data.root`` re-runs ``scale_align``),
- every stage upstream of it (whose outputs it depends on) was reused,
- the project has all of its outputs, and
- (``dexflow-sweep`` and the ablation suite: :func:`run_job`'s ``machine``) this machine made
  them, as the project's ``reports/timing/<stage>.json`` records (:mod:`dexflow.provenance`):
  outputs made on another machine, or without a record (restored from git or the DVC cache),
  are made again, so that the jobs compared with each other come from one machine.

A reused stage's cached outputs are symlinked into the job (``job/data/x -> project/data/x``);
its ``cache: false`` outputs (``reports/...``) are copied, so that each job has its own
``reports/metrics/*.json``, and so is its ``reports/timing`` record (where it ran). Reuse trusts
the project's outputs: run ``dvc repro`` (or check ``dvc status``) in the project first.

Each job directory ends up holding ``.hydra/`` (config, overrides), ``params.yaml``,
``reports/metrics/*.json``, the job's log and ``sweep_status.json``::

    {"status": "ok" | "failed", "stage": <failed stage or null>, "error": <reason or null>,
     "reused": [<stage>, ...], "ran": [<stage>, ...]}

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
import re
import shlex
import shutil
import subprocess
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dvc.utils.serialize import load_yaml  # YAML 1.2 as DVC reads it: `1e-05` is a float
from omegaconf import DictConfig, OmegaConf

from dexflow import provenance
from dexflow.config import load_params, project_root
from dexflow.errors import ConfigError

__all__ = ["Stage", "load_stages", "main", "run_job", "upstream_stages"]
log = logging.getLogger(__name__)

STATUS_FILE = "sweep_status.json"
METRICS_DIR, TIMING_DIR = "reports/metrics", "reports/timing"  # as dexflow.io.layout has them
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
_INTERPOLATION = re.compile(r"\$\{([^}]+)\}")
_PYTHON = ("python", "python3")


@dataclass(frozen=True)
class Stage:
    """One stage of ``dvc.yaml`` (a ``foreach`` stage gives one per item: ``name@key``).

    Attributes:
        name: ``contact``, ``retarget@dexflow``.
        cmd: The command, interpolated.
        deps: Dependency paths, relative to the project.
        params: Dotted keys of ``params.yaml`` the stage reads (``hand``, ``contact.dis_min_m``).
        outs: Cached outputs (``outs``/``metrics``/``plots`` without ``cache: false``).
        copies: ``cache: false`` outputs (reports: small, one copy per job).
        persist: Outputs marked ``persist: true``: not deleted before the stage runs.
    """

    name: str
    cmd: str
    deps: tuple[str, ...] = ()
    params: tuple[str, ...] = ()
    outs: tuple[str, ...] = ()
    copies: tuple[str, ...] = ()
    persist: tuple[str, ...] = ()

    @property
    def outputs(self) -> tuple[str, ...]:
        return self.outs + self.copies

    @property
    def tag(self) -> str:
        """The name of its ``reports/metrics`` and ``reports/timing`` files: its metrics file's
        (``demo@demo`` writes ``demo.json``), else ``name@item`` -> ``name_item``."""
        for path in self.copies:
            rel = Path(path)
            if rel.parent == Path(METRICS_DIR) and rel.suffix == ".json":
                return rel.stem
        return self.name.replace("@", "_")


@dataclass
class _Status:
    status: str = "ok"
    stage: str | None = None
    error: str | None = None
    reused: list[str] = field(default_factory=list)
    ran: list[str] = field(default_factory=list)

    def write(self, job_dir: Path) -> None:
        path = job_dir / STATUS_FILE
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(self.__dict__, indent=2) + "\n")
        os.replace(tmp, path)


def _lookup(context: Mapping[str, Any], dotted: str) -> Any:
    node: Any = context
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            raise KeyError(dotted)
        node = node[part]
    return node


def _interpolate(value: Any, context: Mapping[str, Any], where: str) -> Any:
    """``${item}``, ``${key}`` and ``${dotted.param}`` in strings, recursively."""
    if isinstance(value, list):
        return [_interpolate(v, context, where) for v in value]
    if isinstance(value, dict):
        return {
            _interpolate(k, context, where): _interpolate(v, context, where)
            for k, v in value.items()
        }
    if not isinstance(value, str):
        return value

    def substitute(match: re.Match) -> str:
        try:
            return str(_lookup(context, match.group(1).strip()))
        except KeyError:
            raise ConfigError(
                f"dvc.yaml stage '{where}': cannot interpolate ${{{match.group(1)}}}: "
                "no such key in params.yaml"
            ) from None

    return _INTERPOLATION.sub(substitute, value)


def _paths(entries: list | None, where: str) -> tuple[list[str], list[str], list[str]]:
    """Cached, ``cache: false`` and ``persist: true`` paths of an ``outs``/``metrics``/``plots``
    list."""
    cached, uncached, persist = [], [], []
    for entry in entries or []:
        if isinstance(entry, str):
            entry = {entry: None}
        if not (isinstance(entry, dict) and len(entry) == 1):
            raise ConfigError(f"dvc.yaml stage '{where}': cannot read output entry {entry!r}")
        ((path, options),) = entry.items()
        options = options or {}
        (cached if options.get("cache", True) else uncached).append(str(path))
        if options.get("persist", False):
            persist.append(str(path))
    return cached, uncached, persist


def _param_keys(entries: list | None, where: str) -> tuple[str, ...]:
    keys: list[str] = []
    for entry in entries or []:
        if isinstance(entry, str):
            keys.append(entry)
        elif isinstance(entry, dict) and set(entry) == {"params.yaml"}:
            keys += list(entry["params.yaml"] or [])
        else:
            raise ConfigError(
                f"dvc.yaml stage '{where}': params {entry!r}: dexflow.sweep reads only params "
                "from params.yaml"
            )
    return tuple(keys)


def _stage(name: str, body: dict, context: Mapping[str, Any]) -> Stage:
    unsupported = sorted(set(body) - {"cmd", "deps", "params", "outs", "metrics", "plots", "desc",
                                      "meta", "always_changed", "frozen"})  # fmt: skip
    if unsupported:
        raise ConfigError(f"dvc.yaml stage '{name}': dexflow.sweep does not support {unsupported}")
    body = _interpolate(body, context, name)
    cmd = body.get("cmd")
    if isinstance(cmd, list):
        cmd = " && ".join(cmd)
    if not isinstance(cmd, str) or not cmd.strip():
        raise ConfigError(f"dvc.yaml stage '{name}': expected a cmd, found {cmd!r}")
    outs, copies, persist = [], [], []
    for key in ("outs", "metrics", "plots"):
        cached, uncached, persisted = _paths(body.get(key), name)
        outs += cached
        copies += uncached
        persist += persisted
    for path in outs + copies:
        if Path(path).is_absolute() or ".." in Path(path).parts:
            raise ConfigError(
                f"dvc.yaml stage '{name}': output {path!r} is outside the project; a sweep job "
                "can only hold outputs relative to it"
            )
    return Stage(
        name=name,
        cmd=cmd,
        deps=tuple(str(d) for d in body.get("deps") or []),
        params=_param_keys(body.get("params"), name),
        outs=tuple(outs),
        copies=tuple(copies),
        persist=tuple(persist),
    )


def load_stages(dvc_yaml: str | Path, params: Mapping[str, Any]) -> list[Stage]:
    """The stages of ``dvc.yaml``, ``foreach`` expanded, interpolated, in the order they run:
    file order, except that a stage waits for the stages whose outputs it depends on (refine
    reads replay@retarget, written by a ``foreach`` stage further down).

    Args:
        dvc_yaml: The pipeline file.
        params: The contents of ``params.yaml`` that ``${...}`` refers to.

    Returns:
        One :class:`Stage` per stage; a ``foreach`` over a list gives ``name@<item>``, over a
        dict ``name@<key>`` (as DVC names them).

    Raises:
        ConfigError: a construct dexflow.sweep does not read (``matrix``, ``vars``, ``wdir``,
            params from other files), or an interpolation with no such key.
    """
    spec = load_yaml(dvc_yaml) or {}
    if "vars" in spec:
        raise ConfigError(f"{dvc_yaml}: dexflow.sweep does not support top-level 'vars'")
    stages = []
    for name, body in (spec.get("stages") or {}).items():
        if "foreach" in body:
            items = body["foreach"]
            if isinstance(items, str):  # ``foreach: ${dotted.param}``: the list or dict itself
                whole = _INTERPOLATION.fullmatch(items.strip())
                if whole is None:
                    raise ConfigError(
                        f"dvc.yaml stage '{name}': foreach {items!r} is not a list, a dict or "
                        "one ${param}"
                    )
                try:
                    items = _lookup(params, whole.group(1).strip())
                except KeyError:
                    raise ConfigError(
                        f"dvc.yaml stage '{name}': cannot interpolate {items}: no such key in "
                        "params.yaml"
                    ) from None
            pairs = items.items() if isinstance(items, dict) else ((i, i) for i in items)
            for key, item in pairs:
                context = {**params, "item": item, "key": key}
                stages.append(_stage(f"{name}@{key}", body["do"], context))
        else:
            stages.append(_stage(name, body, params))
    return _in_dependency_order(stages, dvc_yaml)


def _in_dependency_order(stages: list[Stage], where: str | Path) -> list[Stage]:
    """``stages`` reordered so that every stage comes after those whose outputs it depends on;
    otherwise in file order (the first stage that can run next runs next)."""
    producers = {s.name: {o.name for o in stages if _reads(s, o)} for s in stages}
    ordered: list[Stage] = []
    placed: set[str] = set()
    while len(ordered) < len(stages):
        ready = next((s for s in stages if s.name not in placed and producers[s.name] <= placed),
                     None)  # fmt: skip
        if ready is None:
            cycle = sorted(n for n in producers if n not in placed)
            raise ConfigError(f"{where}: the stages {cycle} depend on each other's outputs")
        ordered.append(ready)
        placed.add(ready.name)
    return ordered


def _overlaps(a: str, b: str) -> bool:
    pa, pb = Path(a).parts, Path(b).parts
    n = min(len(pa), len(pb))
    return pa[:n] == pb[:n]


def _reads(stage: Stage, other: Stage) -> bool:
    """Whether ``stage`` depends on an output of ``other`` (a dep equal to, inside or containing
    one of them)."""
    return other is not stage and any(
        _overlaps(dep, out) for dep in stage.deps for out in other.outputs
    )


def upstream_stages(stages: list[Stage]) -> dict[str, list[str]]:
    """For each stage, the earlier stages whose outputs it depends on (a dep equal to, inside
    or containing one of their outputs)."""
    upstream: dict[str, list[str]] = {}
    for i, stage in enumerate(stages):
        upstream[stage.name] = [other.name for other in stages[:i] if _reads(stage, other)]
    return upstream


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
        return _lookup(params, key)
    except KeyError:
        return None


def _why_not_reused(
    stage: Stage,
    project_stage: Stage | None,
    job_params: Mapping[str, Any],
    project_params: Mapping[str, Any],
    locked: Mapping[str, Any] | None,
    upstream_ran: list[str],
    root: Path,
    machine: str | None = None,
) -> str | None:
    """Why ``stage`` must run in the job, or None if the project's outputs can be reused.

    Args:
        locked: The stage's params as ``dvc.lock`` records them (dotted keys as in dvc.yaml),
            or None where the project has no lock entry for the stage.
        upstream_ran: The stages upstream of this one that ran in the job.
        machine: Reuse only outputs this machine id made (None: wherever made).
    """
    if upstream_ran:
        return f"upstream {', '.join(upstream_ran)} ran"
    if project_stage is None:
        return "the project's params.yaml is missing or does not fit dvc.yaml"
    if project_stage != stage:
        return "its cmd, deps or outs differ with the job's params"
    for key in stage.params:
        value = _get(job_params, key)
        differs = _difference(value, _get(project_params, key), key)
        if differs:
            return f"{differs} differs from the project's params.yaml"
        if locked is not None:
            differs = _difference(value, locked.get(key), key)
            if differs:
                return f"the project's outputs were made with another {differs} (dvc.lock)"
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


def _made_by(stage: Stage, root: Path) -> dict[str, Any] | None:
    """Who made the project's outputs of ``stage`` (:func:`dexflow.provenance.made_by`)."""
    record = provenance.read_records(root / TIMING_DIR).get(stage.tag)
    metrics_file = root / METRICS_DIR / f"{stage.tag}.json"
    metrics = None
    if f"{METRICS_DIR}/{stage.tag}.json" in stage.copies:
        try:
            metrics = json.loads(metrics_file.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
    return provenance.made_by(metrics, record)


def _remove(path: Path) -> None:
    if path.is_symlink() or path.is_file():
        path.unlink()
    elif path.is_dir():
        shutil.rmtree(path)


def _reuse(stage: Stage, root: Path, job_dir: Path) -> None:
    """Link (cached) or copy (``cache: false``) the project's outputs of ``stage`` into the
    job, with its ``reports/timing`` record, which says where they were made."""
    for rel in stage.outputs:
        src, dst = root / rel, job_dir / rel
        _remove(dst)
        dst.parent.mkdir(parents=True, exist_ok=True)
        if rel in stage.outs:
            dst.symlink_to(src, target_is_directory=src.is_dir())
        elif src.is_dir():
            shutil.copytree(src, dst, symlinks=True)
        else:
            shutil.copy2(src, dst)
    record = Path(TIMING_DIR) / f"{stage.tag}.json"
    _remove(job_dir / record)
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
            or any(_overlaps(dep, out) for s in stages for out in s.outputs)
        ):
            continue
        src, dst = root / rel, job_dir / rel
        if src.exists() and not (dst.exists() or dst.is_symlink()):
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.symlink_to(src, target_is_directory=src.is_dir())


def _command(cmd: str) -> str:
    """The stage's command with a leading ``python`` replaced by this interpreter."""
    parts = cmd.strip().split(maxsplit=1)
    if parts and parts[0] in _PYTHON:
        return " ".join([shlex.quote(sys.executable), *parts[1:]])
    return cmd


def _run_stage(stage: Stage, job_dir: Path) -> str | None:
    """Run ``stage.cmd`` in the job directory, streaming its output to the job's log.

    Returns:
        None on success, else a one-line reason (exit status and the last line it printed).
    """
    for rel in stage.outputs:
        out = job_dir / rel
        # Never write into the project through a link; and, as DVC does, a stage writes its
        # outputs from scratch unless they persist (resumable stages).
        if out.is_symlink() or rel not in stage.persist:
            _remove(out)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    last = ""
    with subprocess.Popen(
        _command(stage.cmd),
        shell=True,
        cwd=job_dir,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        bufsize=1,
    ) as proc:
        assert proc.stdout is not None
        for line in proc.stdout:
            line = line.rstrip()
            if line:
                log.info("[%s] %s", stage.name, line)
                last = line
    if proc.returncode == 0:
        return None
    reason = f"exit status {proc.returncode}"
    return f"{reason}: {last}" if last else reason


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
            (:func:`dexflow.provenance.machine_id`); None: wherever they were made.

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
        lock = (_load_yaml(root / "dvc.lock") or {}).get("stages", {})
        stages = load_stages(root / "dvc.yaml", job_params)
        project_stages: dict[str, Stage] = {}
        if project_params is not None:
            try:
                project_stages = {s.name: s for s in load_stages(root / "dvc.yaml", project_params)}
            except ConfigError as exc:
                log.warning("project params.yaml does not fit dvc.yaml (%s): reusing nothing", exc)
        upstream = upstream_stages(stages)
        for stage in stages:
            status.stage = stage.name
            entry = lock.get(stage.name)
            locked = ((entry.get("params") or {}).get("params.yaml") or {}) if entry else None
            reason = _why_not_reused(
                stage,
                project_stages.get(stage.name),
                job_params,
                project_params or {},
                locked,
                [u for u in upstream[stage.name] if u in status.ran],
                root,
                machine,
            )
            if reason is None:
                _reuse(stage, root, job_dir)
                status.reused.append(stage.name)
                log.info("stage %s: reused the project's outputs", stage.name)
                continue
            log.info("stage %s: running (%s)", stage.name, reason)
            _link_inputs(stage, stages, root, job_dir)
            status.status, status.error = "failed", UNFINISHED
            status.write(job_dir)  # what a killed job leaves behind
            error = _run_stage(stage, job_dir)
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
    """``dexflow-sweep`` / ``python -m dexflow.sweep``: Hydra's command line (``-m`` for a
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
