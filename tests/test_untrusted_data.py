"""Data files from strangers: no code in them runs, their sizes are checked before anything is
inflated, and no path read from them leads out of its folder."""

from __future__ import annotations

import builtins
import io
import os
import pickle
import subprocess
import sys
import tracemalloc
import types
import zipfile

import numpy as np
import pytest
import scipy.sparse
import yaml
from numpy.lib import format as npy_format
from scipy.spatial.transform import Rotation

from dexflow.data.adapters import ConvertOptions, DatasetLayoutError, RawSequence, convert
from dexflow.data.adapters import write_sequence as write_raw_sequence
from dexflow.errors import SequenceFormatError, UnsafePickleError
from dexflow.human.mano import load_mano
from dexflow.io.sequence import load_sequence
from dexflow.io.untrusted import MAX_ARRAY_BYTES, MAX_FRAMES, load_npz, load_pickle

from .conftest import make_sequence
from .test_adapters import _box, _fake_mano, _hand, _make_dexycb, _poses, _write_ho3d

# ------------------------------------------------------------------------------------ payloads


class _Payload:
    """Unpickling this calls ``func(*args)``, as a crafted data file would."""

    def __init__(self, func, *args):
        self.func, self.args = func, args

    def __reduce__(self):
        return self.func, self.args


def _payloads(marker):
    """(payload, the global it names) pairs; each creates ``marker`` if it runs."""
    write = f"open({str(marker)!r}, 'w').write('ran')"
    return [
        (_Payload(builtins.exec, write), "builtins.exec"),
        (_Payload(builtins.eval, write), "builtins.eval"),
        (_Payload(os.system, f"touch '{marker}'"), f"{os.system.__module__}.system"),
        (_Payload(subprocess.Popen, ["touch", str(marker)]), "subprocess.Popen"),
        (_Payload(open, str(marker), "w"), f"{open.__module__}.open"),
        (
            _Payload(builtins.getattr, _Payload(builtins.__import__, "os"), "system"),
            "builtins.getattr",
        ),
    ]


PAYLOAD_IDS = ["exec", "eval", "os.system", "Popen", "open", "getattr"]


@pytest.mark.parametrize("protocol", [0, 2, 5])
@pytest.mark.parametrize("which", range(len(PAYLOAD_IDS)), ids=PAYLOAD_IDS)
def test_a_pickle_naming_any_other_global_is_refused_unrun(tmp_path, which, protocol):
    marker = tmp_path / "marker"
    payload, name = _payloads(marker)[which]
    path = tmp_path / "frame.pkl"
    path.write_bytes(pickle.dumps({"handJoints3D": np.zeros((21, 3)), "x": payload}, protocol))
    with pytest.raises(UnsafePickleError) as caught:
        load_pickle(path)
    assert caught.value.global_name == name
    assert str(path) in str(caught.value) and f"'{name}'" in str(caught.value)
    assert not marker.exists()


def test_a_hand_written_protocol_0_payload_is_refused(tmp_path):
    marker = tmp_path / "marker"
    path = tmp_path / "frame.pkl"
    path.write_bytes(b"cos\nsystem\n(S'touch " + str(marker).encode() + b"'\ntR.")
    with pytest.raises(UnsafePickleError, match=r"'os\.system'"):
        load_pickle(path)
    with open(path, "rb") as handle, pytest.raises(UnsafePickleError, match=str(path)):
        load_pickle(handle)  # an open file is named too
    assert not marker.exists()


def _plain_data():
    return {
        "floats": np.arange(12.0).reshape(3, 4),
        "fortran": np.asfortranarray(np.arange(6.0).reshape(2, 3)),
        "ints": np.arange(5, dtype=np.int32),
        "bools": np.array([True, False]),
        "text": np.array("025_mug"),
        "texts": np.array(["a", "bc"]),
        "record": np.zeros(2, dtype=[("a", "<f4"), ("b", ">i8")]),
        "objects": np.array({"nested": np.ones(3)}, dtype=object),
        "scalar": np.float64(1.5),
        "int": np.int64(3),
        "dtype": np.dtype("f4"),
        "plain": [1, 2.5, "s", b"bytes", None, True, (1, 2), {3}, frozenset({4}), 1j],
    }


def _assert_same(a, b):
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for key in a:
            _assert_same(a[key], b[key])
    elif isinstance(a, np.ndarray):
        assert type(b) is np.ndarray and a.dtype == b.dtype and a.shape == b.shape
        assert a.flags.f_contiguous == b.flags.f_contiguous
        if a.dtype == object:
            _assert_same(a.item(), b.item())
        else:
            np.testing.assert_array_equal(a, b)
    else:
        assert type(a) is type(b) and a == b


@pytest.mark.parametrize("protocol", range(pickle.HIGHEST_PROTOCOL + 1))
def test_plain_data_unpickles_as_pickle_does(protocol):
    data = pickle.dumps(_plain_data(), protocol)
    _assert_same(load_pickle(io.BytesIO(data)), pickle.loads(data))
    # numpy 1 wrote the same arrays under numpy.core: those names are read too.
    old = data.replace(b"numpy._core.", b"numpy.core.")
    if protocol <= 3 and old != data:
        _assert_same(load_pickle(io.BytesIO(old)), pickle.loads(data))


def test_codecs_encode_is_admitted_for_latin1_bytes_only():
    data = pickle.dumps(b"\x00\xff", protocol=2)
    assert b"_codecs" in data and load_pickle(io.BytesIO(data)) == b"\x00\xff"
    crafted = data.replace(b"latin1", b"utf_16")
    with pytest.raises(pickle.UnpicklingError, match="latin-1"):
        load_pickle(io.BytesIO(crafted))


# ----------------------------------------------------------------------- adapters that unpickle


def test_ho3d_frame_with_a_payload_fails_its_sequence_and_a_genuine_one_converts(tmp_path):
    marker = tmp_path / "marker"
    src = tmp_path / "src"
    for take in ("good", "bad"):
        _write_ho3d(src / "subject" / take, _hand(), _poses())
    _box(src / "models" / "025_mug" / "textured_simple.obj")
    bad = src / "subject" / "bad" / "meta" / "0002.pkl"
    payload, name = _payloads(marker)[0]
    bad.write_bytes(pickle.dumps({"objName": "025_mug", "handJoints3D": payload}, protocol=2))
    report = convert("ho3d", src, tmp_path / "out")
    assert report["sequences"]["subject_good"]["status"] == "ok"
    error = report["sequences"]["subject_bad"]["error"]
    assert str(bad) in error and f"'{name}'" in error
    assert not marker.exists()


def _grab_object(mesh="tools/box.ply"):
    poses = _poses()
    return {
        "params": {
            "transl": poses[:, :3, 3],
            "global_orient": Rotation.from_matrix(poses[:, :3, :3]).as_rotvec(),
        },
        "object_mesh": mesh,
    }


def _write_grab(path, obj, hand=None):
    path.parent.mkdir(parents=True, exist_ok=True)
    hand = {"joints": _hand()} if hand is None else hand
    np.savez(
        path,
        framerate=np.array(120.0),
        object=np.array(obj, dtype=object),
        rhand=np.array(hand, dtype=object),
    )


@pytest.mark.parametrize("which", [0, 2, 3], ids=["exec", "os.system", "Popen"])
def test_grab_npz_with_a_payload_fails_its_file_and_a_genuine_one_converts(tmp_path, which):
    marker = tmp_path / "marker"
    src = tmp_path / "grab"
    _box(src / "tools" / "box.ply")
    _write_grab(src / "s1" / "good.npz", _grab_object())
    payload, name = _payloads(marker)[which]
    _write_grab(src / "s1" / "bad.npz", _grab_object(), {"joints": _hand(), "x": payload})
    report = convert("grab", src, tmp_path / "out")
    assert report["sequences"]["s1_good"]["status"] == "ok", report
    error = report["sequences"]["s1_bad"]["error"]
    assert str(src / "s1" / "bad.npz") in error and "rhand" in error and f"'{name}'" in error
    assert not marker.exists()
    seq = load_sequence(tmp_path / "out" / "sequences" / "grab_s1_good.npz")
    np.testing.assert_allclose(seq.keypoints, _hand(), atol=1e-12)


def test_mano_file_with_a_payload_is_refused_unrun(tmp_path):
    marker = tmp_path / "marker"
    path = tmp_path / "MANO_RIGHT.pkl"
    model = _fake_mano(path)
    payload, name = _payloads(marker)[2]
    path.write_bytes(pickle.dumps({**model, "f": payload}, protocol=2))
    with pytest.raises(UnsafePickleError) as caught:
        load_mano(path)
    assert str(path) in str(caught.value) and f"'{name}'" in str(caught.value)
    assert not marker.exists()
    model["J_regressor"] = _Payload(scipy.sparse.load_npz, str(tmp_path / "x.npz"))
    path.write_bytes(pickle.dumps(model, protocol=2))
    with pytest.raises(UnsafePickleError, match=r"'scipy\.sparse\..*load_npz'"):
        load_mano(path)  # scipy.sparse: its matrix classes only


@pytest.fixture
def fake_chumpy(monkeypatch):
    """A ``chumpy.ch.Ch`` class to pickle with (chumpy itself is not installed)."""
    package, module = types.ModuleType("chumpy"), types.ModuleType("chumpy.ch")

    class Ch:
        def __init__(self, x):
            self.x = x

    Ch.__module__, Ch.__qualname__ = "chumpy.ch", "Ch"
    module.Ch, package.ch = Ch, module
    monkeypatch.setitem(sys.modules, "chumpy", package)
    monkeypatch.setitem(sys.modules, "chumpy.ch", module)
    return Ch


@pytest.mark.parametrize("protocol", [0, 2])
def test_mano_still_reads_chumpy_and_sparse_arrays(tmp_path, fake_chumpy, protocol):
    path = tmp_path / "MANO_RIGHT.pkl"
    model = _fake_mano(path)
    expected = load_mano(path)
    wrapped = {
        **model,
        "v_template": fake_chumpy(model["v_template"]),
        "shapedirs": fake_chumpy(model["shapedirs"]),
        "J_regressor": scipy.sparse.csc_matrix(model["J_regressor"]),
    }
    path.write_bytes(pickle.dumps(wrapped, protocol))
    mano = load_mano(path)
    for key in ("v_template", "shapedirs", "J_regressor", "weights", "parents"):
        np.testing.assert_array_equal(getattr(mano, key), getattr(expected, key))


# ------------------------------------------------------------------------------------ archives


def _write_member(archive, name, shape, descr="<f8", data_bytes=None):
    """A member whose header declares ``shape``; ``data_bytes`` zeros follow (default: as many
    as the shape needs), written in chunks so that nothing large is held in memory."""
    itemsize = np.dtype(descr).itemsize
    left = int(np.prod(shape)) * itemsize if data_bytes is None else data_bytes
    chunk = bytes(1 << 22)
    with archive.open(f"{name}.npy", "w") as member:
        header = {"descr": descr, "fortran_order": False, "shape": shape}
        npy_format.write_array_header_1_0(member, header)
        while left > 0:
            member.write(chunk[: min(left, len(chunk))])
            left -= len(chunk)


def _archive(path, compresslevel=1):
    return zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=compresslevel)


def test_a_small_archive_declaring_two_million_frames_is_refused_before_inflating(
    tmp_path, monkeypatch
):
    path = tmp_path / "take.npz"
    with _archive(path) as archive:
        _write_member(archive, "keypoints", (2_000_000, 21, 3))  # 1 GB of zeros, ~4 MB zipped
    assert path.stat().st_size < 8e6
    inflated = []  # bytes handed out by every read of a zip member: counted, not timed
    read = zipfile.ZipExtFile.read

    def counting_read(self, n=-1):
        data = read(self, n)
        inflated.append(len(data))
        return data

    monkeypatch.setattr(zipfile.ZipExtFile, "read", counting_read)
    tracemalloc.start()
    try:
        with pytest.raises(SequenceFormatError) as caught:
            load_sequence(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert 0 < sum(inflated) < 1 << 20 and peak < 16e6, (sum(inflated), peak)
    message = str(caught.value)
    assert str(path) in message and "'keypoints'" in message
    assert f"at most {MAX_FRAMES} frames" in message and "(2000000, 21, 3)" in message


@pytest.mark.parametrize(
    ("shape", "data_bytes", "words"),
    [
        ((1000, 21, 3), 800, r"a zip entry of \d+ \+ 504000 bytes uncompressed.*found \d+ bytes"),
        ((1000, 21, 3), 504000 + 8, r"a zip entry of \d+ \+ 504000 bytes"),
        ((10, MAX_ARRAY_BYTES // 80 + 1), 0, "MAX_ARRAY_BYTES"),
        ((-5, 21, 3), 0, "sizes >= 0"),
    ],
)
def test_a_header_that_does_not_match_its_entry_or_the_limits_is_refused(
    tmp_path, shape, data_bytes, words
):
    path = tmp_path / "take.npz"
    with _archive(path) as archive:
        _write_member(archive, "obj_pose", (10, 4, 4))
        _write_member(archive, "extra", shape, data_bytes=data_bytes)
    for read in (load_sequence, load_npz):
        with pytest.raises(SequenceFormatError, match=words) as caught:
            read(path)
        assert str(path) in str(caught.value) and "'extra'" in str(caught.value)


def test_arrays_together_may_not_exceed_the_byte_limit(tmp_path):
    path = tmp_path / "take.npz"
    half = MAX_ARRAY_BYTES // 2 + 8
    with _archive(path) as archive:
        for name in ("a", "b"):
            info = zipfile.ZipInfo(f"{name}.npy")
            header = io.BytesIO()
            npy_format.write_array_header_1_0(
                header, {"descr": "|u1", "fortran_order": False, "shape": (half,)}
            )
            archive.writestr(info, header.getvalue())  # then patch the declared size:
            info.file_size = len(header.getvalue()) + half
    with pytest.raises(SequenceFormatError, match=r"'<file>'.*bytes in all.*up to 'b'"):
        load_npz(path)


def test_object_arrays_in_a_sequence_file_are_refused_unread(tmp_path):
    marker = tmp_path / "marker"
    path = tmp_path / "take.npz"
    payload, _ = _payloads(marker)[0]
    arrays = make_sequence().to_arrays() | {"note": np.array(payload, dtype=object)}
    np.savez(path, **arrays)
    with pytest.raises(SequenceFormatError, match=r"'note'.*Python objects"):
        load_sequence(path)
    with pytest.raises(UnsafePickleError, match=r"'note'.*'builtins\.exec'"):
        load_npz(path, allow_objects=True)
    assert not marker.exists()


def test_load_npz_reads_what_np_load_reads(tmp_path):
    arrays = {k: v for k, v in _plain_data().items() if isinstance(v, np.ndarray)}
    arrays |= {"empty": np.zeros((0, 21, 3)), "big_endian": np.arange(4, dtype=">f8")}
    for save in (np.savez, np.savez_compressed):
        path = tmp_path / f"{save.__name__}.npz"
        save(path, **arrays)
        with np.load(path, allow_pickle=True) as data:
            expected = {key: data[key] for key in data.files}
        _assert_same(load_npz(path, allow_objects=True), expected)
    with pytest.raises(SequenceFormatError, match="Python objects"):
        load_npz(path)


def test_a_generic_source_declaring_too_many_frames_fails_that_sequence(tmp_path):
    src = tmp_path / "gen"
    _box(src / "box.obj")
    np.savez(src / "good.npz", keypoints=_hand(), obj_pose=_poses(), obj_mesh="box.obj", fps=30.0)
    with _archive(src / "bomb.npz") as archive:
        _write_member(archive, "keypoints", (MAX_FRAMES + 1, 21, 3), "<f2")
    report = convert("generic", src, tmp_path / "out")
    assert report["sequences"]["good"]["status"] == "ok"
    error = report["sequences"]["bomb"]["error"]
    assert str(src / "bomb.npz") in error and "MAX_FRAMES" in error


# --------------------------------------------------------------------------------------- paths


def _files(root):
    return {p for p in root.rglob("*") if p.is_file() or p.is_symlink()}


def _outside_targets(tmp_path):
    """An object model outside every allowed root, where each escape below would find one."""
    for folder in (tmp_path / "outside", tmp_path / "src" / "outside"):
        _box(folder / "textured_simple.obj")
        _box(folder / "box.obj")
    return tmp_path / "outside"


def _assert_refused(report, name, where, field, root, tmp_path, before):
    entry = report["sequences"][name]
    assert entry["status"] == "failed", entry
    error = entry["error"]
    assert "\n" not in error
    assert str(where) in error and f"field '{field}'" in error and str(root) in error, error
    written = _files(tmp_path) - before
    assert all(p.is_relative_to(tmp_path / "out") for p in written), written
    assert not list((tmp_path / "out").rglob("*.obj"))


@pytest.mark.parametrize(
    "obj_name", ["../outside", "../../outside", "<abs>", "a/b", "..", "x\\..\\..\\outside", ""]
)
def test_ho3d_object_names_stay_inside_the_models_folder(tmp_path, obj_name):
    outside = _outside_targets(tmp_path)
    obj_name = str(outside) if obj_name == "<abs>" else obj_name
    src = tmp_path / "src"
    _write_ho3d(src / "subject" / "take", _hand(), _poses(), obj=obj_name)
    (src / "models").mkdir()
    before = _files(tmp_path)
    report = convert("ho3d", src, tmp_path / "out")
    where = src / "subject" / "take" / "meta" / "0000.pkl"
    _assert_refused(report, "subject_take", where, "objName", src / "models", tmp_path, before)


def test_ho3d_model_linked_out_of_the_models_folder_is_refused(tmp_path):
    outside = _outside_targets(tmp_path)
    src = tmp_path / "src"
    _write_ho3d(src / "subject" / "take", _hand(), _poses())
    (src / "models").mkdir()
    (src / "models" / "025_mug").symlink_to(outside, target_is_directory=True)
    before = _files(tmp_path)
    report = convert("ho3d", src, tmp_path / "out")
    where = src / "subject" / "take" / "meta" / "0000.pkl"
    _assert_refused(report, "subject_take", where, "objName", src / "models", tmp_path, before)
    # A models folder that is itself a link is the user's choice, and is followed.
    (src / "models" / "025_mug").unlink()
    (src / "models").rmdir()
    _box(tmp_path / "shared_models" / "025_mug" / "textured_simple.obj")
    (src / "models").symlink_to(tmp_path / "shared_models", target_is_directory=True)
    assert convert("ho3d", src, tmp_path / "out2")["num_ok"] == 1


def _mesh_escapes(src, outside):
    """obj_mesh values that name a file outside ``src``: each exists, so only a check refuses."""
    (src / "link.obj").symlink_to(outside / "box.obj")
    (src / "linked").symlink_to(outside, target_is_directory=True)
    return {
        "dotdot": "../outside/box.obj",
        "inner_dotdot": "meshes/../../outside/box.obj",
        "absolute": str(outside / "box.obj"),
        "file_link": "link.obj",
        "folder_link": "linked/box.obj",
    }


ESCAPES = ["dotdot", "inner_dotdot", "absolute", "file_link", "folder_link"]


@pytest.mark.parametrize("escape", ESCAPES)
def test_generic_obj_mesh_stays_inside_the_source(tmp_path, escape):
    outside = _outside_targets(tmp_path)
    src = tmp_path / "src"
    _box(src / "meshes" / "box.obj")
    obj_mesh = _mesh_escapes(src, outside)[escape]
    np.savez(src / "a.npz", keypoints=_hand(), obj_pose=_poses(), obj_mesh=obj_mesh, fps=30.0)
    np.savez(src / "ok.npz", keypoints=_hand(), obj_pose=_poses(), obj_mesh="meshes/box.obj",
             fps=30.0)  # fmt: skip
    (src / "b.csv").write_text("kp0_x\n")
    (src / "b.json").write_text(f'{{"obj_mesh": "{obj_mesh}", "fps": 30}}')
    before = _files(tmp_path)
    report = convert("generic", src, tmp_path / "out")
    assert report["sequences"]["ok"]["status"] == "ok"
    (tmp_path / "out" / "meshes" / "box.obj").unlink()  # the genuine one's mesh
    _assert_refused(report, "a", src / "a.npz", "obj_mesh", src, tmp_path, before | _files(
        tmp_path / "out"))  # fmt: skip
    table = {f"kp{i}_{c}": _hand()[:, i, k] for i in range(21) for k, c in enumerate("xyz")}
    table |= {f"obj_{c}": np.zeros(len(_hand())) for c in ("rx", "ry", "rz", "tx", "ty", "tz")}
    import pandas as pd

    pd.DataFrame(table).to_csv(src / "b.csv", index=False)
    report = convert("generic", src, tmp_path / "out_csv")
    assert f"{src / 'b.json'}: field 'obj_mesh'" in report["sequences"]["b"]["error"]


@pytest.mark.parametrize("escape", ESCAPES)
def test_grab_object_mesh_stays_inside_the_source(tmp_path, escape):
    outside = _outside_targets(tmp_path)
    src = tmp_path / "src"
    (src / "s1").mkdir(parents=True)
    _write_grab(src / "s1" / "take.npz", _grab_object(_mesh_escapes(src, outside)[escape]))
    before = _files(tmp_path)
    report = convert("grab", src, tmp_path / "out")
    _assert_refused(report, "s1_take", src / "s1" / "take.npz", "object_mesh", src, tmp_path,
                    before)  # fmt: skip


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("serials", ["../../20200709-subject-01/20200709_141754/836212060125"]),
        ("serials", ["/tmp"]),
        ("extrinsics", "20200702_151821/../../../calibration/extrinsics_20200702_151821"),
        ("ycb_ids", [1, 0]),
        ("ycb_ids", [1, -3]),
    ],
)
def test_dexycb_names_read_from_meta_stay_inside_their_folders(tmp_path, field, value):
    _make_dexycb(tmp_path / "src")
    meta_path = next((tmp_path / "src").rglob("meta.yml"))
    meta = yaml.safe_load(meta_path.read_text())
    meta[field] = value
    meta_path.write_text(yaml.safe_dump(meta))
    report = convert("dexycb", tmp_path / "src", tmp_path / "out")
    (entry,) = report["sequences"].values()
    assert entry["status"] == "failed"
    assert f"{meta_path}: field '{field}'" in entry["error"]


def test_dexycb_model_linked_out_of_the_models_folder_is_refused(tmp_path):
    outside = _outside_targets(tmp_path)
    _make_dexycb(tmp_path / "src")
    models = tmp_path / "src" / "models"
    (models / "025_mug" / "textured_simple.obj").unlink()
    (models / "025_mug" / "textured_simple.obj").symlink_to(outside / "textured_simple.obj")
    report = convert("dexycb", tmp_path / "src", tmp_path / "out")
    (entry,) = report["sequences"].values()
    assert entry["status"] == "failed" and str(models) in entry["error"]


@pytest.mark.parametrize("obj_name", ["../../escape", "a/b", "..", ""])
def test_meshes_are_written_under_the_destination_only(tmp_path, obj_name):
    _box(tmp_path / "box.obj")
    raw = RawSequence("take", _hand(), _poses(), tmp_path / "box.obj", obj_name, 30.0, "right",
                      "generic")  # fmt: skip
    dst = tmp_path / "a" / "out"
    dst.mkdir(parents=True)
    with pytest.raises(DatasetLayoutError, match="field 'obj_name'"):
        write_raw_sequence(raw, dst, ConvertOptions())
    assert not list(tmp_path.rglob("*escape*")) and not list(dst.rglob("*.obj"))


def test_a_destination_meshes_folder_linked_elsewhere_is_refused(tmp_path):
    _box(tmp_path / "box.obj")
    (tmp_path / "elsewhere").mkdir()
    dst = tmp_path / "out"
    dst.mkdir()
    (dst / "meshes").symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    raw = RawSequence("take", _hand(), _poses(), tmp_path / "box.obj", "box", 30.0, "right",
                      "generic")  # fmt: skip
    with pytest.raises(DatasetLayoutError, match=f"leads out of {dst}"):
        write_raw_sequence(raw, dst, ConvertOptions())
    assert not list((tmp_path / "elsewhere").iterdir())


# ------------------------------------------------------------ what the first probe still found


def test_a_pickled_array_asking_for_gigabytes_up_front_is_refused(tmp_path):
    """numpy's ``_reconstruct`` allocates the shape it is given before any byte is read: a
    1 KB pickle asking for (30M, 21, 3) is refused without allocating."""

    class _Bomb:
        def __reduce__(self):
            return np._core.multiarray._reconstruct, (np.ndarray, (30_000_000, 21, 3), b"b")

    path = tmp_path / "bomb.pkl"
    path.write_bytes(pickle.dumps({"handJoints3D": _Bomb()}, protocol=2))
    assert path.stat().st_size < 1024
    tracemalloc.start()
    with pytest.raises(SequenceFormatError, match=r"shape \(30000000, 21, 3\) allocated up front"):
        load_pickle(path)
    assert tracemalloc.get_traced_memory()[1] < 16 * 1024**2
    tracemalloc.stop()
    arrays = {"a": np.arange(12.0).reshape(3, 4), "b": np.zeros((0, 3)), "c": np.float32(2)}
    plain = tmp_path / "plain.pkl"
    plain.write_bytes(pickle.dumps(arrays, protocol=4))
    _assert_same(load_pickle(plain), arrays)  # numpy's own pickles still read


def test_ho3d_frame_numbers_may_not_span_more_than_max_frames(tmp_path):
    """A stray frame file numbered past MAX_FRAMES beside a dozen real ones would make a
    sequence of a million empty frames."""
    src = tmp_path / "src"
    _write_ho3d(src / "subject" / "take", _hand(), _poses())
    _box(src / "models" / "025_mug" / "textured_simple.obj")
    meta = src / "subject" / "take" / "meta"
    stray = meta / f"{MAX_FRAMES + 5}.pkl"
    stray.write_bytes(next(meta.glob("*.pkl")).read_bytes())
    report = convert("ho3d", src, tmp_path / "out")
    error = report["sequences"]["subject_take"]["error"]
    assert str(meta) in error and f"expected at most {MAX_FRAMES}" in error, error
    assert not list((tmp_path / "out").rglob("*.npz"))


def test_a_source_file_linked_out_of_the_source_is_refused(tmp_path):
    src, outside = tmp_path / "gen", tmp_path / "elsewhere"
    _box(src / "box.obj")
    outside.mkdir()
    np.savez(
        outside / "seq.npz", keypoints=_hand(), obj_pose=_poses(), obj_mesh="box.obj", fps=30.0
    )
    (src / "linked.npz").symlink_to(outside / "seq.npz")
    report = convert("generic", src, tmp_path / "out")
    error = report["sequences"]["linked"]["error"]
    assert str(src / "linked.npz") in error and "field '<file>'" in error, error


@pytest.mark.parametrize("fps", [np.array("thirty"), np.array([30.0, 30.0])])
def test_an_fps_that_is_not_one_number_is_named(tmp_path, fps):
    path = tmp_path / "seq.npz"
    seq = make_sequence()
    np.savez(path, keypoints=seq.keypoints, obj_pose=seq.obj_pose, obj_mesh="m.obj",
             obj_name="box", fps=fps)  # fmt: skip
    with pytest.raises(SequenceFormatError, match=r"field 'fps': expected one number > 0"):
        load_sequence(path)
