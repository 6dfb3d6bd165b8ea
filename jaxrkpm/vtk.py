"""VTK export of a solution for ParaView: XML UnstructuredGrid (.vtu), ASCII, no extra dependency.

Each particle is one VTK_VERTEX cell at its reference position; point data carry the
displacement u (3 components, z = 0 in 2D so ParaView's "Warp By Vector" works), the stress
tensor (9 components, row-major, padded to 3x3 in 2D), its von Mises value, and the particle
volumes. ``read_vtu`` parses such a file back (used by the tests; also handy for checks).
"""
from __future__ import annotations

import os
import xml.etree.ElementTree as ET

import numpy as np

VTK_VERTEX = 1


def _pad3(a: np.ndarray) -> np.ndarray:
    """(N, d) -> (N, 3) with zero padding (VTK points and vectors are always 3D)."""
    a = np.asarray(a, dtype=float)
    out = np.zeros((a.shape[0], 3))
    out[:, : a.shape[1]] = a
    return out


def _pad33(s: np.ndarray) -> np.ndarray:
    """(N, d, d) -> (N, 3, 3) with zero padding (a 2D plane-strain-free tensor: zeros out of plane)."""
    s = np.asarray(s, dtype=float)
    out = np.zeros((s.shape[0], 3, 3))
    d = s.shape[1]
    out[:, :d, :d] = s
    return out


def von_mises(s33: np.ndarray) -> np.ndarray:
    """von Mises equivalent stress of (N, 3, 3) tensors: sqrt(3/2 dev:dev)."""
    dev = s33 - np.trace(s33, axis1=1, axis2=2)[:, None, None] * np.eye(3) / 3.0
    return np.sqrt(1.5 * np.einsum("nij,nij->n", dev, dev))


def _data_array(parent, name: str, values: np.ndarray, ncomp: int):
    el = ET.SubElement(parent, "DataArray", type="Float64" if values.dtype.kind == "f" else "Int64",
                       Name=name, NumberOfComponents=str(ncomp), format="ascii")
    flat = values.reshape(-1)
    el.text = "\n" + " ".join(repr(float(v)) if values.dtype.kind == "f" else str(int(v))
                              for v in flat) + "\n"
    return el


def write_points_vtu(path, points, point_data: dict | None = None) -> str:
    """Write points (N, 2|3) with named point data arrays (N,), (N, k) or (N, a, b) to ``path``.

    Returns the path. Raises ValueError on shape mismatches or a non-.vtu name.
    """
    path = os.fspath(path)
    if not path.endswith(".vtu"):
        raise ValueError(f"path {path!r} must end with '.vtu' (XML UnstructuredGrid)")
    X = np.asarray(points, dtype=float)
    if X.ndim != 2 or X.shape[1] not in (2, 3):
        raise ValueError(f"points must be (N, 2) or (N, 3), got shape {X.shape}")
    n = X.shape[0]
    root = ET.Element("VTKFile", type="UnstructuredGrid", version="1.0", byte_order="LittleEndian",
                      header_type="UInt64")
    piece = ET.SubElement(ET.SubElement(root, "UnstructuredGrid"), "Piece",
                          NumberOfPoints=str(n), NumberOfCells=str(n))
    pd = ET.SubElement(piece, "PointData")
    for name, arr in (point_data or {}).items():
        a = np.asarray(arr, dtype=float)
        if a.shape[0] != n:
            raise ValueError(f"point data {name!r} has {a.shape[0]} rows, expected {n} (one per point)")
        _data_array(pd, name, a, int(np.prod(a.shape[1:])) if a.ndim > 1 else 1)
    _data_array(ET.SubElement(piece, "Points"), "Points", _pad3(X), 3)
    cells = ET.SubElement(piece, "Cells")
    _data_array(cells, "connectivity", np.arange(n, dtype=np.int64), 1)
    _data_array(cells, "offsets", np.arange(1, n + 1, dtype=np.int64), 1)
    ET.SubElement(cells, "DataArray", type="UInt8", Name="types", format="ascii").text = (
        " ".join([str(VTK_VERTEX)] * n))
    ET.ElementTree(root).write(path, xml_declaration=True, encoding="utf-8")
    return path


def write_solution(path, model, sol, stress: str = "cauchy") -> str:
    """Write a solved model's particles (reference positions), displacement and stress to .vtu.

    ``stress`` is 'cauchy', 'pk1' or 'pk2' (Model.stress kinds). Stress is evaluated at the
    particles themselves (RK fields are smooth there), not at the quadrature points.
    """
    X = np.asarray(model.body.X)
    u = np.asarray(model.particle_displacements(sol))
    s = _pad33(np.asarray(model.stress(sol, X, kind=stress)))
    data = {"displacement": _pad3(u), f"stress_{stress}": s.reshape(-1, 9),
            f"von_mises_{stress}": von_mises(s), "volume": np.asarray(model.body.volumes)}
    return write_points_vtu(path, X, data)


def read_vtu(path) -> dict:
    """Parse an ASCII .vtu written here: {'points': (N, 3), 'cell_types': (N,), name: array}.

    Arrays with k > 1 components come back as (N, k).
    """
    root = ET.parse(os.fspath(path)).getroot()
    if root.get("type") != "UnstructuredGrid":
        raise ValueError(f"{path}: not a VTK UnstructuredGrid file (type={root.get('type')!r})")
    piece = root.find("UnstructuredGrid/Piece")
    n = int(piece.get("NumberOfPoints"))

    def arr(el):
        k = int(el.get("NumberOfComponents", "1"))
        v = np.array((el.text or "").split(), dtype=float)
        return v.reshape(n, k) if k > 1 else v

    out = {"points": arr(piece.find("Points/DataArray"))}
    out["cell_types"] = np.array(piece.find("Cells/DataArray[@Name='types']").text.split(), dtype=int)
    for el in piece.findall("PointData/DataArray"):
        out[el.get("Name")] = arr(el)
    return out
