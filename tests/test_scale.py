"""Scale: the map backends give the same outputs, and stages resume after being killed."""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

from dexflow.errors import ConfigError
from dexflow.hands import load_hand
from dexflow.hands.spec import load_hand_spec
from dexflow.io.layout import Layout
from dexflow.io.sequence import save_sequence
from dexflow.params import PipelineParams, RunParams
from dexflow.pipeline.parallel import RAY_MISSING, map_items
from dexflow.pipeline.resume import DONE_DIR, STAGE_FILE, StageOutput
from dexflow.stages.contact import run_contact
from dexflow.stages.hand import run_hand
from dexflow.stages.scale_align import run_scale_align

from . import parallel_items
from .conftest import make_sequence

ROOT = Path(__file__).resolve().parents[1]
BACKENDS = [
    RunParams("sequential", 1),
    RunParams("local", 2),
    pytest.param(RunParams("ray", 2), marks=pytest.mark.slow, id="ray"),
]


@pytest.fixture(scope="module", autouse=True)
def _stop_ray():
    yield
    if "ray" in sys.modules:
        import ray

        ray.shutdown()


def _needs_ray(run: RunParams) -> None:
    if run.backend == "ray":
        pytest.importorskip("ray", reason=RAY_MISSING)


def _files(root: Path) -> dict[str, bytes]:
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def _stats(root: Path) -> dict[str, tuple[int, int]]:
    return {
        p.relative_to(root).as_posix(): (p.stat().st_ino, p.stat().st_mtime_ns)
        for p in root.rglob("*")
        if p.is_file()
    }


def _halve(x):
    if x == 3:
        raise ValueError(f"item {x} is bad")
    return {"half": x / 2}


# --- map_items ----------------------------------------------------------------------------


@pytest.mark.parametrize("run", [1, 2, *BACKENDS])
def test_map_items_keeps_order_and_reports_each_error(run):
    if isinstance(run, RunParams):
        _needs_ray(run)
    results = map_items(_halve, range(6), run, "halve", progress=False)
    assert [r.item for r in results] == list(range(6))
    assert [r.value for r in results] == [{"half": x / 2} for x in (0, 1, 2)] + [None] + [
        {"half": x / 2} for x in (4, 5)
    ]
    assert [r.error for r in results] == [None] * 3 + ["ValueError: item 3 is bad"] + [None] * 2
    assert "Traceback" in results[3].details
    assert results[3].entry() == {"status": "failed", "error": "ValueError: item 3 is bad"}


def _where(item):
    import torch

    flag = item[1]
    if multiprocessing.parent_process() is not None:
        flag.touch()
    for _ in range(1200):  # this process waits for a worker to take an item
        if flag.exists():
            break
        time.sleep(0.05)
    return {"pid": os.getpid(), "torch_threads": torch.get_num_threads()}


def test_local_jobs_are_this_process_and_workers_each_with_one_thread(tmp_path):
    items = [(x, tmp_path / "a worker took one") for x in range(4)]
    results = map_items(_where, items, 2, progress=False)
    pids = {r.value["pid"] for r in results}
    assert os.getpid() in pids and len(pids) == 2  # this process and the worker
    assert {r.value["torch_threads"] for r in results} == {1}


def test_a_worker_that_keeps_a_cache_is_kept(tmp_path):
    """A worker whose first item fills a per-process cache (400 MB, as a hand model and its
    meshes) does the following items too: loky's memory-leak guard, which measures the worker
    after the warm-up task, would replace it mid-stage with "A worker stopped while some jobs
    were given to the executor"."""
    items = [(x, tmp_path) for x in range(4)]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        results = map_items(parallel_items.cache_then_work, items, 2, progress=False)
    assert all(r.ok for r in results), [r.error for r in results]
    workers = {r.value for r in results} - {os.getpid()}
    assert len(workers) == 1, f"items ran in {len(workers)} worker processes, expected 1"
    assert not [w for w in caught if "worker stopped" in str(w.message)]


def test_ray_is_optional_and_named_when_missing(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    with pytest.raises(ImportError, match=r"pip install -e '\.\[ray\]'"):
        map_items(_halve, range(3), RunParams("ray", 2), progress=False)
    # Nothing imports Ray unless the ray backend is chosen.
    code = "import dexflow.pipeline.parallel, dexflow.pipeline.resume, dexflow.stages.scale_align, sys; print('ray' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.stdout.strip() == "False", out.stderr


@pytest.mark.parametrize(
    ("kwargs", "key", "found"),
    [
        ({"backend": "dask"}, "run.backend", "'dask'"),
        ({"n_jobs": 0}, "run.n_jobs", "0"),
        ({"backend": "local", "address": "auto"}, "run.address", "'auto'"),
        ({"backend": "ray", "address": " "}, "run.address", "' '"),
    ],
)
def test_run_params_name_the_wrong_key(kwargs, key, found):
    with pytest.raises(ConfigError, match=rf"{key}: expected .*, found {found}"):
        RunParams(**kwargs)
    assert RunParams("ray", 4, "ray://head:10001").address == "ray://head:10001"


# --- StageOutput on a toy stage -------------------------------------------------------------


def _toy_inputs(root: Path, names) -> Path:
    (root / "sequences").mkdir(parents=True, exist_ok=True)
    for name in names:
        np.savez(root / "sequences" / f"{name}.npz", x=np.array([len(name)]))
    return root


def _toy_stage(in_root: Path, out_root: Path, factor: float, calls: list, fail=()):
    """A stage in the shape of the real runners; ``calls`` records the items it computes."""
    stage = StageOutput(out_root, "toy", {"toy": {"factor": factor}}, inputs=(in_root,))
    files = stage.start()

    def one(path: Path) -> dict:
        calls.append(path.stem)
        if path.stem in fail:
            raise RuntimeError(f"{path.stem} cannot be done")
        with np.load(path) as data:
            value = float(data["x"][0] * factor)
        np.savez(out_root / "sequences" / path.name, y=np.array([value]))
        return {"y": value}

    results = stage.map(one, files, 1)
    summary = {"sequences": {r.item.stem: r.entry() for r in results}}
    return stage, summary


def test_resume_reuses_done_items_sweeps_the_rest_and_finish_leaves_only_outputs(tmp_path):
    in_root = _toy_inputs(tmp_path / "in", ["a", "bb", "ccc", "dddd"])
    out = tmp_path / "out"
    calls: list[str] = []
    _toy_stage(in_root, out, 2.0, calls, fail={"ccc"})  # "interrupted": never finished
    assert calls == ["a", "bb", "ccc", "dddd"]
    assert sorted(p.name for p in (out / DONE_DIR / "sequences").iterdir()) == [
        "a.json",
        "bb.json",
        "dddd.json",
    ]
    # What a kill leaves behind: a half-written temporary file and an output without a record.
    (out / "sequences" / ".ccc.npz.x1.tmp.npz").write_bytes(b"partial")
    (out / "sequences" / "ccc.npz").write_bytes(b"half")
    kept = _stats(out / "sequences")["bb.npz"]

    calls.clear()
    stage, summary = _toy_stage(in_root, out, 2.0, calls)
    assert calls == ["ccc"]  # a, bb, dddd reused; ccc had failed
    assert _stats(out / "sequences")["bb.npz"] == kept  # not rewritten
    assert sorted(p.name for p in (out / "sequences").iterdir()) == [
        "a.npz",
        "bb.npz",
        "ccc.npz",
        "dddd.npz",
    ]  # fmt: skip  (the half-written temporary file is gone)

    # an input changed or removed meanwhile changes the key: the stage starts afresh
    _toy_stage(in_root, out, 2.0, calls := [], fail={"ccc"})
    np.savez(in_root / "sequences" / "a.npz", x=np.array([7]))
    (in_root / "sequences" / "dddd.npz").unlink()
    stage, summary = _toy_stage(in_root, out, 2.0, calls := [])
    assert calls == ["a", "bb", "ccc"]
    assert summary["sequences"] == {
        "a": {"status": "ok", "y": 14.0},
        "bb": {"status": "ok", "y": 4.0},
        "ccc": {"status": "ok", "y": 6.0},
    }
    assert sorted(p.name for p in (out / "sequences").iterdir()) == ["a.npz", "bb.npz", "ccc.npz"]
    stage.finish(summary)
    assert sorted(_files(out)) == ["sequences/a.npz", "sequences/bb.npz", "sequences/ccc.npz",
                                   "summary.json"]  # fmt: skip

    calls.clear()
    _toy_stage(in_root, out, 2.0, calls)  # a finished run is not resumed: computed afresh
    assert calls == ["a", "bb", "ccc"]
    calls.clear()
    _toy_stage(in_root, out, 3.0, calls)  # other params: everything again, nothing stale
    assert calls == ["a", "bb", "ccc"]
    fingerprint = json.loads((out / STAGE_FILE).read_text())
    assert set(fingerprint) == {"stage", "key"}
    assert str(tmp_path) not in (out / STAGE_FILE).read_text()  # no absolute paths


def test_largest_inputs_go_first_and_results_keep_the_input_order(tmp_path):
    in_root = tmp_path / "in"
    (in_root / "sequences").mkdir(parents=True)
    for name, frames in (("a", 10), ("b", 1000), ("c", 100)):
        np.savez(in_root / "sequences" / f"{name}.npz", x=np.zeros(frames))
    stage = StageOutput(tmp_path / "out", "toy", {}, inputs=(in_root,))
    calls: list[str] = []

    def one(path: Path) -> dict:
        calls.append(path.stem)
        return {"name": path.stem}

    results = stage.map(one, stage.start(), 1)
    assert calls == ["b", "c", "a"]  # the longest sequence first
    assert [r.value["name"] for r in results] == ["a", "b", "c"]


# --- stages ---------------------------------------------------------------------------------


def _box_inputs(root: Path, count: int) -> Path:
    """``count`` sequences, each with its own box (so scale_align has ``count`` objects)."""
    (root / "meshes").mkdir(parents=True)
    for i in range(count):
        box = trimesh.creation.box(extents=(0.05 + 0.004 * i, 0.04, 0.07))
        box.export(root / "meshes" / f"box{i}.obj")
        seq = make_sequence(10 + i, obj_mesh=f"meshes/box{i}.obj")
        save_sequence(root / "sequences" / f"s{i}.npz", seq, data_root=root)
    return root


def _params(run: RunParams | None = None, **scale_align) -> PipelineParams:
    params = PipelineParams()
    params.hand, _ = load_hand_spec("allegro")
    params.scale_align.sdf_spacing_m = scale_align.get("sdf_spacing_m", 0.004)
    params.scale_align.surface_samples = scale_align.get("surface_samples", 256)
    params.scale_align.convex.max_hulls = 4
    params.run = run or RunParams("sequential", 1)
    return params


@pytest.fixture(scope="module")
def contact_inputs(tmp_path_factory):
    """scale_align output for four sequences and a fake retargeting of each, plus one whose
    joint names are not the hand's (it must fail alone)."""
    root = _box_inputs(tmp_path_factory.mktemp("scale"), 5)
    layout = Layout.of(root, root=root / "project")
    assert run_scale_align(_params(), layout)["num_ok"] == 5
    run_hand(_params(), layout)
    hand = load_hand("allegro")
    retarget = layout.retarget("dexflow")
    retarget.sequences_dir.mkdir(parents=True)
    for i in range(5):
        q = hand.zero(10 + i).numpy()
        q[:, 6:] += np.linspace(0, 0.3, len(q))[:, None]  # fingers closing
        names = list(hand.joint_names) if i != 2 else [f"j{k}" for k in range(q.shape[1])]
        np.savez(retarget.sequence(f"s{i}"), q=q, joint_names=np.array(names))
    return layout


def _contact_project(inputs: Layout, name: str) -> Layout:
    """A project of its own for one contact run, its inputs linked to ``inputs``'."""
    layout = Layout.of(inputs.data_root, root=inputs.root.parent / name)
    (layout.root / "data" / "retarget").mkdir(parents=True)
    layout.scale_align.root.symlink_to(inputs.scale_align.root.resolve())
    layout.retarget("dexflow").root.symlink_to(inputs.retarget("dexflow").root.resolve())
    layout.hand_files.root.symlink_to(inputs.hand_files.root.resolve())
    return layout


@pytest.fixture(scope="module")
def contact_reference(contact_inputs):
    """The contact stage run in this process, one sequence after another."""
    layout = _contact_project(contact_inputs, "contact_reference")
    run_contact(_params(), layout)
    return _files(layout.contact.root)


@pytest.mark.parametrize("run", BACKENDS, ids=lambda r: r.backend)
def test_contact_backends_give_the_same_outputs_and_report_the_bad_sequence(
    run, contact_inputs, contact_reference
):
    _needs_ray(run)
    layout = _contact_project(contact_inputs, f"contact_{run.backend}")
    summary = run_contact(_params(run), layout)
    out = layout.contact.root
    assert summary["num_ok"] == 4 and summary["num_failed"] == 1
    assert "joint_names do not match the hand" in summary["sequences"]["s2"]["error"]
    files = _files(out)
    assert sorted(files) == [f"sequences/s{i}.npz" for i in (0, 1, 3, 4)] + ["summary.json"]
    # arrays and summary byte for byte (the summary's error names the file in this project)
    summary_bytes = files["summary.json"].replace(
        out.parents[1].name.encode(), b"contact_reference"
    )
    assert files | {"summary.json": summary_bytes} == contact_reference


_KILLABLE = """
import sys
from pathlib import Path
from dexflow.stages.scale_align import run_scale_align
from dexflow.io.layout import Layout
from tests.test_scale import _params
run_scale_align(_params(sdf_spacing_m={spacing}), Layout.of(Path(sys.argv[1]), Path(sys.argv[2])))
"""


def _killed_midway(in_root: Path, project: Path, spacing: float) -> set[str]:
    """Run scale_align in a subprocess and SIGKILL it once 1 to n-1 objects are done."""
    script = textwrap.dedent(_KILLABLE.format(spacing=spacing))
    proc = subprocess.Popen(
        [sys.executable, "-c", script, str(in_root), str(project)],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    done_dir = Layout.of(in_root, project).scale_align.root / DONE_DIR / "objects"
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            if done_dir.is_dir() and _records(done_dir):
                break
            time.sleep(0.005)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait()
    return _records(done_dir)


def _records(done_dir: Path) -> set[str]:
    """The objects recorded done: not the hidden ``.<name>.json.*.tmp.json`` of a record the
    kill interrupted mid-write (the stage ignores those too: it reads records by name)."""
    return {p.stem for p in done_dir.glob("[!.]*.json")}


@pytest.mark.slow
def test_a_killed_stage_resumes_without_recomputing_and_matches_an_uninterrupted_run(tmp_path):
    in_root = _box_inputs(tmp_path / "in", 5)
    spacing = 0.0025  # about 1 s per object: time to kill between the first and the last
    project = Layout.of(in_root, tmp_path / "out")
    out = project.scale_align.root
    done = _killed_midway(in_root, project.root, spacing)
    assert 1 <= len(done) < 5, f"killed too late or too early: {done} done"
    assert not (out / "summary.json").exists()
    before = _stats(out)

    summary = run_scale_align(_params(sdf_spacing_m=spacing), project)
    after = _stats(out)
    for key in done:  # the objects completed before the kill were not computed again
        files = [rel for rel in before if rel.startswith(f"objects/{key}/")]
        assert len(files) == 5 and all(after[rel] == before[rel] for rel in files), key
    assert summary["num_ok"] == 5

    fresh = Layout.of(in_root, tmp_path / "fresh")
    assert run_scale_align(_params(sdf_spacing_m=spacing), fresh) == summary
    assert _files(out) == _files(
        fresh.scale_align.root
    )  # no bookkeeping, no temporaries left: the same bytes

    # Other params: everything is recomputed and nothing of the old run survives.
    summary = run_scale_align(_params(sdf_spacing_m=spacing, surface_samples=128), project)
    assert summary["num_ok"] == 5
    recomputed = _stats(out)
    assert sorted(recomputed) == sorted(after)
    assert all(recomputed[rel] != after[rel] for rel in recomputed)
    for key in summary["objects"]:
        with np.load(out / "objects" / key / "surface.npz") as surface:
            assert len(surface["points"]) == 128


def test_contact_in_chunks_of_frames_gives_the_same_outputs(contact_inputs, contact_reference):
    """Contact works through a sequence in chunks of frames (memory bounded by a chunk, for
    long captures): chunks of 3 frames give the same files, byte for byte, as one chunk."""
    from dexflow.measures import frame_chunks
    from dexflow.stages import contact

    layout = _contact_project(contact_inputs, "contact_chunked")
    original = contact.frame_chunks
    contact.frame_chunks = lambda n: frame_chunks(n, 3)
    try:
        run_contact(_params(), layout)
    finally:
        contact.frame_chunks = original
    files = _files(layout.contact.root)
    summary = files["summary.json"].replace(b"contact_chunked", b"contact_reference")
    assert files | {"summary.json": summary} == contact_reference
