"""Any hand a user brings runs the whole pipeline, physics included.

The hands are shaped like public models (:mod:`tests.hand_models`): a root link named ``world``
and links named ``object``, ``table`` and ``floor``; inertias violating A + B >= C; links without
``<inertial>``; 1e-9 kg m² inertias; an MJCF with its own world (light, camera, floor, table) and
includes; a left hand. Each is proposed by ``hand init``, passes ``hand check`` (which builds and
steps every physics scene) and runs every stage of ``dvc.yaml`` on a two-sequence demo.
"""

from __future__ import annotations

import functools
import json
import shutil
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np
import pytest

from dexflow.config import compose_params, load_params
from dexflow.errors import HandConfigError
from dexflow.hands import load_hand
from dexflow.hands.init import init_hand
from dexflow.hands.physics import WORLD_ALIAS, physics_urdf, repair_inertia
from dexflow.io.layout import Layout, project_root
from dexflow.params import SimulateParams
from dexflow.pipeline.runner import stage_main
from dexflow.sim.mujoco_world import MujocoGraspWorld, hand_name
from dexflow.sim.pybullet_world import PybulletGraspWorld, hand_urdf
from dexflow.sim.scene_check import _unstable, check_scenes
from dexflow.tools.bench.pipeline import pipeline_stages
from dexflow.tools.cli import main as cli_main
from tests import quick_pipeline
from tests.hand_models import PUBLIC_SHAPES, hand4

# ------------------------------------------------------------------------------ the repairs


def test_repair_balances_like_mujoco_and_keeps_valid_inertias():
    rng = np.random.default_rng(0)
    rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    valid = rotation @ np.diag([2e-6, 3e-6, 4e-6]) @ rotation.T
    assert repair_inertia(0.05, valid, 0.002, 1e-7) == (0.05, valid, "")
    tiny = np.eye(3) * 1e-9  # tiny but valid: kept
    assert repair_inertia(1e-6, tiny, 0.002, 1e-7)[2] == ""

    unbalanced = rotation @ np.diag([1e-6, 1e-6, 5e-6]) @ rotation.T
    mass, tensor, what = repair_inertia(0.05, unbalanced, 0.002, 1e-7)
    assert mass == 0.05 and "violate A + B >= C" in what and "balanceinertia" in what
    np.testing.assert_allclose(tensor, np.eye(3) * 7e-6 / 3)  # MuJoCo's: the mean of the three

    for bad_mass, bad_tensor in ((0.0, valid), (0.05, -valid), (np.nan, valid)):
        mass, tensor, what = repair_inertia(bad_mass, bad_tensor, 0.002, 1e-7)
        assert mass == 0.002 and "not positive" in what
        np.testing.assert_allclose(tensor, np.eye(3) * 1e-7)


def _proposed(tmp_path: Path, shape: str):
    model = PUBLIC_SHAPES[shape](tmp_path)
    init_hand(model, tmp_path / f"{shape}.yaml")
    return load_hand(tmp_path / f"{shape}.yaml")


def test_engines_refuse_the_raw_models_that_dexflow_repairs(tmp_path):
    """The fixtures are broken the way public models are: MuJoCo refuses the raw files."""
    unbalanced = PUBLIC_SHAPES["unbalanced_inertia"](tmp_path)
    with pytest.raises(ValueError, match="A \\+ B >= C"):
        mujoco.MjSpec.from_file(str(unbalanced)).compile()
    world = PUBLIC_SHAPES["world_rooted"](tmp_path)
    spec = mujoco.MjSpec.from_file(str(world))
    assert spec.body("world").name == spec.worldbody.name  # MuJoCo merges the root into its own


@pytest.mark.parametrize("shape", sorted(PUBLIC_SHAPES))
def test_hand_check_builds_and_steps_every_scene(tmp_path, shape, capsys, monkeypatch):
    hand = _proposed(tmp_path, shape)
    lines = check_scenes(hand, SimulateParams(engines=["mujoco", "pybullet"]))
    assert [line.split(":")[0] for line in lines if not line.startswith("model")] == [
        "grasp test (MuJoCo)", "replay (MuJoCo)", "grasp test (pybullet)"
    ]  # fmt: skip
    monkeypatch.chdir(tmp_path)  # no params.yaml: the default params, no picture written
    assert cli_main(["hand", "check", f"{shape}.yaml"]) == 0
    out = capsys.readouterr().out
    assert "replay (MuJoCo): built, 10 frames played, stable" in out and out.endswith("ok\n")
    assert not list(tmp_path.glob("*.png"))


def test_world_root_and_scene_names_are_namespaced(tmp_path):
    hand = _proposed(tmp_path, "world_rooted")
    assert hand.model.root == "world"
    world = MujocoGraspWorld(hand, SimulateParams())  # checks every frame against the model
    m = world.model
    names = {m.body(i).name for i in range(m.nbody)}
    assert {hand_name(n) for n in ("object", "table", "floor", "world")} <= names
    assert hand_name("world") == f"hand/{WORLD_ALIAS}"
    assert {"dexflow_mount", "world"} <= names  # the scene's own, untouched


def test_engines_get_the_same_repaired_inertias(tmp_path):
    """MuJoCo's scene and pybullet load one repaired file: the balanced moments agree."""
    hand = _proposed(tmp_path, "unbalanced_inertia")
    params = SimulateParams()
    urdf, repairs = physics_urdf(hand, 0.002, 1e-7)
    assert any("link 'palm'" in r and "A + B >= C" in r for r in repairs)
    assert hand_urdf(hand, params) == urdf != hand.model.path
    m = MujocoGraspWorld(hand, params).model
    bullet = PybulletGraspWorld(hand, urdf, params)
    for link in ("palm", "if_proximal", "th_distal"):
        moments = m.body(hand_name(link)).inertia
        assert moments == pytest.approx([moments.mean()] * 3)  # balanced
        info = bullet.client.getDynamicsInfo(bullet.body, bullet.link_index[link])
        np.testing.assert_allclose(info[2], moments, rtol=1e-6)
        assert info[0] == pytest.approx(m.body(hand_name(link)).mass[0])
    text = ET.parse(urdf).getroot()
    assert next(link.get("name") for link in text.iter("link")) == "forearm"  # parents first


def test_hand_check_names_the_joint_of_an_unstable_scene(tmp_path):
    """When MuJoCo finds a state it cannot integrate (it resets it by itself and warns), the
    check names the joint and link of the degree of freedom."""
    hand = _proposed(tmp_path, "tiny_inertia")
    world = MujocoGraspWorld(hand, SimulateParams())
    m, d = world.model, world.data
    assert _unstable(hand, m, d) == ""
    dof = int(m.joint(hand_name("if_pip")).dofadr[0])
    d.qvel[dof] = 1e12  # beyond MuJoCo's largest valid velocity
    mujoco.mj_step(m, d)
    assert _unstable(hand, m, d) == (
        "MuJoCo found unstable velocities at joint 'if_pip' (link 'if_middle'): give that link a "
        "realistic mass and inertia in the model, or raise its joint damping"
    )


def _ply_palm(folder: Path) -> Path:
    """The four-finger hand with its palm as a PLY mesh: the kinematics read it (trimesh),
    MuJoCo has no decoder for it."""
    import trimesh

    path = hand4(folder)
    trimesh.creation.box(extents=(0.02, 0.075, 0.09)).export(folder / "palm.ply")
    path.write_text(path.read_text().replace('<box size="0.02 0.075 0.09"/>',
                                             '<mesh filename="palm.ply"/>', 1))  # fmt: skip
    assert "palm.ply" in path.read_text()
    return path


def test_a_hand_the_engines_cannot_load_stops_the_stage_once(
    tmp_path, monkeypatch, caplog, demo_data
):
    """Stage simulate exits 2 with one line naming the hand and the file, not a retry per
    sequence; ``hand check`` says the same before any stage runs."""
    from dexflow.stages.simulate import STAGE

    project = _project(tmp_path, "plyhand", _ply_palm)
    for name, call in _stages(project, demo_data):
        if name == "simulate@baseline":
            break
        call()
    monkeypatch.chdir(project)
    caplog.clear()
    assert stage_main(STAGE, ["baseline"]) == 2
    failures = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(failures) == 1 and "hand 'plyhand'" in failures[0], failures
    assert "palm.ply" in failures[0] and "retry" not in failures[0]
    assert not (project / "data" / "simulate" / "baseline" / "summary.json").exists()
    with pytest.raises(HandConfigError, match=r"scene 'grasp test \(MuJoCo\)'.*palm\.ply.*fix: "
                       r"MuJoCo reads \.obj, \.stl and \.msh meshes"):  # fmt: skip
        check_scenes(load_hand(project / "conf" / "hand" / "plyhand.yaml"))


# --------------------------------------------------------------------- the whole pipeline


DEMO = ["demo.objects=[061_foam_brick]", "demo.min_frames=40", "demo.max_frames=45"]


def _project(tmp_path: Path, name: str, build) -> Path:
    """A project folder with this repository's conf/, the hand ``name`` built by ``build`` in
    conf/hand/ and proposed there by ``hand init``, params for a two-sequence demo of 40-45
    frames and a quick refinement (:mod:`tests.quick_pipeline`)."""
    project = tmp_path / "project"
    shutil.copytree(project_root() / "conf", project / "conf")
    folder = project / "conf" / "hand"
    model = build(folder)
    init_hand(model, folder / f"{name}.yaml")
    overrides = [f"hand={name}", *DEMO, "simulate.max_frames=2"]
    compose_params(overrides + quick_pipeline.overrides(), project / "params.yaml",
                   config_dir=project / "conf")  # fmt: skip
    return project


@pytest.fixture(scope="module")
def demo_data(tmp_path_factory) -> Path:
    """The demo stage's output for :func:`_project`'s params, made once: the demo does not
    depend on the hand, so each hand's project starts from a copy."""
    project = tmp_path_factory.mktemp("demo") / "project"
    compose_params(DEMO, project / "params.yaml")
    params = load_params(project / "params.yaml")
    layout = Layout.of(params.data.root, root=project)
    for name, call in pipeline_stages(params, layout):
        if name == "demo":
            call()
            return project / layout.data_root
    raise AssertionError("no demo stage")


def _stages(project: Path, demo_data: Path):
    """The pipeline's stages after the demo (copied from ``demo_data``), as bench runs them."""
    params = load_params(project / "params.yaml")
    layout = Layout.of(params.data.root, root=project)
    shutil.copytree(demo_data, project / layout.data_root)
    return [(name, call) for name, call in pipeline_stages(params, layout) if name != "demo"]


@pytest.mark.slow
@pytest.mark.parametrize("shape", sorted(PUBLIC_SHAPES))
def test_public_shaped_hand_runs_every_stage(tmp_path, shape, demo_data):
    project = _project(tmp_path, shape, PUBLIC_SHAPES[shape])
    results = {name: call() for name, call in _stages(project, demo_data)}
    for name, summary in results.items():
        if name in ("hand", "metrics"):
            continue
        assert summary["num_ok"] == summary["num_sequences"] == 2, (name, summary)
    assert results["simulate@refine"]["frames_evaluated"] > 0
    assert results["replay@refine"]["num_replayed"] > 0
    assert np.isfinite(results["replay@refine"]["position_error_mean_m"])


@pytest.mark.slow
def test_public_shaped_hand_through_dvc_repro(tmp_path):
    """The same as a user runs it: `dvc repro` with a world-rooted left hand, up to a stage that
    reads the hand stage's copy of it (every stage runs with it above), refine not waiting on
    replay (the grip is off)."""
    project = _project(tmp_path, "world_rooted_left", PUBLIC_SHAPES["world_rooted_left"])
    quick_pipeline.copy_project(project)
    run = functools.partial(quick_pipeline.run, cwd=project, project=project)
    run("git init -q -b main && git add -A && git commit -qm init")
    dag = run(["dvc", "dag", "refine"])  # refine and the stages it waits on
    assert "contact" in dag and "replay" not in dag  # no replay while the grip is off
    run(["dvc", "repro", "retarget@dexflow"])
    out = run([sys.executable, "-m", "dexflow.tools.cli", "hand", "check", "world_rooted_left"])
    assert "physics (params.yaml, engines mujoco)" in out and "\nok\n" in out
    done = json.loads((project / "data" / "retarget" / "dexflow" / "summary.json").read_text())
    assert done["num_ok"] == done["num_sequences"] == 2


@pytest.mark.slow
def test_refine_waits_on_replay_exactly_when_the_grip_reads_it(tmp_path):
    """Stage refine's dvc.yaml dep ``${refine.grip_input}`` follows refine.grip_m: a grip
    without replay@retarget's folder as the dep (or the dep without the grip) is refused."""
    from dexflow.errors import ConfigError

    out = tmp_path / "params.yaml"
    assert load_params(compose_params([], out)).refine.grip_input == "data/contact"
    with pytest.raises(ConfigError, match=r"refine\.grip_input: expected 'data/replay/retarget'"):
        load_params(compose_params(["refine.grip_m=0.005"], out))
    with pytest.raises(ConfigError, match=r"refine\.grip_input: expected 'data/contact'"):
        load_params(compose_params(["refine.grip_input=data/replay/retarget"], out))
    both = ["refine.grip_m=0.005", "refine.grip_input=data/replay/retarget"]
    assert load_params(compose_params(both, out)).refine.grip_m == 0.005
    assert "- ${refine.grip_input}" in (project_root() / "dvc.yaml").read_text()
