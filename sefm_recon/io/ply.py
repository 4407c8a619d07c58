"""Binary PLY point clouds and meshes, written atomically; read through open3d.

Point-cloud files carry the vertex properties ``x y z nx ny nz red green blue``
(positions and normals as ``float``, colours as ``uchar``), binary
little-endian -- the layout of COLMAP's own ``fused.ply``, which MeshLab and
CloudCompare read. They are written as numpy record arrays (the bytes
open3d's tensor writer gives, several times faster and without holding
Python's lock). Meshes are written the same way in open3d's own layout
(``double`` vertices), so that writing them needs no open3d. Properties whose
data is absent (no normals, no colours) are omitted.

Empty inputs: open3d refuses to write a cloud or mesh with no vertices, and an
empty reconstruction is almost always a bug upstream, so the writers raise
``ValueError`` for N = 0 instead of producing an empty file.

Every writer writes to a hidden temporary file next to the target (same folder,
same extension, because open3d and OpenCV pick the format from the extension)
and then ``os.replace``-s it into place, so a reader never sees a half-written
file. :func:`atomic_path` is shared by the other writers in ``sefm_recon.io``.

open3d is imported lazily inside the functions (its import costs ~1 s).
"""

from __future__ import annotations

import contextlib
import logging
import os
import secrets
from pathlib import Path
from typing import Iterator

import numpy as np

from .space import check_written

log = logging.getLogger(__name__)

#: Vertices packed and written at a time (9 MB of a cloud's records with normals and colours): a buffer
#: reused from block to block, so that writing millions of vertices costs no fresh memory.
_WRITE_BLOCK = 1 << 18

__all__ = [
    "atomic_path",
    "iter_point_cloud",
    "read_mesh",
    "read_ply_header",
    "read_point_cloud",
    "write_mesh",
    "write_point_cloud",
]


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path to write to; on success move it onto ``path``.

    The temporary name is ``.<name>.tmp-<random><suffix>`` in the same folder as
    ``path`` (so ``os.replace`` is atomic and the extension is preserved). The
    file is not created here -- the writer creates it, with normal permissions.
    On an exception the temporary file is removed and ``path`` is untouched.
    The parent folder is created if missing.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp-{secrets.token_hex(4)}{path.suffix}")
    try:
        yield tmp
        if not tmp.exists():
            raise OSError(f"writer did not create {tmp}")
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def read_ply_header(path: str | os.PathLike) -> dict:
    """Parse a PLY header (pure Python, no open3d).

    Returns ``{"format": "binary_little_endian" | "ascii" | ...,
    "elements": {name: {"count": int, "properties": [(type, name), ...]}}}``;
    list properties appear as ``("list <count type> <item type>", name)``.
    """
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise ValueError(f"{path}: not a PLY file")
        fmt = None
        elements: dict[str, dict] = {}
        current = None
        for raw in f:
            words = raw.decode("ascii", "replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                current = {"count": int(words[2]), "properties": []}
                elements[words[1]] = current
            elif words[0] == "property" and current is not None:
                if words[1] == "list":
                    current["properties"].append((" ".join(words[1:4]), words[4]))
                else:
                    current["properties"].append((words[1], words[2]))
        else:
            raise ValueError(f"{path}: PLY header has no end_header")
    return {"format": fmt, "elements": elements}


def _check_xyz(xyz: np.ndarray, name: str = "xyz") -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"{name} must be (N, 3), got {xyz.shape}")
    return xyz


def _check_rgb(rgb: np.ndarray | None, n: int, name: str = "rgb") -> np.ndarray | None:
    if rgb is None:
        return None
    rgb = np.asarray(rgb)
    if rgb.shape != (n, 3):
        raise ValueError(f"{name} must be ({n}, 3), got {rgb.shape}")
    if rgb.dtype != np.uint8:
        raise ValueError(f"{name} must be uint8, got {rgb.dtype}")
    return rgb


def _to_uint8_colors(c: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(np.asarray(c) * 255.0), 0, 255).astype(np.uint8)


def _check_normals(normals: np.ndarray | None, n: int, name: str = "normals") -> np.ndarray | None:
    if normals is None:
        return None
    normals = _check_xyz(normals, name)
    if len(normals) != n:
        raise ValueError(f"{name} must be ({n}, 3), got {normals.shape}")
    return normals


_PLY_NAMES = {"<f4": "float", "<f8": "double", "u1": "uchar"}


def _vertex_dtype(real: str, normals: bool, colors: bool) -> np.dtype:
    """The vertex record ``x y z [nx ny nz] [red green blue]``, positions and normals of
    type ``real`` (``"<f4"`` or ``"<f8"``), colours ``uchar``."""
    fields = [(a, real) for a in "xyz"]
    if normals:
        fields += [(a, real) for a in ("nx", "ny", "nz")]
    if colors:
        fields += [(a, "u1") for a in ("red", "green", "blue")]
    return np.dtype(fields)


def _ply_header(vertex: np.dtype, n: int, tail: str = "") -> bytes:
    """A binary little-endian PLY header with ``n`` vertices of the record ``vertex``, then ``tail``
    (further elements' lines)."""
    return "".join(["ply\nformat binary_little_endian 1.0\ncomment Created by sefm-recon\n",
                    f"element vertex {n}\n",
                    *(f"property {_PLY_NAMES[vertex[a].str.replace('|', '')]} {a}\n" for a in vertex.names),
                    tail, "end_header\n"]).encode("ascii")


def _write_vertices(f, vertex: np.dtype, xyz: np.ndarray, normals: np.ndarray | None, rgb: np.ndarray | None) -> int:
    """Write the vertex records of ``xyz``, ``normals`` and ``rgb`` (N, 3) to the file ``f``,
    :data:`_WRITE_BLOCK` at a time through one buffer; returns the bytes written.

    Packing every record into one array took 0.35 s the first time in a process for the bench
    pair's 2.6 M points, most of it in the kernel filling its 71 MB of new pages; a block reused,
    0.04-0.10 s."""
    n = len(xyz)
    rec = np.empty(min(n, _WRITE_BLOCK), vertex)
    for s in range(0, n, len(rec)):
        block = rec[:min(len(rec), n - s)]
        for names, a in (("xyz", xyz), (("nx", "ny", "nz"), normals), (("red", "green", "blue"), rgb)):
            if a is not None:
                for k, name in enumerate(names):
                    block[name] = a[s:s + len(block), k]
        f.write(block.view(np.uint8).data)  # (numpy's tofile says "requested and written", no errno)
    return n * vertex.itemsize


def write_point_cloud(
    path: str | os.PathLike,
    xyz: np.ndarray,
    rgb: np.ndarray | None,
    normals: np.ndarray | None = None,
) -> Path:
    """Write a binary little-endian PLY point cloud atomically.

    Args:
        path: target ``.ply`` file (parent folders are created).
        xyz: (N, 3) float positions, world units.
        rgb: (N, 3) uint8 colours, or None (no colour properties).
        normals: (N, 3) float normals, or None (no normal properties).

    Vertex properties: ``x y z nx ny nz red green blue`` (float x6, uchar x3).
    Raises ``ValueError`` for N = 0 or mismatched shapes; ``OSError`` if the
    write fails. Returns ``Path(path)``.
    """
    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise ValueError(f"point cloud path must end in .ply: {path}")
    xyz = _check_xyz(xyz)
    n = len(xyz)
    if n == 0:
        raise ValueError("refusing to write an empty point cloud (N = 0)")
    rgb = _check_rgb(rgb, n)
    normals = _check_normals(normals, n)
    # numpy's records: open3d's writer (RPly) writes value by value and holds Python's lock
    # throughout (the bench pair's 2.6 M points: 0.41 s, while the COLMAP model could not be
    # built beside it)
    vertex = _vertex_dtype("<f4", normals is not None, rgb is not None)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(_ply_header(vertex, n))
            size = _write_vertices(f, vertex, xyz, normals, rgb)
        check_written(tmp, size)
    log.debug("wrote %d points to %s", n, path)
    return path


def read_point_cloud(
    path: str | os.PathLike,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Read a point cloud.

    Returns ``(xyz (N, 3) float64, rgb (N, 3) uint8 or None, normals (N, 3)
    float64 or None)``; colours/normals are None when the file has none.
    Raises ``FileNotFoundError`` if the file is missing.
    """
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(path)
    pcd = o3d.io.read_point_cloud(str(path))
    xyz = np.asarray(pcd.points, dtype=np.float64).reshape(-1, 3).copy()
    rgb = _to_uint8_colors(pcd.colors) if pcd.has_colors() else None
    normals = np.asarray(pcd.normals, dtype=np.float64).copy() if pcd.has_normals() else None
    return xyz, rgb, normals


_PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1", "uint8": "u1",
              "char": "i1", "int8": "i1", "short": "<i2", "ushort": "<u2", "int": "<i4", "int32": "<i4",
              "uint": "<u4", "uint32": "<u4"}


def iter_point_cloud(
    path: str | os.PathLike, block: int = 1 << 18,
) -> Iterator[tuple[np.ndarray, np.ndarray | None, np.ndarray | None]]:
    """Read a point cloud back in blocks of ``block`` points: ``(xyz float64, rgb uint8 or None, normals or None)``.

    A binary little-endian PLY with a single vertex element of scalar properties
    (what :func:`write_point_cloud` writes) is memory-mapped, so only one block is
    in memory at a time; any other file is read whole and then cut into blocks.
    """
    path = Path(path)
    head = read_ply_header(path)
    els = head["elements"]
    props = els.get("vertex", {}).get("properties", [])
    simple = (head["format"] == "binary_little_endian" and list(els) == ["vertex"]
              and all(t in _PLY_TYPES for t, _ in props))
    if not simple:
        xyz, rgb, nrm = read_point_cloud(path)
        for s in range(0, len(xyz), block):
            yield xyz[s:s + block], None if rgb is None else rgb[s:s + block], None if nrm is None else nrm[s:s + block]
        return
    dtype = np.dtype([(name, _PLY_TYPES[t]) for t, name in props])
    n = els["vertex"]["count"]
    with open(path, "rb") as f:
        while f.readline().strip() != b"end_header":
            pass
        start = f.tell()
    if n == 0:
        return
    data = np.memmap(path, dtype=dtype, mode="r", offset=start, shape=(n,))
    names = set(dtype.names)
    try:
        for s in range(0, n, block):
            chunk = data[s:s + block]
            xyz = np.stack([chunk[c].astype(np.float64) for c in ("x", "y", "z")], 1)
            rgb = (np.stack([chunk[c] for c in ("red", "green", "blue")], 1).astype(np.uint8)
                   if {"red", "green", "blue"} <= names else None)
            nrm = (np.stack([chunk[c].astype(np.float64) for c in ("nx", "ny", "nz")], 1)
                   if {"nx", "ny", "nz"} <= names else None)
            yield xyz, rgb, nrm
    finally:
        del data


def write_mesh(
    path: str | os.PathLike,
    vertices: np.ndarray,
    triangles: np.ndarray,
    vertex_colors: np.ndarray | None = None,
    vertex_normals: np.ndarray | None = None,
) -> Path:
    """Write a binary little-endian PLY triangle mesh atomically.

    Args:
        path: target ``.ply`` file.
        vertices: (V, 3) float positions.
        triangles: (F, 3) int vertex indices (counter-clockwise = front).
        vertex_colors: (V, 3) uint8 or None.
        vertex_normals: (V, 3) float or None.

    Vertex properties ``x y z [nx ny nz] [red green blue]`` (double, uchar), faces
    ``vertex_indices`` (a uchar count, uint indices): the layout open3d writes.
    Raises ``ValueError`` for V = 0, bad shapes or out-of-range indices.
    Returns ``Path(path)``.
    """
    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise ValueError(f"mesh path must end in .ply: {path}")
    vertices = _check_xyz(vertices, "vertices")
    v = len(vertices)
    if v == 0:
        raise ValueError("refusing to write an empty mesh (0 vertices)")
    triangles = np.asarray(triangles)
    if triangles.size == 0:
        triangles = triangles.reshape(0, 3)
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise ValueError(f"triangles must be (F, 3), got {triangles.shape}")
    if triangles.size and (triangles.min() < 0 or triangles.max() >= v):
        raise ValueError("triangle indices out of range")
    vertex_colors = _check_rgb(vertex_colors, v, "vertex_colors")
    vertex_normals = _check_normals(vertex_normals, v, "vertex_normals")
    # numpy's records, as for the point cloud: open3d's writer is as quick on a mesh of the
    # default grid's size, but importing open3d took 0.9 s of every `pair` run that needs
    # it for nothing else (its write stage 1.1 s in a fresh process, 0.45 s once imported)
    vertex = _vertex_dtype("<f8", vertex_normals is not None, vertex_colors is not None)
    faces = np.empty(len(triangles), np.dtype([("n", "u1"), ("v", "<u4", (3,))]))
    faces["n"] = 3
    faces["v"] = triangles
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(_ply_header(vertex, v, f"element face {len(faces)}\nproperty list uchar uint vertex_indices\n"))
            size = _write_vertices(f, vertex, vertices, vertex_normals, vertex_colors)
            f.write(faces.view(np.uint8).data)
        check_written(tmp, size + faces.nbytes)
    log.debug("wrote mesh (%d vertices, %d triangles) to %s", v, len(triangles), path)
    return path


def read_mesh(
    path: str | os.PathLike,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Read a triangle mesh.

    Returns ``(vertices (V, 3) float64, triangles (F, 3) int64,
    vertex_colors (V, 3) uint8 or None, vertex_normals (V, 3) float64 or None)``.
    """
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(path)
    mesh = o3d.io.read_triangle_mesh(str(path))
    vertices = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3).copy()
    triangles = np.asarray(mesh.triangles, dtype=np.int64).reshape(-1, 3).copy()
    colors = _to_uint8_colors(mesh.vertex_colors) if mesh.has_vertex_colors() else None
    normals = (
        np.asarray(mesh.vertex_normals, dtype=np.float64).copy()
        if mesh.has_vertex_normals()
        else None
    )
    return vertices, triangles, colors, normals
