"""NumPy ``.npz`` archives: reading a tetrahedral mesh (:func:`read_npz`) and writing arrays to exactly a path
(:func:`save_npz`).

The archive holds ``tets`` (k, 4) integer and the vertex positions (m, 3) under the first of these names
that is present: ``vertices``, ``rest_positions``, ``positions``. Nothing is unpickled
(``allow_pickle=False``). Before any array is loaded, the sizes the archive declares are checked: every member's
uncompressed size (the zip directory) against the cap on decompressed mesh data (1 GiB unless the environment
variable ``FEPR_MAX_MESH_BYTES`` says otherwise, :mod:`fepr.io._limits`), and the shape and dtype in each loaded
array's ``.npy`` header against its member's size, so a small deflated archive cannot make NumPy allocate or
inflate gigabytes.
"""

from __future__ import annotations

import ast
import os
import struct
import zipfile
from pathlib import Path
from typing import Dict, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from ..errors import MeshError
from ._checks import check_duplicate_tets
from ._limits import max_mesh_bytes, over_limit

__all__ = ["VERTEX_KEYS", "check_npz_sizes", "read_npz", "save_npz"]

PathLike = Union[str, "os.PathLike[str]"]

VERTEX_KEYS = ("vertices", "rest_positions", "positions")


def read_npz(path: PathLike) -> Tuple[np.ndarray, np.ndarray]:
    """Read a mesh from an ``.npz`` archive.

    Returns
    -------
    vertices : numpy.ndarray, shape (m, 3), float64
    tets : numpy.ndarray, shape (k, 4), int64

    Raises
    ------
    MeshError
        If the file is missing or not an ``.npz`` archive, an array is missing (the message lists the arrays
        present), an array has the wrong shape or type, or the archive declares more uncompressed data than its
        members hold or than the cap on decompressed mesh data (``FEPR_MAX_MESH_BYTES``, default 1 GiB; the
        message names the array).
    ConfigError
        If ``FEPR_MAX_MESH_BYTES`` is set to something other than a number of bytes.
    """
    p = Path(os.fspath(path))
    if not p.exists():
        raise MeshError(f"{p}: file not found")
    if not p.is_file():
        raise MeshError(f"{p}: not a regular file")
    check_npz_sizes(p, _arrays_to_load(p))
    try:
        archive = np.load(p, allow_pickle=False)
    except Exception as exc:
        raise MeshError(f"{p}: cannot read as an .npz archive: {type(exc).__name__}: {exc}") from None
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise MeshError(f"{p}: not an .npz archive (it holds a single array; save with numpy.savez)")
    with archive:
        names = list(archive.files)
        key = next((k for k in VERTEX_KEYS if k in names), None)
        if key is None or "tets" not in names:
            missing = [] if key else ["vertices (or rest_positions / positions)"]
            missing += [] if "tets" in names else ["tets"]
            raise MeshError(
                f"{p}: missing array(s) {', '.join(missing)}; the archive holds: {', '.join(names) or 'nothing'}"
            )
        try:
            vertices = archive[key]
            tets = archive["tets"]
        except Exception as exc:
            raise MeshError(f"{p}: cannot read arrays: {type(exc).__name__}: {exc}") from None
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise MeshError(f"{p}: array '{key}' must have shape (m, 3), got {vertices.shape}")
    if not (np.issubdtype(vertices.dtype, np.floating) or np.issubdtype(vertices.dtype, np.integer)):
        raise MeshError(f"{p}: array '{key}' must be numeric, got dtype {vertices.dtype}")
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise MeshError(f"{p}: array 'tets' must have shape (k, 4), got {tets.shape}")
    if not np.issubdtype(tets.dtype, np.integer):
        raise MeshError(f"{p}: array 'tets' must hold integer vertex indices, got dtype {tets.dtype}")
    tets = np.ascontiguousarray(tets, dtype=np.int64)
    check_duplicate_tets(p, tets)
    return np.ascontiguousarray(vertices, dtype=np.float64), tets


# ----------------------------------------------------------------------------------------------------
# Size checks before loading


def _arrays_to_load(p: Path) -> Optional[Tuple[str, ...]]:
    """The arrays :func:`read_npz` loads from the archive: ``tets`` and the first vertex key present."""
    try:
        with zipfile.ZipFile(p) as zf:
            names = {_array_name(i) for i in zf.infolist()}
    except (zipfile.BadZipFile, OSError, ValueError, EOFError):
        return None
    key = next((k for k in VERTEX_KEYS if k in names), None)
    return ("tets",) if key is None else ("tets", key)


def check_npz_sizes(path: PathLike, names: Optional[Sequence[str]] = None) -> None:
    """Raise :class:`MeshError` naming the file and the array if the arrays ``names`` (all arrays when ``None``)
    of the ``.npz`` archive at ``path`` declare more uncompressed data than the cap on decompressed mesh data
    (:func:`fepr.io._limits.max_mesh_bytes`), one array or all of them together, or if an array's ``.npy``
    header declares a shape and dtype larger than its member of the archive holds.

    Only the zip directory and the ``.npy`` headers are read. A file that is not a zip archive is left to
    :func:`numpy.load` (which reports it).
    """
    p = Path(os.fspath(path))
    try:
        zf = zipfile.ZipFile(p)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError):
        return
    cap = max_mesh_bytes()
    with zf:
        wanted = None if names is None else set(names)
        infos = [i for i in zf.infolist() if not i.is_dir() and (wanted is None or _array_name(i) in wanted)]
        if not infos:
            return
        for info in infos:
            if info.file_size > cap:
                raise MeshError(
                    f"{p}: array {_array_name(info)!r} declares {info.file_size} bytes uncompressed "
                    f"({info.compress_size} bytes in the archive), {over_limit(cap)}"
                )
        total = sum(i.file_size for i in infos)
        if total > cap:
            biggest = max(infos, key=lambda i: i.file_size)
            raise MeshError(
                f"{p}: the arrays to load declare {total} bytes uncompressed in all (the largest, "
                f"{_array_name(biggest)!r}, {biggest.file_size} bytes), {over_limit(cap)}"
            )
        for info in infos:
            name = _array_name(info)
            header = _npy_header(zf, info)
            if header is None:
                continue  # not a .npy member numpy can read: numpy.load reports it
            shape, dtype, header_len = header
            count = 1
            for n in shape:
                count *= n
            nbytes = count * dtype.itemsize
            if header_len + nbytes > info.file_size:
                raise MeshError(
                    f"{p}: array {name!r} declares shape {shape} of {dtype} ({nbytes} bytes), but its member of "
                    f"the archive holds only {max(info.file_size - header_len, 0)} bytes of data; the file is "
                    "truncated or corrupt"
                )


def _array_name(info: zipfile.ZipInfo) -> str:
    name = info.filename
    return name[:-4] if name.endswith(".npy") else name


def _npy_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> Optional[Tuple[Tuple[int, ...], np.dtype, int]]:
    """``(shape, dtype, header length)`` from the ``.npy`` header of a member, or ``None`` if it has none that
    numpy would accept (numpy then reports the problem)."""
    try:
        with zf.open(info) as fh:
            magic = fh.read(8)
            if len(magic) < 8 or magic[:6] != b"\x93NUMPY":
                return None
            major = magic[6]
            if major == 1:
                raw = fh.read(2)
                (hlen,) = struct.unpack("<H", raw) if len(raw) == 2 else (None,)
                start = 10
            elif major in (2, 3):
                raw = fh.read(4)
                (hlen,) = struct.unpack("<I", raw) if len(raw) == 4 else (None,)
                start = 12
            else:
                return None
            if hlen is None or hlen > 100_000:
                return None
            text = fh.read(hlen)
        d = ast.literal_eval(text.decode("utf-8" if major == 3 else "latin1"))
        shape = tuple(int(n) for n in d["shape"])
        dtype = np.lib.format.descr_to_dtype(d["descr"])
    except Exception:  # a damaged header or member: numpy.load reports it
        return None
    if any(n < 0 for n in shape):
        return None
    return shape, dtype, start + hlen


# ----------------------------------------------------------------------------------------------------
# Writing


def save_npz(path: PathLike, arrays: Mapping[str, np.ndarray], *, compressed: bool = False) -> Path:
    """Write ``arrays`` to a NumPy ``.npz`` archive at exactly ``path``, atomically; return the path.

    Unlike ``numpy.savez(path, ...)``, no ``.npz`` is appended to a path with another suffix (``"x.npy"`` stays
    ``x.npy``, holding an ``.npz`` archive, which :func:`numpy.load` reads by its content). The archive is written to
    a temporary file in the same folder and renamed onto ``path`` (:func:`fepr.io.atomic.atomic_path`), so a reader
    sees either the previous file or the complete new one, never a half-written one.

    Parameters
    ----------
    path : str or os.PathLike
        The file to write (its folder must exist).
    arrays : mapping of str to array_like
        The archive's arrays by name (as the keyword arguments of :func:`numpy.savez`).
    compressed : bool
        Deflate the members (:func:`numpy.savez_compressed`).

    Raises
    ------
    OSError
        If the file cannot be written (nothing is left behind: the temporary file is removed).
    """
    from .atomic import atomic_path

    target = Path(os.fspath(path))
    payload: Dict[str, np.ndarray] = {str(k): np.asanyarray(v) for k, v in arrays.items()}
    save = np.savez_compressed if compressed else np.savez
    with atomic_path(target) as tmp:
        with open(tmp, "wb") as fh:
            save(fh, **payload)
    return target
