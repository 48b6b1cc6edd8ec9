"""Hands, yamls and meshes from someone else: no file outside the model's folder is read or
copied, no YAML alias bomb hangs a command, no degenerate or inside-out mesh reaches a stage
unsaid, and a hand naming a missing link stops ``dexflow params``."""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from dexflow.config import compose_params, load_params
from dexflow.data.ycb_standins import STANDINS, build_standin
from dexflow.errors import ConfigError, HandConfigError, MeshError
from dexflow.hands.files import copy_model, model_files, model_root, resolve_model_path
from dexflow.hands.model import load_kinematic_model
from dexflow.hands.spec import MAX_YAML_ALIASES, load_hand_spec
from dexflow.io.layout import Layout, StageDir, project_root
from dexflow.io.sequence import save_sequence
from dexflow.objects.mesh import MESH_WARNING, load_mesh, write_obj
from dexflow.objects.sdf import SignedDistanceGrid
from dexflow.params import PipelineParams
from dexflow.stages.hand import run_hand
from dexflow.stages.scale_align import run_scale_align
from dexflow.tools.cli import main
from tests.conftest import make_sequence
from tests.test_bad_input import _params as _small_params

ROOT = project_root()
BOX = trimesh.creation.box(extents=(0.06, 0.04, 0.08))

# --- 1. a hand model reads only files inside its folder -------------------------------------


def _urdf(folder: Path, filename: str) -> Path:
    """``folder/hand.urdf``: one link whose collision mesh is ``filename``."""
    folder.mkdir(parents=True, exist_ok=True)
    urdf = folder / "hand.urdf"
    urdf.write_text(
        '<robot name="mine"><link name="base"><collision><geometry>'
        f'<mesh filename="{filename}"/></geometry></collision></link></robot>'
    )
    return urdf


def _mjcf(folder: Path, body: str, compiler: str = "") -> Path:
    """``folder/hand.xml``: a hinged box plus ``body`` (asset or include elements)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "hand.xml").write_text(
        f"<mujoco>{compiler}{body}<worldbody><body name='palm'><joint name='j' type='hinge'/>"
        "<geom type='box' size='.01 .01 .01'/></body></worldbody></mujoco>"
    )
    return folder / "hand.xml"


def _secret(tmp_path: Path) -> Path:
    """A valid mesh outside every model folder: what must never be read or copied."""
    BOX.export(tmp_path / "secret.obj")
    return tmp_path / "secret.obj"


def _escapes(tmp_path: Path) -> dict[str, Path]:
    """URDFs whose mesh lies outside their folder: by ``..``, absolute, ``file://``,
    ``package://`` (found beside the URDF) and a symlink inside the folder."""
    secret = _secret(tmp_path)
    link_dir = tmp_path / "symlink" / "meshes"
    link_dir.mkdir(parents=True)
    os.symlink(secret, link_dir / "palm.obj")
    return {
        "dotdot": _urdf(tmp_path / "dotdot", "../secret.obj"),
        "absolute": _urdf(tmp_path / "absolute", str(secret)),
        "file_uri": _urdf(tmp_path / "file_uri", f"file://{secret}"),
        "package": _urdf(tmp_path / "package", "package://mine/../secret.obj"),
        "symlink": _urdf(tmp_path / "symlink", "meshes/palm.obj"),
    }


@pytest.mark.parametrize("case", ["dotdot", "absolute", "file_uri", "package", "symlink"])
def test_a_urdf_mesh_outside_the_model_folder_is_refused(tmp_path, case):
    urdf = _escapes(tmp_path)[case]
    secret, folder = re.escape(str(tmp_path / "secret.obj")), re.escape(str(urdf.parent))
    words = rf"{re.escape(str(urdf))}: <mesh filename=.*> resolves to {secret}, outside {folder}"
    with pytest.raises(HandConfigError, match=words):
        model_files(urdf)
    with pytest.raises(HandConfigError, match=words):  # hand check and the stages load it so
        load_kinematic_model(urdf)


def test_stage_hand_copies_nothing_and_hand_check_exits_2(tmp_path, capsys):
    urdf = _escapes(tmp_path)["symlink"]
    params = PipelineParams()
    params.hand.model = str(urdf)
    layout = Layout.of(tmp_path / "data", root=tmp_path / "project")
    with pytest.raises(HandConfigError, match="outside"):
        run_hand(params, layout)
    out = layout.hand_files.root
    assert not out.exists() or not any(out.rglob("*.obj"))

    yaml = urdf.parent / "mine.yaml"
    yaml.write_text(f"name: mine\nmodel: {urdf.name}\n")
    assert main(["hand", "check", str(yaml)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {urdf}: <mesh filename='meshes/palm.obj'>") and "\n" not in err


def test_a_package_mesh_stays_inside_its_installed_package(tmp_path, monkeypatch):
    """``package://`` resolved to an installed Python package may read that package's files,
    and no others."""
    site = tmp_path / "site"
    (site / "fakepkg" / "meshes").mkdir(parents=True)
    (site / "fakepkg" / "__init__.py").write_text("raise RuntimeError('imported')\n")
    BOX.export(site / "fakepkg" / "meshes" / "palm.obj")
    BOX.export(site / "secret.obj")
    monkeypatch.syspath_prepend(str(site))
    inside = _urdf(tmp_path / "model_a", "package://fakepkg/meshes/palm.obj")
    assert model_files(inside)[1] == (site / "fakepkg" / "meshes" / "palm.obj").resolve()
    outside = _urdf(tmp_path / "model_b", "package://fakepkg/../secret.obj")
    with pytest.raises(HandConfigError, match=rf"outside {re.escape(str(site / 'fakepkg'))}"):
        model_files(outside)
    with pytest.raises(HandConfigError, match=r"outside"):
        resolve_model_path("pkg://fakepkg/../secret.obj")


@pytest.mark.parametrize(
    ("case", "field"),
    [
        ("include_dotdot", "<include file='../outside.xml'>"),
        ("include_absolute", "<include file='/"),
        ("include_symlink", "<include file='parts.xml'>"),
        ("meshdir", "<compiler meshdir='..'>"),
        ("mesh_absolute", "<mesh file='/"),
        ("mesh_symlink", "<mesh file='palm.obj'>"),
    ],
)
def test_an_mjcf_file_outside_the_model_folder_is_refused(tmp_path, case, field):
    secret = _secret(tmp_path)
    (tmp_path / "outside.xml").write_text("<mujocoinclude/>")
    folder = tmp_path / "model"
    folder.mkdir()
    if case.endswith("symlink"):
        os.symlink(tmp_path / "outside.xml", folder / "parts.xml")
        os.symlink(secret, folder / "palm.obj")
    body, compiler = {
        "include_dotdot": ("<include file='../outside.xml'/>", ""),
        "include_absolute": (f"<include file='{tmp_path / 'outside.xml'}'/>", ""),
        "include_symlink": ("<include file='parts.xml'/>", ""),
        "meshdir": ("<asset><mesh file='secret.obj'/></asset>", "<compiler meshdir='..'/>"),
        "mesh_absolute": (f"<asset><mesh file='{secret}'/></asset>", ""),
        "mesh_symlink": ("<asset><mesh file='palm.obj'/></asset>", ""),
    }[case]
    xml = _mjcf(folder, body, compiler)
    words = rf"{re.escape(f'{xml}: {field}')}.*outside {re.escape(str(folder))}"
    with pytest.raises(HandConfigError, match=words):
        model_files(xml)
    with pytest.raises(HandConfigError, match=r"outside"):  # before MuJoCo opens anything
        load_kinematic_model(xml)


def test_the_folder_a_model_may_read(tmp_path):
    """A user's model: its folder; a packaged one: the package (ShadowHand's meshes are in a
    sibling folder of its xml); the pipeline's copy: the copy."""
    shadow = resolve_model_path("pkg://gymnasium_robotics/envs/assets/hand/reach.xml")
    assert model_root(shadow).name == "gymnasium_robotics"
    allegro = resolve_model_path("pkg://dexflow/hands/assets/allegro_right.urdf")
    assert model_root(allegro) == (ROOT / "dexflow").resolve()
    urdf = _urdf(tmp_path / "mine", "palm.obj")
    assert model_root(urdf) == urdf.parent.resolve()
    params = PipelineParams()
    params.hand, _ = load_hand_spec("shadow")
    layout = Layout.of(tmp_path / "data", root=tmp_path / "project")
    record = run_hand(params, layout)
    copy = layout.hand_files.root / record["model"]
    assert model_root(copy) == (layout.hand_files.root / "model").resolve()
    assert len(model_files(copy)) == len(record["files"])


def test_a_ros_package_reads_its_sibling_mesh_folder_and_no_further(tmp_path):
    """The ROS layout ``<package>/urdf/hand.urdf`` naming ``package://<package>/meshes/...``
    loads, as does stage hand's copy of it; a file beside the package is still refused."""
    package = tmp_path / "myhand_description"
    (package / "meshes").mkdir(parents=True)
    (package / "package.xml").write_text("<package><name>myhand_description</name></package>")
    trimesh.creation.box((0.02, 0.02, 0.02)).export(package / "meshes" / "palm.obj")
    urdf = _urdf(package / "urdf", "package://myhand_description/meshes/palm.obj")
    assert model_root(urdf) == package.resolve()
    mesh = (package / "meshes" / "palm.obj").resolve()
    assert model_files(urdf) == [urdf.resolve(), mesh]
    copy = tmp_path / "copy"
    record = copy_model(str(urdf), None, copy)
    assert sorted(record["files"]) == ["model/meshes/palm.obj", "model/urdf/hand.urdf"]
    assert model_files(copy / record["model"])[1] == (copy / "model/meshes/palm.obj").resolve()
    _secret(tmp_path)
    (package / "urdf" / "hand.urdf").write_text(
        urdf.read_text().replace("package://myhand_description/meshes/palm.obj", "../../secret.obj")
    )
    with pytest.raises(HandConfigError, match=r"secret\.obj"):
        model_files(package / "urdf" / "hand.urdf")


# --- 2. YAML aliases cannot expand without bound -----------------------------------------------


def _laughs(levels: int, width: int = 9) -> str:
    """The "billion laughs": each level a list of ``width`` aliases of the level below."""
    lines = ['lol0: &a0 ["lol"]']
    for i in range(1, levels + 1):
        lines.append(f"lol{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * width) + "]")
    return "\n".join(lines) + "\n"


def _forbid_construction(patch: pytest.MonkeyPatch) -> None:
    """Fail if any YAML document is constructed (its aliases expanded) under ``patch``: a bomb
    must be refused from its composed nodes alone, before any loader expands it (a
    deterministic check in place of timing the refusal)."""

    def construct_document(self, node):
        __tracebackhide__ = True  # a failure report must not print ``node``: it would expand it
        raise AssertionError("a YAML document was constructed before the bomb was refused")

    patch.setattr(yaml.constructor.BaseConstructor, "construct_document", construct_document)


@pytest.mark.parametrize(
    ("text", "words"),
    [
        (_laughs(9), "expand it to more than"),  # 81 aliases, 9**9 nodes
        (_laughs(1, MAX_YAML_ALIASES + 1), f"more than {MAX_YAML_ALIASES} aliases"),
        ("loop: &a [1, *a]\n", "recursive"),
    ],
    ids=["billion_laughs", "too_many_aliases", "recursive"],
)
def test_a_yaml_alias_bomb_is_refused_at_once(tmp_path, capsys, monkeypatch, text, words):
    hand = tmp_path / "bomb.yaml"
    hand.write_text(text + (ROOT / "conf" / "hand" / "allegro.yaml").read_text())
    with monkeypatch.context() as patch:
        _forbid_construction(patch)
        with pytest.raises(HandConfigError, match=rf"YAML document refused: .*{words}"):
            load_hand_spec(hand)
    assert main(["hand", "check", str(hand)]) == 2
    assert capsys.readouterr().err.startswith(f"error: {hand}: YAML document refused")


def test_the_built_in_yamls_load_and_a_params_bomb_is_refused(tmp_path, monkeypatch):
    for name in ("shadow", "allegro"):
        assert load_hand_spec(name)[0].name == name
    load_params(ROOT / "params.yaml")
    bomb = tmp_path / "params.yaml"
    bomb.write_text(_laughs(9) + (ROOT / "params.yaml").read_text())
    with monkeypatch.context() as patch:
        _forbid_construction(patch)
        with pytest.raises(ConfigError, match=rf"{re.escape(str(bomb))}: YAML document refused"):
            load_params(bomb)
    conf = tmp_path / "conf"
    shutil.copytree(ROOT / "conf", conf)
    (conf / "hand" / "bomb.yaml").write_text(
        _laughs(9) + (conf / "hand" / "allegro.yaml").read_text()
    )
    with pytest.raises(ConfigError, match=r"bomb.yaml: YAML document refused"):
        compose_params(["hand=bomb"], tmp_path / "out.yaml", config_dir=conf)


# --- 3. object meshes: refused when degenerate, flipped when inside out ------------------------


def _mesh_file(tmp_path: Path, name: str, mesh: trimesh.Trimesh) -> Path:
    path = tmp_path / f"{name}.obj"
    write_obj(path, mesh)
    return path


def _inverted(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    inverted = mesh.copy()
    inverted.invert()
    return inverted


def test_an_inside_out_mesh_is_flipped_and_said(tmp_path, caplog):
    path = _mesh_file(tmp_path, "inverted", _inverted(BOX))
    plain = SignedDistanceGrid.from_mesh(trimesh.load(path, force="mesh"), spacing=0.004)
    assert plain.query(np.zeros((1, 3)))[0] > 0  # as it is: its centre reads outside
    mesh = load_mesh(path)
    assert "inside out" in mesh.metadata[MESH_WARNING] and "flipped" in mesh.metadata[MESH_WARNING]
    assert any("inside out" in r.getMessage() for r in caplog.records)
    sdf = SignedDistanceGrid.from_mesh(mesh, spacing=0.004)
    np.testing.assert_allclose(sdf.query(np.zeros((1, 3))), [-0.02], atol=0.004)  # one cell
    outward = load_mesh(_mesh_file(tmp_path, "outward", BOX))
    np.testing.assert_array_equal(mesh.faces, outward.faces)


def test_an_inside_out_open_shell_is_flipped_too(tmp_path):
    """The demo's bowl (a thin open shell with holes) turned inside out: its signed volume is
    a small part of the unsigned one, yet clearly negative."""
    bowl = build_standin("024_bowl")
    mesh = load_mesh(_mesh_file(tmp_path, "inverted", _inverted(bowl)))
    assert MESH_WARNING in mesh.metadata
    np.testing.assert_array_equal(mesh.faces, load_mesh(_mesh_file(tmp_path, "bowl", bowl)).faces)


@pytest.mark.parametrize("name", sorted(STANDINS))
def test_no_demo_stand_in_is_refused_or_flipped(tmp_path, name):
    """Closed, concave, and open shells with holes (bowl, mug) alike."""
    path = _mesh_file(tmp_path, name, build_standin(name))
    mesh = load_mesh(path)
    assert MESH_WARNING not in mesh.metadata
    plain = trimesh.load(path, force="mesh", process=True)
    np.testing.assert_array_equal(mesh.faces, plain.faces)
    np.testing.assert_array_equal(mesh.vertices, plain.vertices)


def _flat_grid() -> trimesh.Trimesh:
    square = np.array([[0, 0, 0], [0.05, 0, 0], [0.05, 0.05, 0], [0, 0.05, 0.0]])
    vertices, faces = trimesh.remesh.subdivide(square, np.array([[0, 1, 2], [0, 2, 3]]))
    tilt = trimesh.transformations.rotation_matrix(0.7, [1, 1, 0])  # not along the box axes
    return trimesh.Trimesh(vertices, faces).apply_transform(tilt)


def _nan_box_text() -> str:
    """The box as OBJ, its first vertex's x NaN."""
    lines = trimesh.exchange.obj.export_obj(BOX, include_normals=False).splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("v "))
    lines[first] = "v nan " + " ".join(lines[first].split()[2:])
    return "\n".join(lines) + "\n"


def _triangle() -> trimesh.Trimesh:
    return trimesh.Trimesh([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0]], [[0, 1, 2]])


@pytest.mark.parametrize(
    ("write", "words"),
    [
        (
            lambda p: write_obj(p, _triangle()),
            r"1 triangle\(s\); an object's surface needs at least 4",
        ),
        (
            lambda p: write_obj(p, _flat_grid()),
            r"flat mesh: \S+ mm thick along its thinnest principal axis and 70.7 mm wide",
        ),
        (
            lambda p: p.write_text(_nan_box_text()),
            r"1 of 8 vertices are NaN or inf \(first: vertex 0",
        ),
    ],
    ids=["single_triangle", "flat_square", "nan_vertex"],
)
def test_a_degenerate_mesh_is_refused_with_what_was_found(tmp_path, write, words):
    path = tmp_path / "bad.obj"
    write(path)
    with pytest.raises(MeshError, match=rf"{re.escape(str(path))}: {words}"):
        load_mesh(path)


def test_scale_align_lists_the_flip_of_an_object_as_a_warning(tmp_path):
    root = tmp_path / "root"
    (root / "meshes").mkdir(parents=True)
    _inverted(BOX).export(root / "meshes" / "box.obj")
    save_sequence(StageDir(root).sequence("a"), make_sequence(10), data_root=root)
    params = _small_params()  # allegro, a coarse grid, few convex parts, one process
    summary = run_scale_align(params, Layout.of(root, root=tmp_path / "project"))
    assert summary["num_ok"] == 1
    (entry,) = summary["objects"].values()
    assert "inside out" in entry["warning"]
    (note,) = summary["warnings"]["a"]
    assert note.startswith("scale_align: object meshes/box.obj: the mesh was inside out")


# --- 4. a hand the stages would refuse stops `dexflow params` ----------------------------------


def test_dexflow_params_refuses_a_hand_naming_a_missing_link(tmp_path, monkeypatch, capsys):
    shutil.copytree(ROOT / "conf", tmp_path / "conf")
    allegro = (tmp_path / "conf" / "hand" / "allegro.yaml").read_text()
    broken = allegro.replace("name: allegro", "name: broken").replace(
        "link: link_3.0_tip,", "link: link_3.0_tipX,"
    )
    (tmp_path / "conf" / "hand" / "broken.yaml").write_text(broken)
    monkeypatch.chdir(tmp_path)
    assert main(["params", "hand=broken"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: hand 'broken': unknown keypoint links ['link_3.0_tipX']")
    assert "\n" not in err and not (tmp_path / "params.yaml").exists()
    assert main(["params", "--check", "hand=broken"]) == 2
    assert main(["params", "hand=allegro"]) == 0
    assert load_params(tmp_path / "params.yaml").hand.name == "allegro"
