"""Point clouds as PLY files: ``x y z`` and ``red green blue``, the layout of 3DGS's own ``points3D.ply`` (with zero
normals). ``mi-gs points`` writes the cloud a run would start from; ``mi-gs view`` and ``mi-gs info`` read one (a
PLY with positions but without the 3DGS attributes), the viewer showing each point as a small Gaussian."""

from __future__ import annotations

import os

import numpy as np

from ..io_utils import atomic_path
from .ply import PLYError, read_ply_header, read_vertices


def is_point_cloud(path: str | os.PathLike) -> bool:
    """Whether the PLY file ``path`` holds points (``x y z``) rather than 3DGS Gaussians (no ``opacity``)."""
    vertex = read_ply_header(path).element("vertex")
    names = {p.name for p in vertex.properties} if vertex is not None else set()
    return {"x", "y", "z"} <= names and "opacity" not in names


def write_points(path: str | os.PathLike, xyz, rgb) -> None:
    """Write points (N, 3) with colours (N, 3) in [0, 1] as a binary PLY (float x y z nx ny nz, uchar red green blue),
    atomically."""
    xyz = np.asarray(xyz, np.float32).reshape(-1, 3)
    rgb = np.asarray(rgb, np.float64).reshape(-1, 3)
    if len(rgb) != len(xyz):
        raise PLYError(path, f"cannot write {len(xyz)} points with {len(rgb)} colours")
    if not np.all(np.isfinite(xyz)):
        raise PLYError(path, "cannot write non-finite point positions")
    names = ("x", "y", "z", "nx", "ny", "nz", "red", "green", "blue")
    dtype = np.dtype([(n, "<f4") for n in names[:6]] + [(n, "u1") for n in names[6:]])
    rec = np.zeros(len(xyz), dtype)
    for i, n in enumerate("xyz"):
        rec[n] = xyz[:, i]
    for i, n in enumerate(("red", "green", "blue")):
        rec[n] = np.clip(np.round(np.nan_to_num(rgb[:, i]) * 255.0), 0, 255).astype(np.uint8)
    header = ("ply\nformat binary_little_endian 1.0\n" + f"element vertex {len(xyz)}\n"
              + "".join(f"property float {n}\n" for n in names[:6])
              + "".join(f"property uchar {n}\n" for n in names[6:]) + "end_header\n")
    with atomic_path(path, suffix=".ply") as tmp:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(rec.tobytes())


def read_points(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (N, 3) float32, rgb (N, 3) float32 in [0, 1]) of a point-cloud PLY: ``red green blue`` as bytes (or
    floats in [0, 1]); grey without them. PLYError (one line naming the file) when it has no positions or holds
    non-finite ones."""
    vertex, rec = read_vertices(path)
    names = {p.name for p in vertex.properties}
    if not {"x", "y", "z"} <= names:
        raise PLYError(path, "no point positions (vertex properties x, y, z)")
    xyz = np.stack([np.asarray(rec[n], np.float64) for n in "xyz"], axis=1).astype(np.float32)
    if not np.all(np.isfinite(xyz)):
        raise PLYError(path, f"{int((~np.isfinite(xyz)).any(axis=1).sum())} points with non-finite positions")
    if {"red", "green", "blue"} <= names:
        rgb = np.stack([np.asarray(rec[n], np.float64) for n in ("red", "green", "blue")], axis=1)
        integer = all(rec.dtype.fields[n][0].kind in "iu" for n in ("red", "green", "blue"))
        rgb = rgb / 255.0 if integer else rgb
    else:
        rgb = np.full((len(xyz), 3), 0.5)
    return xyz, np.clip(np.nan_to_num(rgb), 0.0, 1.0).astype(np.float32)
