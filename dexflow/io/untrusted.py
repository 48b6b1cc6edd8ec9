"""Reading files from strangers: pickles that run no code, ``.npz`` archives sized before use.

Datasets are downloaded from people the user does not know, so reading one must never run code
from it, nor let its declared sizes decide how much memory is taken.

**Pickles.** Unpickling calls whatever global the file names (``os.system``, ``builtins.exec``):
a crafted HO-3D ``meta/*.pkl``, GRAB ``.npz`` member or MANO file would run its payload.
:class:`RestrictedUnpickler` resolves only the globals that pickles of plain data name: numpy
arrays, scalars and dtypes (numpy 2's ``numpy._core`` names and numpy 1's ``numpy.core`` ones),
sets, complex numbers, and ``_codecs.encode`` for latin-1 only (how protocol 0-2 pickles written
by Python 3 hold bytes). Lists, tuples, dicts, strings, bytes, numbers, None and bools need no
global. ``bytes`` and ``bytearray`` are not callable from a pickle: ``bytes(10**10)`` would
allocate 10 GB from a 20-byte file. Any other global is refused with :class:`UnsafePickleError`,
which names the file and the global (``module.name``). A format may add its own stand-ins
(:meth:`RestrictedUnpickler.find_extra`; MANO maps chumpy classes to an inert holder). A pickle
file may hold at most :data:`MAX_ARRAY_BYTES`.

**Archives.** ``np.load`` inflates a member before anything looks at it: a 1 MB archive of zeros
declaring 2 million frames takes 1 GB before being refused. :func:`load_npz` first reads every
member's ``.npy`` header (a few hundred bytes) and refuses the archive unless:

- each array and all of them together hold at most :data:`MAX_ARRAY_BYTES` (2 GiB). A real
  capture of 100k frames holds 50 MB of keypoints; a sequence of :data:`MAX_FRAMES` frames holds
  0.5 GB of keypoints and 0.13 GB of object poses, which leaves room for extras (MANO parameters,
  stage outputs) while a laptop can still hold the archive;
- with ``max_frames``, no array is longer than that along its first axis (sequences use
  :data:`MAX_FRAMES` = 1,000,000: 9 hours at 30 fps, 2.3 hours at GRAB's 120 fps, ten times the
  longest real captures);
- the uncompressed size the zip records for the member is the header's length plus shape x
  itemsize, as ``np.save`` writes it: a header may not promise less than the member inflates to;
- object arrays (pickles) appear only where the caller allows them, and are read with the
  restricted unpickler: ``np.load(allow_pickle=True)`` is never called.

Damaged archives (a truncated zip, a bad CRC) raise what :mod:`zipfile` or numpy raise, for the
caller to name the file as it does for any unreadable one; refusals are
:class:`~dexflow.errors.SequenceFormatError` naming the file, the member, what was expected and
what was found.
"""

from __future__ import annotations

import _compat_pickle
import math
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from numpy.lib import format as npy_format

from dexflow.errors import SequenceFormatError, UnsafePickleError

__all__ = [
    "MAX_ARRAY_BYTES",
    "MAX_FRAMES",
    "NpyHeader",
    "RestrictedUnpickler",
    "load_npz",
    "load_pickle",
    "read_npz_headers",
]

MAX_ARRAY_BYTES = 2 * 1024**3
MAX_FRAMES = 1_000_000

_NUMPY_CORES = ("numpy.core", "numpy._core")
_SAFE_GLOBALS = frozenset(
    {
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
        *((f"{core}.multiarray", "_reconstruct") for core in _NUMPY_CORES),
        *((f"{core}.multiarray", "scalar") for core in _NUMPY_CORES),
        *((f"{core}.numeric", "_frombuffer") for core in _NUMPY_CORES),
        *(("builtins", name) for name in ("set", "frozenset", "complex", "list", "tuple", "dict")),
    }
)
_RECONSTRUCT_MAX_ITEMS = 1  # numpy pickles reconstruct (0,) and fill it from the bytes
_LATIN1 = ("latin1", "latin-1", "iso-8859-1", "iso8859-1")


def _latin1_bytes(text: str, encoding: str = "utf-8", errors: str = "strict") -> bytes:
    """``_codecs.encode`` as protocol 0-2 pickles use it for bytes: latin-1 only."""
    if not isinstance(text, str) or encoding.lower() not in _LATIN1:
        raise pickle.UnpicklingError(
            f"_codecs.encode is allowed for latin-1 text only, not {type(text).__name__} "
            f"with encoding {encoding!r}"
        )
    return text.encode("latin1", errors)


def _python3_name(module: str, name: str) -> tuple[str, str]:
    """``module.name`` as Python 3 calls it (``__builtin__.set`` -> ``builtins.set``), as
    :meth:`pickle.Unpickler.find_class` maps Python 2 names."""
    if (module, name) in _compat_pickle.NAME_MAPPING:
        return _compat_pickle.NAME_MAPPING[(module, name)]
    return _compat_pickle.IMPORT_MAPPING.get(module, module), name


class RestrictedUnpickler(pickle.Unpickler):
    """An unpickler that builds plain data only and refuses every other global.

    Args:
        file: The open binary stream.
        source: The file it comes from (named in errors).
        field: What part of the file the stream is (``<pickle>``, or an archive's member).
        encoding: How Python 2 ``str`` objects are decoded (``latin1`` keeps numpy's bytes).
    """

    def __init__(
        self,
        file: BinaryIO,
        source: str | Path | None,
        field: str = "<pickle>",
        encoding: str = "latin1",
    ) -> None:
        super().__init__(file, encoding=encoding)
        self.source = source
        self.field = field

    def find_extra(self, module: str, name: str) -> Any | None:
        """A format's own stand-in for ``module.name`` (Python 3 names), or None to apply the
        common rule."""
        return None

    def find_class(self, module: str, name: str) -> Any:
        module3, name3 = _python3_name(module, name)
        extra = self.find_extra(module3, name3)
        if extra is not None:
            return extra
        if (module3, name3) == ("_codecs", "encode"):
            return _latin1_bytes
        if name3 == "_reconstruct" and (module3, name3) in _SAFE_GLOBALS:
            return self._bounded_reconstruct(super().find_class(module3, name3))
        if (module3, name3) in _SAFE_GLOBALS:
            return super().find_class(module3, name3)
        raise UnsafePickleError(self.source, f"{module3}.{name3}", self.field)

    def _bounded_reconstruct(self, reconstruct: Any) -> Any:
        """numpy's ``_reconstruct(subtype, shape, dtype)``, which allocates ``shape`` before the
        array's bytes are read: numpy's own pickles call it with shape ``(0,)`` and fill the
        array from the bytes that follow, so a larger shape is a 1 KB file asking for
        gigabytes and is refused."""

        def bounded(subtype: Any, shape: Any, dtype: Any) -> Any:
            dims = tuple(int(n) for n in np.atleast_1d(shape))
            count = math.prod(dims)
            if count > _RECONSTRUCT_MAX_ITEMS:
                raise SequenceFormatError(
                    self.source,
                    self.field,
                    f"numpy arrays pickled as numpy writes them (reconstructed empty, at most "
                    f"{_RECONSTRUCT_MAX_ITEMS} item, then filled from the file's bytes)",
                    f"an array of shape {dims} allocated up front",
                )
            return reconstruct(subtype, shape, dtype)

        return bounded


def load_pickle(
    file: str | Path | BinaryIO,
    encoding: str = "latin1",
    unpickler: type[RestrictedUnpickler] = RestrictedUnpickler,
) -> Any:
    """Unpickle plain data (arrays, numbers, strings, containers) without running any code.

    Args:
        file: A path, or an open binary stream (named by its ``name`` if it has one).
        encoding: How Python 2 ``str`` objects are decoded.
        unpickler: :class:`RestrictedUnpickler` or a subclass adding a format's stand-ins.

    Returns:
        The unpickled object.

    Raises:
        UnsafePickleError: The pickle names a global outside the allowed ones.
        SequenceFormatError: The file is larger than :data:`MAX_ARRAY_BYTES`.
    """
    if isinstance(file, (str, Path)):
        size = Path(file).stat().st_size
        if size > MAX_ARRAY_BYTES:
            raise SequenceFormatError(
                file, "<pickle>", f"a pickle of at most {MAX_ARRAY_BYTES} bytes (MAX_ARRAY_BYTES)",
                f"{size} bytes",
            )  # fmt: skip
        with open(file, "rb") as handle:
            return unpickler(handle, file, encoding=encoding).load()
    return unpickler(file, getattr(file, "name", None), encoding=encoding).load()


@dataclass(frozen=True)
class NpyHeader:
    """What an ``.npy`` header declares.

    Attributes:
        shape: The array's shape.
        dtype: Its dtype.
        fortran_order: Whether the data is column-major.
        header_bytes: Length of the magic string and header, before the data.
    """

    shape: tuple[int, ...]
    dtype: np.dtype
    fortran_order: bool
    header_bytes: int

    @property
    def nbytes(self) -> int:
        """Bytes of the data (Python ints: no overflow)."""
        return math.prod(self.shape) * self.dtype.itemsize


def _read_header(path: Path, key: str, member: BinaryIO) -> NpyHeader:
    """The header at the start of one member (reads a few hundred bytes of it)."""
    try:
        version = npy_format.read_magic(member)
        if version not in ((1, 0), (2, 0)):
            raise ValueError(f"version {version[0]}.{version[1]}")
        read = (
            npy_format.read_array_header_1_0
            if version == (1, 0)
            else npy_format.read_array_header_2_0
        )
        shape, fortran_order, dtype = read(member)
    except ValueError as exc:
        raise SequenceFormatError(
            path, key, "an .npy array of format version 1.0 or 2.0 (np.savez)", str(exc)
        ) from exc
    return NpyHeader(tuple(shape), dtype, bool(fortran_order), member.tell())


def _check_header(
    path: Path,
    key: str,
    header: NpyHeader,
    file_size: int,
    allow_objects: bool,
    max_frames: int | None,
) -> None:
    """Refuse a member whose header is unsafe or does not match its zip entry."""
    shape = header.shape
    if any(d < 0 for d in shape):
        raise SequenceFormatError(path, key, "a shape of sizes >= 0", f"shape {shape}")
    if header.dtype.hasobject:
        if not allow_objects:
            raise SequenceFormatError(
                path, key, "numeric and string arrays only", "an array of Python objects "
                "(pickled; save strings as np.array('text'), not dtype=object)",
            )  # fmt: skip
        data_bytes = file_size - header.header_bytes
        if data_bytes > MAX_ARRAY_BYTES:
            raise SequenceFormatError(
                path, key, f"a pickled member of at most {MAX_ARRAY_BYTES} bytes "
                "(MAX_ARRAY_BYTES)", f"{data_bytes} bytes",
            )  # fmt: skip
        return
    if max_frames is not None and shape and shape[0] > max_frames:
        raise SequenceFormatError(
            path, key, f"at most {max_frames} frames (MAX_FRAMES)", f"shape {shape}"
        )
    if header.nbytes > MAX_ARRAY_BYTES:
        raise SequenceFormatError(
            path, key, f"an array of at most {MAX_ARRAY_BYTES} bytes (MAX_ARRAY_BYTES)",
            f"shape {shape} of {header.dtype}: {header.nbytes} bytes",
        )  # fmt: skip
    if file_size != header.header_bytes + header.nbytes:
        raise SequenceFormatError(
            path, key, f"a zip entry of {header.header_bytes} + {header.nbytes} bytes "
            f"uncompressed, as its header declares shape {shape} of {header.dtype}",
            f"{file_size} bytes",
        )  # fmt: skip


def read_npz_headers(
    path: str | Path,
    archive: zipfile.ZipFile,
    allow_objects: bool = False,
    max_frames: int | None = None,
) -> dict[str, tuple[zipfile.ZipInfo, NpyHeader]]:
    """Read and check the header of every member of an open archive, inflating no data.

    Args:
        path: The archive's file (named in errors).
        archive: The open archive.
        allow_objects: Whether object arrays (pickles) may appear.
        max_frames: If given, the most rows any array may have along its first axis.

    Returns:
        Per array name (the member's name without ``.npy``) its zip entry and header.

    Raises:
        SequenceFormatError: A member is not an ``.npy`` array or fails a check of the module
            docstring.
    """
    path = Path(path)
    headers: dict[str, tuple[zipfile.ZipInfo, NpyHeader]] = {}
    total = 0
    for info in archive.infolist():
        if not info.filename.endswith(".npy"):
            raise SequenceFormatError(
                path, info.filename, "only .npy arrays in the archive (np.savez)", "another file"
            )
        key = info.filename.removesuffix(".npy")
        with archive.open(info) as member:
            header = _read_header(path, key, member)
        _check_header(path, key, header, info.file_size, allow_objects, max_frames)
        total += info.file_size - header.header_bytes
        if total > MAX_ARRAY_BYTES:
            raise SequenceFormatError(
                path, "<file>", f"arrays of at most {MAX_ARRAY_BYTES} bytes in all "
                "(MAX_ARRAY_BYTES)", f"{total} bytes up to '{key}'",
            )  # fmt: skip
        headers[key] = (info, header)
    return headers


def _read_objects(
    path: Path, key: str, member: BinaryIO, header: NpyHeader, encoding: str
) -> np.ndarray:
    """An object array's pickle, read with the restricted unpickler (past its header)."""
    member.read(header.header_bytes)
    array = RestrictedUnpickler(member, path, key, encoding).load()
    if not isinstance(array, np.ndarray) or array.shape != header.shape:
        found = getattr(array, "shape", type(array).__name__)
        raise SequenceFormatError(
            path, key, f"a pickled array of shape {header.shape}, as its header says", str(found)
        )
    return array


def load_npz(
    path: str | Path,
    allow_objects: bool = False,
    max_frames: int | None = None,
    encoding: str = "ASCII",
) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` archive, its headers checked before any data is inflated.

    Non-object arrays are read exactly as ``np.load`` reads them.

    Args:
        path: The archive.
        allow_objects: Whether object arrays may appear; they are unpickled with
            :class:`RestrictedUnpickler` (GRAB's dicts).
        max_frames: If given, the most rows any array may have along its first axis.
        encoding: How Python 2 ``str`` objects in pickled members are decoded (numpy's default).

    Returns:
        Per array name (member name without ``.npy``) the array.

    Raises:
        SequenceFormatError: A header fails a check (see the module docstring).
        UnsafePickleError: A pickled member names a global outside the allowed ones.
    """
    path = Path(path)
    arrays: dict[str, np.ndarray] = {}
    with zipfile.ZipFile(path) as archive:
        headers = read_npz_headers(path, archive, allow_objects, max_frames)
        for key, (info, header) in headers.items():
            with archive.open(info) as member:
                if header.dtype.hasobject:
                    arrays[key] = _read_objects(path, key, member, header, encoding)
                else:
                    arrays[key] = npy_format.read_array(member, allow_pickle=False)
    return arrays
