"""Bad input is answered clearly, nothing is dropped silently, and the machine's errors fail.

One section per kind of fault: dropped sequences are counted and listed (and machine errors fail
the stage so that a rerun retries them); mesh paths stay inside the data root; documented fields
(``timestamps``, ``side``) are used or refused; smaller format faults (hidden files, arrays that
are not archives, bad meshes, YAML syntax).
"""

from __future__ import annotations

import errno
import json
import multiprocessing
import os
import signal
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

import dexflow.stages.scale_align
from dexflow.errors import IncompleteStageError, MeshError, SequenceFormatError
from dexflow.hands.spec import load_hand_spec
from dexflow.io.layout import Layout, StageDir
from dexflow.io.mirror import MIRROR, mirror_mesh
from dexflow.io.sequence import load_sequence, save_sequence, validate_sequence
from dexflow.params import PipelineParams, RunParams
from dexflow.pipeline.parallel import map_items
from dexflow.pipeline.resume import DONE_DIR
from dexflow.pipeline.runner import StageSpec, run_stage, stage_main
from dexflow.stages.hand import run_hand
from dexflow.stages.report import write_summary
from dexflow.stages.retarget import run_retarget
from dexflow.stages.scale_align import STAGE as SCALE_ALIGN
from dexflow.stages.scale_align import run_scale_align

from .conftest import make_sequence
from .test_metrics import _metrics_dir

ROOT = Path(__file__).resolve().parents[1]


def _params(**retarget) -> PipelineParams:
    params = PipelineParams()
    params.hand, _ = load_hand_spec("allegro")
    params.scale_align.sdf_spacing_m = 0.004
    params.scale_align.surface_samples = 256
    params.scale_align.convex.max_hulls = 4
    params.scale_align.convex.preprocess_resolution = 10
    params.scale_align.convex.mcts_iterations = 10
    params.retarget.global_search.mode = "off"
    params.retarget.iterations = retarget.get("iterations", 10)
    params.run = RunParams("sequential", 1)
    return params


def _save(root: Path, name: str, seq) -> Path:
    path = StageDir(root).sequence(name)
    save_sequence(path, seq, data_root=root)
    return path


def _raw(root: Path, name: str, seq, **fields) -> Path:
    """Write a sequence file without validating it (a user's bad file)."""
    arrays = seq.to_arrays() | fields
    path = StageDir(root).sequence(name)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **arrays)
    return path


# --- 1. dropped sequences are counted and listed; the machine's errors fail the stage --------


def _fails_on(x):
    if x == 1:
        raise SequenceFormatError(None, "keypoints", "metres", "millimetres")
    if x == 2:
        raise OSError(errno.ENOSPC, "No space left on device")
    if x == 3:
        raise MemoryError("out of memory")
    return {"x": x}


@pytest.mark.parametrize("run", [1, 2])
def test_only_bad_input_is_skipped_other_errors_are_marked_for_retry(run):
    results = map_items(_fails_on, range(5), run, "items", progress=False)
    assert [r.ok for r in results] == [True, False, False, False, True]
    assert [r.retry for r in results] == [False, False, True, True, False]
    assert "millimetres" in results[1].error and "No space left" in results[2].error


def _killed_in_a_worker(item):
    x, flag = item
    if multiprocessing.parent_process() is not None:  # a worker process, not the test's
        flag.touch()
        os.kill(os.getpid(), signal.SIGKILL)  # what the OS does to a worker out of memory
    for _ in range(1200):  # this process waits until a worker has taken an item (and died)
        if flag.exists():
            break
        time.sleep(0.05)
    return {"x": x}


@pytest.mark.skipif(sys.platform == "win32", reason="SIGKILL")
def test_a_killed_worker_fails_its_item_for_retry_and_this_process_does_the_rest(tmp_path):
    items = [(x, tmp_path / "a worker took one") for x in range(6)]
    results = map_items(_killed_in_a_worker, items, 2, "items", progress=False)
    assert [r.item for r in results] == items
    failed = [r for r in results if not r.ok]
    assert len(failed) == 1 and failed[0].retry and "worker" in failed[0].error
    assert [r.value for r in results if r.ok] == [{"x": r.item[0]} for r in results if r.ok]


def test_a_full_disk_fails_the_stage_and_the_rerun_retries_only_that_sequence(
    data_root, tmp_path_factory, monkeypatch
):
    for i in range(3):
        _save(data_root, f"s{i}", make_sequence(10 + i))
    layout = Layout.of(data_root, root=tmp_path_factory.mktemp("project"))
    real_save = dexflow.stages.scale_align.save_sequence

    def disk_full_on_s1(path, *args, **kwargs):
        if Path(path).stem == "s1":
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real_save(path, *args, **kwargs)

    monkeypatch.setattr(dexflow.stages.scale_align, "save_sequence", disk_full_on_s1)
    with pytest.raises(IncompleteStageError, match=r"s1: OSError: \[Errno 28\]") as info:
        run_stage(SCALE_ALIGN, _params(), layout)
    assert list(info.value.failed) == ["s1"]
    out = layout.scale_align.root
    assert not (out / "summary.json").exists()  # nothing looks complete
    assert not layout.stage_metrics("scale_align").exists()
    assert sorted(p.stem for p in (out / DONE_DIR / "sequences").iterdir()) == ["s0", "s2"]

    monkeypatch.setattr(dexflow.stages.scale_align, "save_sequence", real_save)
    computed = []
    real_align = dexflow.stages.scale_align.align_sequence
    monkeypatch.setattr(
        dexflow.stages.scale_align,
        "align_sequence",
        lambda path, *a, **k: computed.append(Path(path).stem) or real_align(path, *a, **k),
    )
    summary = run_stage(SCALE_ALIGN, _params(), layout)
    assert computed == ["s1"]  # the rerun retries the failed sequence only
    assert summary["num_ok"] == 3 and summary["num_dropped"] == 0


def _stage(run) -> StageSpec:
    return StageSpec(name="toy", run=run, metric_keys=(), describe=lambda s: "done")


def _project(tmp_path: Path, monkeypatch, params_text: str | None = None) -> None:
    (tmp_path / "params.yaml").write_text(
        params_text or (ROOT / "params.yaml").read_text(encoding="utf-8"), encoding="utf-8"
    )
    monkeypatch.chdir(tmp_path)


def test_stage_exit_codes_say_what_failed(tmp_path, monkeypatch, caplog):
    _project(tmp_path, monkeypatch)

    def machine(params, layout):
        raise IncompleteStageError("toy", {"a": "OSError: [Errno 28] No space left on device"})

    def none_ok(params, layout):
        return {"sequences": {"a": {"status": "failed", "error": "bad"}}, "num_ok": 0}

    def some_ok(params, layout):
        return {"sequences": {"a": {"status": "ok"}, "b": {"status": "failed"}}, "num_ok": 1}

    assert stage_main(_stage(machine)) == 1
    assert "run `dvc repro` again to retry" in caplog.text
    assert stage_main(_stage(none_ok)) == 1
    assert stage_main(_stage(some_ok)) == 0
    text = (ROOT / "params.yaml").read_text().replace("base_sigma_m: 0.05", "base_sigma_m: 0")
    _project(tmp_path, monkeypatch, text)
    caplog.clear()
    assert stage_main(_stage(some_ok)) == 2
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert errors == ["toy: params.yaml: retarget.base_sigma_m: expected > 0, found 0.0"]


@pytest.fixture(scope="module")
def dropped_run(tmp_path_factory):
    """scale_align and retarget on 2 good sequences, 2 bad ones and 2 hidden files."""
    root = tmp_path_factory.mktemp("dropped")
    (root / "meshes").mkdir()
    trimesh.creation.box(extents=(0.06, 0.04, 0.08)).export(root / "meshes" / "box.obj")
    good = make_sequence(12)
    _save(root, "good_a", good)
    _save(root, "good_b", make_sequence(14))
    _raw(root, "in_mm", good, keypoints=good.keypoints * 1000)
    (root / "sequences" / "not_npz.npz").write_bytes(b"keypoints,obj_pose\n")
    (root / "sequences" / "._good_a.npz").write_bytes(b"\x00\x05\x16\x07 resource fork")
    _save(root, ".good_a.npz.k2j.tmp", good)  # what an interrupted atomic write leaves
    layout = Layout.of(root, root=root / "project")
    params = _params()
    aligned = run_stage(SCALE_ALIGN, params, layout)
    run_hand(params, layout)
    retarget_stage = StageSpec("retarget", run_retarget, ("num_ok",), lambda s: "")
    retargeted = run_stage(retarget_stage, params, layout, ("position",))
    return layout, aligned, retargeted


def test_every_stage_counts_the_inputs_and_lists_each_dropped_one_with_its_reason(dropped_run):
    layout, aligned, retargeted = dropped_run
    assert aligned["num_input_sequences"] == 4  # hidden files are not sequences
    assert (aligned["num_ok"], aligned["num_dropped"]) == (2, 2)
    # retarget saw two sequences, and still accounts for the four of the data
    assert retargeted["num_sequences"] == 2 and retargeted["num_failed"] == 0
    assert retargeted["num_input_sequences"] == 4 and retargeted["num_dropped"] == 2
    dropped = retargeted["dropped"]
    assert sorted(dropped) == ["in_mm", "not_npz"]
    assert dropped["in_mm"]["stage"] == "scale_align" and "millimetres" in dropped["in_mm"]["error"]
    assert "not a zip archive" in dropped["not_npz"]["error"]
    on_disk = json.loads(layout.retarget("position").summary.read_text())
    assert on_disk["dropped"] == dropped
    metrics = json.loads(layout.stage_metrics("retarget_position").read_text())
    assert (metrics["num_input_sequences"], metrics["num_dropped"]) == (4, 2)
    assert "dropped" not in metrics  # per-sequence reasons stay out of the DVC metrics


def test_the_report_lists_every_dropped_sequence_and_warning(tmp_path):
    metrics_dir, table, plots = _metrics_dir(tmp_path)
    aggregates = json.loads((metrics_dir / "metrics.json").read_text())
    aggregates |= {"num_input_sequences": 34, "num_dropped": 28}
    (metrics_dir / "metrics.json").write_text(json.dumps(aggregates))
    dropped = {
        f"take_{i:02d}": {"stage": "scale_align", "error": f"SequenceFormatError: take_{i:02d}"}
        for i in range(27)
    } | {"odd": {"stage": "refine", "error": "ArtifactError: a | b\nc"}}
    warnings = {"far": ["scale_align: the hand never comes within 30 mm of the object"]}
    stage_summary = tmp_path / "summary.json"
    stage_summary.write_text(json.dumps({"dropped": dropped, "warnings": warnings}))
    out = write_summary(metrics_dir, table, plots, tmp_path / "summary.md", tmp_path / "figures",
                        stage_summary=stage_summary)  # fmt: skip
    text = out.read_text()
    assert "Sequences: 34 in the data, 6 through every stage, **28 dropped**" in text
    section = text.split("## Dropped sequences")[1].split("\n## ")[0]
    rows = [line for line in section.splitlines() if line.startswith("| take_") or "odd" in line]
    assert len(rows) == 28
    assert "| odd | refine | ArtifactError: a \\| b c |" in section
    assert "| far | scale_align: the hand never comes within 30 mm" in text


# --- 2. nothing is read from outside the data root --------------------------------------------


@pytest.mark.parametrize(
    ("obj_mesh", "words"),
    [("/data/meshes/box.obj", "absolute path"), ("../meshes/box.obj", "climbs out")],
)
def test_mesh_paths_outside_the_data_root_are_refused(sequence, obj_mesh, words):
    with pytest.raises(SequenceFormatError, match=rf"obj_mesh.*{words}"):
        validate_sequence(replace(sequence, obj_mesh=obj_mesh))


def test_scale_align_never_reads_a_mesh_outside_the_data_root(tmp_path, monkeypatch):
    root = tmp_path / "root"
    (root / "meshes").mkdir(parents=True)
    box = trimesh.creation.box(extents=(0.06, 0.04, 0.08))
    box.export(root / "meshes" / "box.obj")
    box.export(tmp_path / "outside.obj")  # a valid mesh DVC does not track
    _save(root, "inside", make_sequence(10))
    _raw(root, "outside", make_sequence(10), obj_mesh=np.array("../outside.obj"))
    _raw(root, "absolute", make_sequence(10), obj_mesh=np.array(str(tmp_path / "outside.obj")))
    read = []
    real = dexflow.stages.scale_align.load_mesh
    monkeypatch.setattr(
        dexflow.stages.scale_align, "load_mesh", lambda p: read.append(Path(p)) or real(p)
    )
    summary = run_scale_align(_params(), Layout.of(root, root=tmp_path / "project"))
    assert summary["num_ok"] == 1 and summary["num_objects"] == 1
    assert read == [root / "meshes" / "box.obj"]
    for name in ("outside", "absolute"):
        assert "obj_mesh" in summary["sequences"][name]["error"]


# --- 3. documented fields are used or refused ----------------------------------------------------


def _timestamps(n: int, fps: float = 30.0, gap_at: int | None = None, jitter: float = 0.0):
    ts = np.arange(n) / fps + np.random.default_rng(0).uniform(-jitter, jitter, n) / fps
    if gap_at is not None:
        ts[gap_at:] += 1.0
    return ts


def test_timestamps_with_a_gap_or_another_rate_are_refused_jitter_is_not(sequence):
    n = sequence.num_frames
    validate_sequence(replace(sequence, timestamps=_timestamps(n, jitter=0.2)))
    with pytest.raises(SequenceFormatError, match=r"timestamps', frame 4: .*insert|invalid"):
        validate_sequence(replace(sequence, timestamps=_timestamps(n, gap_at=4)))
    with pytest.raises(SequenceFormatError, match=r"timestamps.*25 fps: set fps"):
        validate_sequence(replace(sequence, timestamps=_timestamps(n, fps=25.0)))


def _asymmetric_root(root: Path) -> trimesh.Trimesh:
    """A data root whose object is not symmetric about x = 0 (so mirroring matters)."""
    (root / "meshes").mkdir(parents=True)
    mesh = trimesh.util.concatenate(
        [trimesh.creation.box(extents=(0.06, 0.04, 0.08)),
         trimesh.creation.box(extents=(0.02, 0.02, 0.02), transform=_shift(0.04, 0.0, 0.03))]
    )  # fmt: skip
    mesh.export(root / "meshes" / "right.obj")
    mirror_mesh(mesh).export(root / "meshes" / "left.obj")
    return mesh


def _shift(x, y, z):
    transform = np.eye(4)
    transform[:3, 3] = [x, y, z]
    return transform


def test_a_left_hand_is_mirrored_with_its_scene_and_retargets_like_the_right_one(tmp_path):
    root = tmp_path / "root"
    _asymmetric_root(root)
    right = replace(make_sequence(12, obj_mesh="meshes/right.obj"), obj_name="thing")
    m4 = np.eye(4)
    m4[:3, :3] = MIRROR
    left = replace(
        right,
        keypoints=right.keypoints @ MIRROR,
        obj_pose=m4 @ right.obj_pose @ m4,
        obj_mesh="meshes/left.obj",
        side="left",
    )  # the same motion, recorded as a left hand in a mirrored world
    _save(root, "right", right)
    _save(root, "left", left)
    _save(root, "left_taken_for_right", replace(left, side="right"))  # what was done before
    layout = Layout.of(root, root=tmp_path / "project")
    params = _params()
    assert run_scale_align(params, layout)["num_ok"] == 3
    aligned = {n: load_sequence(layout.scale_align.sequence(n)) for n in ("left", "right")}
    assert aligned["left"].mirrored and not aligned["right"].mirrored
    np.testing.assert_array_equal(aligned["left"].keypoints, aligned["right"].keypoints)
    np.testing.assert_array_equal(aligned["left"].obj_pose, aligned["right"].obj_pose)
    meshes = {n: trimesh.load(layout.root / "data/scale_align" / s.obj_mesh, force="mesh")
              for n, s in aligned.items()}  # fmt: skip
    np.testing.assert_allclose(meshes["left"].vertices, meshes["right"].vertices, atol=1e-9)
    np.testing.assert_array_equal(meshes["left"].faces, meshes["right"].faces)

    run_hand(params, layout)
    summary = run_retarget(params, layout, "dexflow")
    error = {n: e["keypoint_error_mm"] for n, e in summary["sequences"].items()}
    assert error["left"] == pytest.approx(error["right"], abs=1e-6)
    assert error["left_taken_for_right"] > error["right"] + 3.0  # a right robot hand, a left one


def _under_the_index_tip(seq, gap_m: float):
    """``seq`` with the box (8 cm tall) held still ``gap_m`` below its last index fingertip."""
    pose = np.repeat(np.eye(4)[None], seq.num_frames, axis=0)
    pose[:, :3, 3] = seq.keypoints[-1, 8] - [0.0, 0.0, 0.04 + gap_m]
    return replace(seq, obj_pose=pose)


def test_a_hand_that_never_comes_near_the_object_is_warned_about(data_root, tmp_path, caplog):
    near = _under_the_index_tip(make_sequence(10), 0.005)
    far = _under_the_index_tip(make_sequence(10), 1.0)  # another frame, or other units
    _save(data_root, "near", near)
    _save(data_root, "far", far)
    layout = Layout.of(data_root, root=tmp_path / "project")
    summary = run_stage(SCALE_ALIGN, _params(), layout)
    entries = summary["sequences"]
    assert entries["far"]["status"] == "ok" and entries["far"]["closest_fingertip_mm"] > 900
    assert "never comes within 30 mm" in entries["far"]["warning"]
    assert "warning" not in entries["near"]
    assert entries["near"]["closest_fingertip_mm"] == pytest.approx(5.0, abs=0.5)
    assert list(summary["warnings"]) == ["far"]
    assert "never comes within 30 mm" in caplog.text


# --- 6. smaller format faults ----------------------------------------------------------------


def test_hidden_files_are_not_sequences(tmp_path, capsys):
    from dexflow.tools.cli import main

    stage = StageDir(tmp_path)
    stage.sequences_dir.mkdir()
    save_sequence(stage.sequence("take"), make_sequence())
    (stage.sequences_dir / "._take.npz").write_bytes(b"\x00\x05\x16\x07")
    save_sequence(stage.sequences_dir / ".take.npz.a1b2.tmp.npz", make_sequence())
    assert [p.name for p in stage.sequence_files()] == ["take.npz"]
    assert stage.names() == ["take"]
    assert main(["validate", str(stage.sequences_dir)]) == 0
    assert "1 valid, 0 invalid" in capsys.readouterr().out


def _with_object_array() -> dict:
    return make_sequence().to_arrays() | {"obj_name": np.array(["box", 1], dtype=object)}


@pytest.mark.parametrize(
    ("write", "words"),
    [
        (lambda p: p.write_bytes(b""), "an empty file"),
        (lambda p: np.save(open(p, "wb"), np.zeros(3)), r"a single \.npy array"),
        (lambda p: p.write_text("kp0_x,kp0_y\n"), "not a zip archive"),
        (lambda p: np.savez(p, **_with_object_array()), "Python objects"),
    ],
)
def test_a_file_that_is_not_an_npz_archive_says_what_it_is(tmp_path, write, words):
    path = tmp_path / "take.npz"
    write(path)
    with pytest.raises(SequenceFormatError, match=words):
        load_sequence(path)


@pytest.mark.parametrize(
    ("mesh_text", "words"),
    [
        ("", "no triangles"),
        ("v 1 2\nf 1 2 x\n", "cannot read mesh"),
        (None, "millimetres"),
    ],
)
def test_validate_loads_the_mesh_as_scale_align_will(data_root, capsys, mesh_text, words):
    from dexflow.tools.cli import main

    mesh = data_root / "meshes" / "bad.obj"
    if mesh_text is None:
        trimesh.creation.box(extents=(60.0, 40.0, 80.0)).export(mesh)
    else:
        mesh.write_text(mesh_text)
    _save(data_root, "bad_mesh", make_sequence(obj_mesh="meshes/bad.obj"))
    _save(data_root, "good", make_sequence())
    assert main(["validate", str(data_root / "sequences"), "--data-root", str(data_root)]) == 1
    out = capsys.readouterr().out
    fail = next(line for line in out.splitlines() if line.startswith("FAIL"))
    assert "bad_mesh.npz: field 'obj_mesh'" in fail and "bad.obj" in fail and words in fail
    assert "1 valid, 1 invalid" in out
    with pytest.raises(MeshError, match=words):  # scale_align refuses it the same way
        dexflow.stages.scale_align.load_mesh(mesh)


def test_a_yaml_syntax_error_is_one_line_with_its_place(tmp_path, capsys):
    from dexflow.tools.cli import main

    hand = tmp_path / "myhand.yaml"
    hand.write_text((ROOT / "conf" / "hand" / "allegro.yaml").read_text() + "scale: [1\n")
    assert main(["hand", "check", str(hand), "--png", str(tmp_path / "z.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {hand}: line ") and "column" in err and "\n" not in err
