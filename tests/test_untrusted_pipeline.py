"""The pipeline against what users' folders and interruptions hold: every input counted, no
stage outliving a killed ``dvc repro``, no two runs of one stage at once."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil
import pytest

from dexflow.io.layout import StageDir, project_root, stray_files
from dexflow.io.sequence import save_sequence
from dexflow.pipeline.resume import StageOutput
from dexflow.pipeline.runner import StageBusyError, stage_lock
from dexflow.tools.cli import main as cli_main
from tests.conftest import make_sequence


def _data_root(tmp_path: Path) -> Path:
    """``sequences/a.npz`` (read), ``sequences/takes/b.npz`` and ``sequences/notes.txt`` (not
    read), ``sequences/._a.npz`` (a hidden resource fork: nobody's input)."""
    root = tmp_path / "data"
    (root / "sequences" / "takes").mkdir(parents=True)
    (root / "meshes").mkdir()
    import trimesh

    trimesh.creation.box(extents=(0.06, 0.04, 0.08)).export(root / "meshes" / "box.obj")
    save_sequence(root / "sequences" / "a.npz", make_sequence())
    save_sequence(root / "sequences" / "takes" / "b.npz", make_sequence())
    (root / "sequences" / "notes.txt").write_text("take notes")
    (root / "sequences" / "._a.npz").write_bytes(b"\0\5\26\7")
    return root


def test_validate_and_the_pipeline_see_the_same_sequences(tmp_path, capsys):
    root = _data_root(tmp_path)
    folder = root / "sequences"
    assert stray_files(folder) == {
        folder / "notes.txt": "not an .npz sequence file",
        folder / "takes" / "b.npz": "in a sub-folder of sequences/: the pipeline reads "
        "sequences/*.npz only",
    }
    assert cli_main(["validate", str(root)]) == 1  # the data root or its sequences/ alike
    out = capsys.readouterr().out
    assert f"FAIL {folder / 'takes' / 'b.npz'}: in a sub-folder" in out
    assert out.strip().endswith("1 valid, 2 invalid")
    assert cli_main(["validate", str(folder)]) == 1

    # A stage maps over a.npz alone and lists the other two as dropped by `data`.
    stage = StageOutput(tmp_path / "out", "demo stage", {}, inputs=[root])
    files = stage.start()
    assert files == [folder / "a.npz"]
    tally = stage.run(lambda path: {"frames": 1}, files, 1)
    summary = {"sequences": tally.sequences}
    stage.finish(summary)
    assert summary["num_input_sequences"] == 3 and summary["num_dropped"] == 2
    assert set(summary["dropped"]) == {"notes.txt", "takes/b.npz"}
    assert {d["stage"] for d in summary["dropped"].values()} == {"data"}

    shutil.rmtree(folder / "takes")
    (folder / "notes.txt").unlink()
    assert cli_main(["validate", str(root)]) == 0
    assert StageDir(root).names() == ["a"]


def test_a_second_run_of_a_stage_stops_while_the_first_holds_it(tmp_path):
    holder = subprocess.Popen(
        [sys.executable, "-c",
         "import sys, time\n"
         "from dexflow.pipeline.runner import stage_lock\n"
         f"with stage_lock({str(tmp_path)!r}, 'refine'):\n"
         "    print('held', flush=True); time.sleep(60)\n"],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(StageBusyError, match=f"refine: another run .* \\(pid {holder.pid}\\)"):
            with stage_lock(tmp_path, "refine"):
                pass
        with stage_lock(tmp_path, "contact"):  # another stage of the project: free
            pass
    finally:
        holder.kill()
        holder.wait()
    with stage_lock(tmp_path, "refine"):  # the kernel released it with its holder
        pass


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="watches through /proc")
def test_a_stage_under_sh_c_stops_when_its_launcher_is_killed(tmp_path):
    """DVC runs a stage as `/bin/sh -c <cmd>`, and the shell outlives a SIGKILLed launcher, so
    the parent-death signal alone never reaches the stage: the stage watches the launcher."""
    marker = tmp_path / "stopped"
    stage = f"""import time, pathlib
from dexflow.pipeline.runner import _stops_with_parent
marker = pathlib.Path({str(marker)!r})
try:
    with _stops_with_parent():
        marker.with_suffix(".started").touch()
        time.sleep(60)
except KeyboardInterrupt as stop:
    marker.write_text(str(stop))
"""
    (tmp_path / "stage.py").write_text(stage)
    launcher = subprocess.Popen(
        [sys.executable, "-c", "import subprocess, sys, time; "
         f"subprocess.Popen('{sys.executable} stage.py', shell=True); time.sleep(60)"],
        cwd=tmp_path,
    )  # fmt: skip
    deadline = time.monotonic() + 60
    while not marker.with_suffix(".started").exists():
        assert time.monotonic() < deadline, "the stage did not start"
        time.sleep(0.1)
    launcher.kill()
    launcher.wait()
    deadline = time.monotonic() + 10
    while not marker.exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert marker.exists() and marker.read_text() == "signal 15"


@pytest.mark.slow
def test_a_killed_dvc_repro_leaves_no_stage_or_worker_running(tmp_path):
    """SIGKILL to `dvc repro` while stage scale_align runs with two workers: within a few
    seconds no process of the project is left, and the next `dvc repro` completes."""
    project = tmp_path / "project"
    project.mkdir()
    for rel in ("conf", "stages", "dexflow", ".dvc"):
        shutil.copytree(project_root() / rel, project / rel,
                        ignore=shutil.ignore_patterns("tmp", "cache", "__pycache__"))  # fmt: skip
    for rel in ("dvc.yaml", ".dvcignore", ".gitignore"):
        shutil.copy2(project_root() / rel, project / rel)
    overrides = ["demo.objects=[002_master_chef_can,006_mustard_bottle,021_bleach_cleanser]",
                 "demo.sequences_per_object=1", "run.n_jobs=2"]  # fmt: skip
    env = {**os.environ, "DVC_NO_ANALYTICS": "1"}
    subprocess.run([sys.executable, "-m", "dexflow.tools.cli", "params", *overrides], cwd=project,
                   check=True, env=env, capture_output=True)  # fmt: skip
    for cmd in (
        ["git", "init", "-q"],
        ["git", "add", "-A"],
        ["git", "-c", "user.email=t@t", "-c", "user.name=t", "commit", "-qm", "init"],
    ):
        subprocess.run(cmd, cwd=project, check=True, capture_output=True)  # fmt: skip

    def ours() -> list[psutil.Process]:
        found = []
        for proc in psutil.process_iter(["pid", "cwd", "cmdline"]):
            try:
                if proc.info["cwd"] == str(project) and proc.pid != os.getpid():
                    found.append(proc)
            except (psutil.Error, TypeError):
                continue
        return found

    dvc = subprocess.Popen(["dvc", "repro", "scale_align"], cwd=project, env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        running = [
            p for p in ours() if "stages/scale_align.py" in " ".join(p.info["cmdline"] or [])
        ]
        if running and len(ours()) >= 3:  # dvc, the stage, a worker
            break
        assert dvc.poll() is None, "dvc repro ended before scale_align got going"
        time.sleep(0.2)
    else:
        pytest.fail("stage scale_align did not start")
    time.sleep(3)
    dvc.send_signal(signal.SIGKILL)
    dvc.wait()
    deadline = time.monotonic() + 20
    while ours() and time.monotonic() < deadline:
        time.sleep(0.5)
    left = [" ".join(p.info["cmdline"] or []) for p in ours()]
    assert not left, left
    done = subprocess.run(["dvc", "repro", "scale_align"], cwd=project, env=env,
                          capture_output=True, text=True, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    assert len(list((project / "data" / "scale_align" / "sequences").glob("*.npz"))) == 3


def test_nearest_observed_frame_without_a_frames_by_frames_table():
    """retarget's initial base and the adapters' held object poses fill unobserved frames from
    the nearest observed one (the earlier on a tie), in memory that grows with the frames, not
    with their square (the table this replaced took 0.3 GB at 6,000 frames)."""
    from dexflow.human.cleaning import nearest_index

    rng = np.random.default_rng(0)
    for _ in range(200):
        n = int(rng.integers(1, 60))
        idx = np.sort(rng.choice(n, int(rng.integers(1, n + 1)), replace=False))
        table = idx[np.abs(np.arange(n)[:, None] - idx[None]).argmin(axis=1)]
        np.testing.assert_array_equal(nearest_index(idx, n), table)
    assert nearest_index(np.array([2, 4]), 6).tolist() == [2, 2, 2, 2, 4, 4]
