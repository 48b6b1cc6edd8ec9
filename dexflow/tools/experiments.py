"""The comparison of experiments: ``dexflow report ablation`` -> ``reports/sweep.md``.

:func:`write_ablation` writes every experiment found in ``dvc exp show --json``
(:func:`collect_dvc`) and/or Hydra multirun directories (:func:`collect_multirun`), one table
and one plot per swept parameter, best values in bold. Failed or incomplete experiments are
listed, never dropped; runs of another machine than the one compared are listed, not compared.
It opens with its provenance (:mod:`dexflow.pipeline.provenance`), as the summary does.
``dexflow exp`` (:mod:`dexflow.tools.headline`) reads the same experiments.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dexflow.pipeline import provenance
from dexflow.stages.report import METHOD_LABELS, METRICS, cell, pyplot, save_figure
from dexflow.tools.ablation import metric_label

__all__ = ["Experiment", "collect_dvc", "collect_multirun", "swept_factors", "write_ablation"]


@dataclass
class Experiment:
    """One run of the pipeline: its parameters (flat, dotted keys), metrics (flat) and, per
    stage, who made its outputs (:func:`dexflow.pipeline.provenance.made_by`: machine, commit; None
    where not recorded)."""

    name: str
    source: str
    params: dict[str, object] = field(default_factory=dict)
    metrics: dict[str, float] = field(default_factory=dict)
    error: str | None = None
    stages: dict[str, dict | None] = field(default_factory=dict)
    rev: str | None = None  # the git commit of a DVC experiment

    @property
    def machine(self) -> str | None:
        """The machine id that made every stage's outputs; None if one is not recorded or
        several machines made them."""
        return provenance.machine_of(self.stages)

    def machine_text(self) -> str:
        """The machine id, ``not recorded`` or ``mixed: a, b``."""
        if self.machine:
            return self.machine
        ids = sorted({str(s["machine_id"]) for s in self.stages.values() if s})
        if len(ids) > 1:
            return "mixed: " + ", ".join(ids)
        unknown = sorted(tag for tag, s in self.stages.items() if not s)
        return "not recorded" + (f" ({', '.join(unknown)})" if ids and unknown else "")


def _flatten(tree, prefix: str = "") -> dict:
    out = {}
    if isinstance(tree, dict):
        for key, value in tree.items():
            out.update(_flatten(value, f"{prefix}{key}."))
    elif isinstance(tree, list):
        out[prefix[:-1]] = json.dumps(tree)
    else:
        out[prefix[:-1]] = tree
    return out


def _metrics_only(files: dict) -> dict[str, float]:
    """Flat numeric metrics from ``{file: {"data": {...}}}`` (DVC) or ``{file: {...}}``."""
    out = {}
    for path, content in sorted(files.items()):
        data = content.get("data", content) if isinstance(content, dict) else {}
        prefix = "" if Path(path).stem == "metrics" else f"{Path(path).stem}."
        for key, value in _flatten(data).items():
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                out[prefix + key] = float(value)
    return out


def collect_dvc(show: list | dict, timing_dir: str | Path | None = None) -> list[Experiment]:
    """Experiments from the output of ``dvc exp show --json`` (DVC 3).

    Args:
        show: The parsed output.
        timing_dir: The workspace's ``reports/timing``: the machine that made each stage's
            metrics is known where its record lists their digest (the stages that ran in this
            workspace, ``dvc exp run`` ones included); None: no machine is known.
    """
    records = provenance.read_records(timing_dir)
    found: list[Experiment] = []

    def visit(node, name_hint: str, state: str | None = None) -> None:
        if isinstance(node, list):
            for item in node:
                visit(item, name_hint, state)
            return
        if not isinstance(node, dict):
            return
        executor = node.get("executor")
        if isinstance(executor, dict) and executor.get("state"):
            state = executor["state"]  # queued, running, success, failed
        data = node.get("data")
        if isinstance(data, dict) and ("params" in data or "metrics" in data):
            name = node.get("name") or data.get("name") or node.get("rev") or name_hint
            params = {}
            for content in (data.get("params") or {}).values():
                params.update(_flatten(content.get("data", {})))
            files = data.get("metrics") or {}
            metrics = _metrics_only(files)
            stages = {
                Path(path).stem: provenance.made_by(
                    content.get("data", content), records.get(Path(path).stem)
                )
                for path, content in sorted(files.items())
                if isinstance(content, dict)
            }
            error = node.get("error") or data.get("error")
            if isinstance(error, dict):
                error = error.get("msg") or json.dumps(error)
            if error is None and state not in (None, "success"):
                error = f"{state}, not finished (its metrics would be the baseline's)"
            rev = node.get("rev") or data.get("rev")
            found.append(Experiment(str(name), "dvc", params, metrics, error, stages, rev))
        for key in ("experiments", "revs"):
            if key in node:
                visit(node[key], name_hint, state)

    visit(show, "workspace")
    unique, seen, contents = [], set(), {}
    for exp in found:
        key = json.dumps([exp.params, exp.metrics], sort_keys=True, default=str)
        if exp.name in seen:
            continue
        if key in contents and exp.metrics:  # the workspace holding an experiment's results
            if contents[key].name == "workspace":
                unique[unique.index(contents[key])] = exp
                contents[key] = exp
            continue
        seen.add(exp.name)
        contents[key] = exp
        unique.append(exp)
    return unique


def collect_multirun(root) -> list[Experiment]:
    """Experiments from a Hydra multirun directory (one job per subdirectory holding
    ``params.yaml``, ``reports/metrics/*.json``, ``reports/timing/*.json`` (where each stage
    ran; :func:`dexflow.tools.sweep.run_job` copies the records of the stages it reuses) and
    ``sweep_status.json``)."""
    import yaml

    root = Path(root)
    found = []
    for job in sorted(p.parent for p in root.rglob("params.yaml")):
        params = _flatten(yaml.safe_load((job / "params.yaml").read_text()) or {})
        files = {
            str(p.relative_to(job)): json.loads(p.read_text())
            for p in sorted((job / "reports" / "metrics").glob("*.json"))
        }
        status_file = job / "sweep_status.json"
        status = json.loads(status_file.read_text()) if status_file.is_file() else {}
        error = None
        if status.get("status") not in (None, "ok"):
            error = f"stage {status.get('stage')}: {status.get('error')}"
        name = str(job.relative_to(root)) if job != root else root.name
        stages = provenance.stages_of(job / "reports" / "metrics", job / "reports" / "timing")
        metrics = _metrics_only(files) | _speeds(job / "reports" / "timing")
        found.append(Experiment(name, "multirun", params, metrics, error, stages))
    return found


def _speeds(timing_dir: Path) -> dict[str, float]:
    """``timing.<stage>.frames_per_second`` of each stage's record in ``reports/timing``."""
    out = {}
    for path in sorted(timing_dir.glob("*.json")):
        speed = json.loads(path.read_text()).get("frames_per_second")
        if isinstance(speed, (int, float)) and not isinstance(speed, bool):
            out[f"timing.{path.stem}.frames_per_second"] = float(speed)
    return out


def _swept(experiments: list[Experiment], skip: tuple[str, ...] = ("data.", "hydra.")) -> list[str]:
    keys = sorted({k for e in experiments for k in e.params})
    return [
        k
        for k in keys
        if len({_canon(e.params.get(k)) for e in experiments}) > 1 and not k.startswith(skip)
    ]


def _canon(value) -> str:
    return json.dumps(value, sort_keys=True, default=str)


@dataclass
class _Factor:
    """Swept keys that vary together (every ``hand.*`` key when the hand is swept)."""

    name: str
    keys: list[str]

    def value(self, experiment: Experiment) -> str:
        return _canon(experiment.params.get(self.name))


def swept_factors(
    experiments: list[Experiment], skip: tuple[str, ...] = ("data.", "hydra.")
) -> list[_Factor]:
    """The swept keys (but those starting with ``skip``) grouped into factors: keys that split
    the experiments the same way are one factor, named by its most telling key (``*.name``,
    then the shortest)."""
    by_split: dict[tuple, list[str]] = {}
    for key in _swept(experiments, skip):
        labels: dict[str, int] = {}
        split = tuple(
            labels.setdefault(_canon(e.params.get(key)), len(labels)) for e in experiments
        )
        by_split.setdefault(split, []).append(key)
    factors = []
    for keys in by_split.values():
        name = min(keys, key=lambda k: (not k.endswith(".name"), k.count("."), k))
        factors.append(_Factor(name, [name, *(k for k in keys if k != name)]))
    return sorted(factors, key=lambda f: f.name)


def _reference(factor: _Factor, experiments: list[Experiment]) -> str:
    """The value most experiments have (ties: the first experiment's)."""
    values = [factor.value(e) for e in experiments]
    return max(dict.fromkeys(values), key=values.count)


def write_ablation(
    experiments: list[Experiment],
    out_md,
    figures_dir,
    metrics=None,
    machine: str | None = None,
) -> Path:
    """Write the ablation report: per swept parameter a table (one row per value) and a plot of
    each metric against it; the best value per metric in bold.

    With ``machine``, only experiments whose every stage was made on that machine are compared
    (the reference values' runs included): one made elsewhere, or without a record of where
    (:attr:`Experiment.machine`), is listed as not compared, since a difference between
    machines would read as the parameter's. Without, every complete experiment is compared and
    the report says whether they are known to come from one machine.

    Parameters that change together (all ``hand.*`` keys of ``hand=allegro``) are one factor,
    shown once under its most telling key. With several factors swept, each factor's table holds
    the experiments where every other factor is at its reference value (the value most
    experiments share), one factor at a time; the closing table lists every experiment.

    Args:
        experiments: From :func:`collect_dvc` and/or :func:`collect_multirun`.
        out_md: The Markdown file.
        figures_dir: Where the PNGs go.
        metrics: Flat metric keys to show; default: the paper's metrics for every method.
        machine: The machine id (:func:`dexflow.pipeline.provenance.machine_id`) whose runs are
            compared; None: every complete run.
    """
    from dexflow.io.atomic import atomic_path

    out_md, figures_dir = Path(out_md), Path(figures_dir)
    finished = [e for e in experiments if e.error is None and e.metrics]
    complete = [e for e in finished if machine is None or e.machine == machine]
    elsewhere = [e for e in finished if e not in complete]
    broken = [e for e in experiments if e not in finished]
    if metrics is None:
        metrics = [
            f"{m}.{k}"
            for m in METHOD_LABELS
            for k in ("ssr", "pd_mm", "cd_mm", "keypoint_error_mm")
        ] + ["retarget.rms_acc", "retarget.velocity_kl", "contact.flicker_final"]
    shown = [m for m in metrics if any(m in e.metrics for e in complete)]
    lines = [
        "# dexflow sweep report",
        "",
        f"Generated by `dexflow report ablation` from {len(experiments)} experiments "
        f"({len(complete)} compared, {len(elsewhere)} not compared: made on another machine "
        f"or not recorded where, {len(broken)} failed or without metrics). "
        "Best value per column in **bold**; ↑ higher is better, ↓ lower.",
        "",
        "Written by:",
        "",
        *provenance.markdown(None, _experiments_data(complete)),
        "",
        _machine_statement(complete, elsewhere, machine),
        "",
    ]
    factors = swept_factors(complete)
    if not factors:
        lines += ["No parameter differs between the complete experiments.", ""]
    reference = {f.name: _reference(f, complete) for f in factors}
    plt = pyplot()
    for factor in factors:
        others = [f for f in factors if f is not factor]
        members = [e for e in complete if all(f.value(e) == reference[f.name] for f in others)]
        held = bool(others)
        if len({factor.value(e) for e in members}) < 2:  # never swept alone: show every run
            members, held = complete, False
        groups: dict[str, list[Experiment]] = {}
        for e in members:
            groups.setdefault(factor.value(e), []).append(e)
        values = sorted(groups, key=_sort_key)
        table = {m: [_mean([e.metrics.get(m) for e in groups[v]]) for v in values] for m in shown}
        lines += [f"## `{factor.name}`", ""]
        if len(factor.keys) > 1:
            also = ", ".join(f"`{k}`" for k in factor.keys[1:6])
            more = f" and {len(factor.keys) - 6} more" if len(factor.keys) > 6 else ""
            lines += [f"Changes together with {also}{more}.", ""]
        if held:
            at = ", ".join(f"`{f.name}` = {json.loads(reference[f.name])}" for f in others)
            lines += [f"Other swept parameters held at {at}.", ""]
        elif others:
            lines += ["Other swept parameters vary within the rows (means over runs).", ""]
        lines += _ablation_table(values, groups, table, shown)
        drawn = [m for m in HEADLINE if m in shown]
        flat = [m for m in drawn if _flat(table[m])]
        drawn = [m for m in drawn if m not in flat]
        if drawn:
            name = "ablation_" + "".join(c if c.isalnum() else "_" for c in factor.name) + ".png"
            runs = [len(groups[v]) for v in values]
            _ablation_plot(plt, factor.name, values, table, drawn, figures_dir / name, runs)
            rel = figures_dir.relative_to(out_md.parent) if figures_dir.is_relative_to(
                out_md.parent) else figures_dir  # fmt: skip
            lines += ["", f"![{factor.name}]({rel / name})"]
        if shown:
            lines += ["", _figure_note(drawn, flat)]
        lines.append("")
    plt.close("all")
    overview = [m for m in ("refine.ssr", "refine.pd_mm", "retarget.keypoint_error_mm")
                if m in shown]  # fmt: skip
    lines += [
        "## Experiments",
        "",
        "| experiment | source | status | swept values | "
        + " | ".join(_metric_label(m) for m in overview)
        + " | machine |",
        "|---" * (5 + len(overview)) + "|",
    ]
    for e in experiments:
        if e in complete:
            status = "ok"
        elif e in elsewhere:
            status = "not compared: " + (
                f"made on machine {e.machine}" if e.machine else "not recorded on which machine"
            )
        else:
            status = f"failed: {e.error or 'no metrics'}"
        values = ", ".join(f"{f.name}={e.params.get(f.name)}" for f in factors) or "—"
        cells = [cell(e.metrics.get(m) if e in complete else None, 3) for m in overview]
        lines.append(
            f"| {e.name} | {e.source} | {status.replace('|', '/')} | {values} | "
            + " | ".join(cells)
            + f" | {e.machine_text()} |"
        )
    with atomic_path(out_md) as tmp:
        tmp.write_text("\n".join(lines).rstrip() + "\n")
    return out_md


def _experiments_data(experiments: list[Experiment]) -> str:
    """The data of the compared runs (name, sequences, frames), each distinct one once."""
    texts = [
        provenance.data_text(
            e.params.get("data.name"),
            e.metrics.get("num_input_sequences", e.metrics.get("num_sequences")),
            e.metrics.get("num_frames"),
        )
        for e in experiments
    ]
    return "; ".join(dict.fromkeys(texts)) or "no run compared"


def _machine_statement(complete: list[Experiment], elsewhere: list[Experiment], machine) -> str:
    """Which machine the compared runs (the reference values' included) were made on."""
    if machine is not None:
        text = (
            f"Compared: the runs whose every stage was made on machine {machine}"
            + (" (this machine)" if machine == provenance.machine_id() else "")
            + ", so every value, the reference's included, comes from that one machine."
        )
        if elsewhere:
            text += (
                f" {len(elsewhere)} made on another machine, or without a record of where, are "
                "listed under *Experiments* and not compared: rerun them here."
            )
        return text
    ids = {e.machine for e in complete}
    if len(ids) == 1 and None not in ids:
        return f"All {len(complete)} compared runs were made on machine {ids.pop()}."
    known = sorted(i for i in ids if i)
    unknown = sum(e.machine is None for e in complete)
    return (
        f"**Not checked to come from one machine**: made on {len(known)} known machine(s)"
        + (f", {unknown} run(s) without a record of where" if unknown else "")
        + "; a difference between runs of different machines may be the machines'. "
        "`dexflow report ablation` compares only runs of this machine unless given "
        "`--any-machine`."
    )


def _ablation_table(values: list[str], groups: dict, table: dict, shown: list[str]) -> list[str]:
    """One row per value; the best of each metric in bold where the values differ."""
    head = [_metric_label(m) for m in shown]
    lines = ["| value | runs | " + " | ".join(head) + " |", "|---" * (len(shown) + 2) + "|"]
    for i, v in enumerate(values):
        cells = []
        for m in shown:
            text = cell(table[m][i], 3)
            finite = [x for x in table[m] if math.isfinite(x)]
            higher = metric_label(m)[2]
            distinct = len(finite) > 1 and max(finite) > min(finite)
            best = (max if higher else min)(finite) if distinct else None
            cells.append(f"**{text}**" if best is not None and table[m][i] == best else text)
        lines.append(f"| {json.loads(v)} | {len(groups[v])} | " + " | ".join(cells) + " |")
    return lines


# The metrics an ablation figure draws (at most 8): the headline of each question; the table
# beside it holds every metric.
HEADLINE = (
    "refine.ssr", "refine.pd_mm", "refine.cd_mm", "refine.keypoint_error_mm",
    "retarget.keypoint_error_mm", "retarget.rms_acc", "retarget.velocity_kl",
    "contact.flicker_final",
)  # fmt: skip


def _flat(values: list[float]) -> bool:
    """No finite value differs from the others by more than 1e-9 of their size (or none is
    finite): a panel of it would be a flat line."""
    finite = [v for v in values if math.isfinite(v)]
    if len(finite) < 2:
        return True
    return max(finite) - min(finite) <= 1e-9 * max(1.0, max(abs(v) for v in finite))


def _figure_note(drawn: list[str], flat: list[str]) -> str:
    """What the factor's figure shows and which headline metrics it leaves out as flat."""
    text = (
        f"Figure: {len(drawn)} headline metrics, mean over the runs at each value (n runs "
        "per value on the axis)."
        if drawn
        else "No figure: every headline metric is the same at every value."
    )
    if flat:
        text += " Not drawn, flat across the values: " + ", ".join(map(_metric_label, flat)) + "."
    return text + " Every metric: the table."


def _ablation_plot(plt, key: str, values: list[str], table: dict, shown: list[str], path,
                   runs: list[int] | None = None) -> None:  # fmt: skip
    """Each metric against the factor's value (categorical axis for non-numbers); ``runs``:
    the runs behind each value's mean, written on the axis."""
    columns = min(4, len(shown))
    rows = math.ceil(len(shown) / columns)
    fig, axes = plt.subplots(
        rows, columns, figsize=(max(3.2 * columns, 6.0), 2.6 * rows + 0.4), squeeze=False
    )
    parsed = [json.loads(v) for v in values]
    numeric = all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in parsed)
    x = parsed if numeric else list(range(len(values)))
    ticks = [str(v) + (f"\n(n = {n})" if runs else "") for v, n in zip(parsed, runs or parsed,
                                                                        strict=True)]  # fmt: skip
    for ax, m in zip(np.ravel(axes), shown, strict=False):
        if numeric:
            ax.plot(x, table[m], marker="o")
        else:  # categories (hands, methods): bars, not a line between them
            ax.bar(x, table[m], color="#4c72b0")
        ax.set_xticks(x, ticks, fontsize=7)
        ax.set_title(_metric_label(m), fontsize=8)
    for ax in np.ravel(axes)[len(shown) :]:
        ax.axis("off")
    total = sum(runs) if runs else len(values)
    fig.suptitle(f"{key}\nheadline metrics, mean over the runs per value ({total} runs)",
                 fontsize=10)  # fmt: skip
    fig.tight_layout()
    save_figure(fig, path)


def _metric_label(key: str) -> str:
    method, _, metric = key.rpartition(".")
    label = METRICS.get(metric, (metric, False))[0]
    return f"{method} {label}".strip()


def _mean(values) -> float:
    finite = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return float(np.mean(finite)) if finite else float("nan")


def _sort_key(value: str):
    parsed = json.loads(value)
    return (0, parsed, "") if isinstance(parsed, (int, float)) else (1, 0, str(parsed))
