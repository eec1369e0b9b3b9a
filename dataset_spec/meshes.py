"""Triangle meshes as binary little-endian PLY (readable by trimesh, Blender, MeshLab).

Actor meshes are stored in world coordinates (metres), so rasterising them with a camera's
K and extrinsics gives the actor's amodal silhouette.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .atomic import atomic_write_bytes
from .errors import SpecError

_FACE_DTYPE = np.dtype([("n", "u1"), ("v", "<i4", (3,))])


def write_mesh(path: str | Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    vertices = np.asarray(vertices, dtype="<f4")
    faces = np.asarray(faces, dtype="<i4")
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"mesh needs vertices (N, 3) and triangle faces (M, 3), got {vertices.shape} {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError("mesh faces index outside the vertex array")
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode("ascii")
    face_rec = np.zeros(len(faces), dtype=_FACE_DTYPE)
    face_rec["n"] = 3
    face_rec["v"] = faces
    atomic_write_bytes(path, header + vertices.tobytes() + face_rec.tobytes())


def read_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a mesh written by ``write_mesh`` -> (vertices (N, 3) float64, faces (M, 3) int64)."""
    path = Path(path)
    if not path.is_file():
        raise SpecError(path, "mesh file is missing")
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise SpecError(path, "not a PLY file")
    try:
        lines = data[:end].decode("ascii").splitlines()
        n_vert = n_face = None
        for line in lines:
            parts = line.split()
            if parts[:2] == ["element", "vertex"]:
                n_vert = int(parts[2])
            elif parts[:2] == ["element", "face"]:
                n_face = int(parts[2])
        if "format binary_little_endian 1.0" not in lines or n_vert is None or n_face is None:
            raise ValueError("unsupported PLY header")
    except (ValueError, UnicodeDecodeError, IndexError) as exc:
        raise SpecError(path, f"malformed PLY header ({exc})") from None
    body = data[end + len(b"end_header\n"):]
    need = n_vert * 12 + n_face * _FACE_DTYPE.itemsize
    if n_vert < 0 or n_face < 0 or len(body) != need:
        raise SpecError(path, f"PLY body has {len(body)} bytes, header says {need} (truncated?)")
    verts = np.frombuffer(body[: n_vert * 12], dtype="<f4").reshape(n_vert, 3).astype(np.float64)
    faces = np.frombuffer(body[n_vert * 12:], dtype=_FACE_DTYPE)
    if n_face and (np.any(faces["n"] != 3) or faces["v"].min() < 0 or faces["v"].max() >= n_vert):
        raise SpecError(path, "PLY faces are not valid triangles of this mesh")
    return verts, faces["v"].astype(np.int64)
