"""ParaView output: VTK XML unstructured grids (``.vtu``, binary base64 inline, UInt64 headers),
one file per part and frame, and one ``.pvd`` collection that lists them by time.

Layout of ``<run>/<output.vtk>/``:
- ``fluid_NNNNN.vtu``: fluid particles as vertex cells; point data ``velocity`` (m/s),
  ``speed`` (m/s), ``density`` (kg/m^3), ``pressure`` (Pa);
- ``blocks_NNNNN.vtu``: rock blocks as VTK polyhedra (cell type 42) in world coordinates; cell data
  ``block`` (index);
- ``surface_NNNNN.vtu``: the fluid surface (triangles in 3D, line segments in 2D);
- ``rockwave.pvd``: the series: one ``DataSet`` per part and frame with ``timestep`` (s), ``part``
  and ``name``; open it in ParaView for all parts over time.
Every file is written to a temporary name and renamed into place.
"""

from __future__ import annotations

import base64
import os
from pathlib import Path

import numpy as np

VTK_VERTEX, VTK_LINE, VTK_TRIANGLE, VTK_POLYHEDRON = 1, 3, 5, 42
_VTK_TYPES = {np.dtype(np.float32): "Float32", np.dtype(np.float64): "Float64", np.dtype(np.int32): "Int32",
              np.dtype(np.int64): "Int64", np.dtype(np.uint8): "UInt8"}
PARTS = ("fluid", "blocks", "surface")


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _data_array(name: str, a: np.ndarray, ncomp: int = 1) -> str:
    a = np.ascontiguousarray(a)
    raw = a.tobytes()
    enc = base64.b64encode(np.uint64(len(raw)).tobytes() + raw).decode("ascii")
    return (f'<DataArray type="{_VTK_TYPES[a.dtype]}" Name="{name}" NumberOfComponents="{ncomp}" format="binary">'
            f"{enc}</DataArray>\n")


def vtu_bytes(points: np.ndarray, connectivity: np.ndarray, offsets: np.ndarray, types: np.ndarray,
              point_data: dict | None = None, cell_data: dict | None = None,
              faces: np.ndarray | None = None, faceoffsets: np.ndarray | None = None) -> bytes:
    """A VTK XML UnstructuredGrid. ``point_data``/``cell_data``: name -> (n,) or (n, k) arrays."""
    pts = np.zeros((len(points), 3), np.float32)
    if len(points):
        p = np.asarray(points, np.float32)
        pts[:, : p.shape[1]] = p
    out = ['<?xml version="1.0"?>\n<VTKFile type="UnstructuredGrid" version="1.0" byte_order="LittleEndian" header_type="UInt64">\n',
           f'<UnstructuredGrid>\n<Piece NumberOfPoints="{len(pts)}" NumberOfCells="{len(types)}">\n']
    for tag, data in (("PointData", point_data), ("CellData", cell_data)):
        out.append(f"<{tag}>\n")
        for name, a in (data or {}).items():
            a = np.asarray(a)
            a = a.astype(np.float32) if a.dtype.kind == "f" else a.astype(np.int32)
            out.append(_data_array(name, a, 1 if a.ndim == 1 else a.shape[1]))
        out.append(f"</{tag}>\n")
    out.append("<Points>\n" + _data_array("Points", pts, 3) + "</Points>\n<Cells>\n")
    out.append(_data_array("connectivity", np.asarray(connectivity, np.int64)))
    out.append(_data_array("offsets", np.asarray(offsets, np.int64)))
    out.append(_data_array("types", np.asarray(types, np.uint8)))
    if faces is not None:
        out.append(_data_array("faces", np.asarray(faces, np.int64)))
        out.append(_data_array("faceoffsets", np.asarray(faceoffsets, np.int64)))
    out.append("</Cells>\n</Piece>\n</UnstructuredGrid>\n</VTKFile>\n")
    return "".join(out).encode("ascii")


def fluid_vtu(x: np.ndarray, v: np.ndarray, rho: np.ndarray, p: np.ndarray) -> bytes:
    n = len(x)
    v3 = np.zeros((n, 3), np.float32)
    v3[:, : v.shape[1]] = v
    return vtu_bytes(x, np.arange(n), np.arange(1, n + 1), np.full(n, VTK_VERTEX),
                     point_data={"velocity": v3, "speed": np.linalg.norm(v3, axis=1), "density": rho, "pressure": p})


def blocks_vtu(blocks: list[tuple[np.ndarray, list]]) -> bytes:
    """``blocks``: (world vertices (V, 3), faces as lists of vertex indices, outward CCW) per block."""
    pts, conn, offs, faces, foffs = [], [], [], [], []
    base = 0
    for verts, fl in blocks:
        pts.append(np.asarray(verts, np.float64))
        conn.extend(range(base, base + len(verts)))
        offs.append(len(conn))
        faces.append(len(fl))
        for f in fl:
            faces.append(len(f))
            faces.extend(base + int(i) for i in f)
        foffs.append(len(faces))
        base += len(verts)
    x = np.concatenate(pts) if pts else np.zeros((0, 3))
    n = len(blocks)
    return vtu_bytes(x, np.asarray(conn), np.asarray(offs), np.full(n, VTK_POLYHEDRON), cell_data={"block": np.arange(n)},
                     faces=np.asarray(faces), faceoffsets=np.asarray(foffs))


def surface_vtu(mesh) -> bytes:
    """A :class:`rockwave.output.surface.SurfaceMesh` as triangles (3D) or lines (2D)."""
    cells = mesh.triangles if mesh.dim == 3 else mesh.segments
    k = cells.shape[1] if len(cells) else (3 if mesh.dim == 3 else 2)
    n = len(cells)
    return vtu_bytes(mesh.points, cells.reshape(-1), k * np.arange(1, n + 1), np.full(n, VTK_TRIANGLE if k == 3 else VTK_LINE))


class VtkSeries:
    """Writes the per-frame ``.vtu`` files of each part and keeps ``rockwave.pvd`` up to date."""

    def __init__(self, folder: str | os.PathLike, name: str = "rockwave"):
        self.dir = Path(folder)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.pvd = self.dir / f"{name}.pvd"
        self.entries: list[tuple[float, str, str]] = []  # (time, part, file)

    def write(self, frame: int, time_s: float, part: str, data: bytes) -> Path:
        name = f"{part}_{frame:05d}.vtu"
        _atomic_write(self.dir / name, data)
        self.entries = [e for e in self.entries if e[2] != name] + [(float(time_s), part, name)]
        return self.dir / name

    def flush(self) -> None:
        lines = ['<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n<Collection>\n']
        for t, part, name in self.entries:
            lines.append(f'<DataSet timestep="{t:.9g}" group="" part="{PARTS.index(part) if part in PARTS else 0}" name="{part}" file="{name}"/>\n')
        lines.append("</Collection>\n</VTKFile>\n")
        _atomic_write(self.pvd, "".join(lines).encode("ascii"))


def read_vtu_arrays(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Decode every DataArray of a ``.vtu`` written here (for tests and scripts): name -> flat array."""
    import xml.etree.ElementTree as ET

    types = {v: k for k, v in _VTK_TYPES.items()}
    out = {}
    for da in ET.parse(path).getroot().iter("DataArray"):
        raw = base64.b64decode(da.text or "")
        n = int(np.frombuffer(raw[:8], np.uint64)[0])
        out[da.get("Name")] = np.frombuffer(raw[8: 8 + n], types[da.get("type")])
    return out
