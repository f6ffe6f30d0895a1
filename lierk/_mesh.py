"""Closed triangle meshes of solid bodies: read from STL or OBJ files, checked
to enclose a volume, and integrated for mass properties.

A `TriangleMesh` is ``vertices`` ``(V, 3)`` (m, after ``scale``) and ``faces``
``(F, 3)`` (vertex indices).  `lierk.inertia.from_mesh` turns one into an
inertia tensor; scenes take ``[body] kind = "mesh"``.

The mass properties are exact for the polyhedron: the divergence theorem
turns each volume integral of ``1, x, y, z, x^2, ..., xy, ...`` into a sum over
the faces of polynomials in their vertices (Eberly, "Polyhedral Mass
Properties (Revisited)", 2002, after Mirtich 1996), so a box or a prism mesh
gives its closed form to rounding and a cylinder mesh that of the inscribed
prism.  This needs a closed surface with consistently oriented faces:
`check_closed` says which edges are not.

Everything here runs in NumPy on the host (it reads files); nothing is traced.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

__all__ = ["TriangleMesh", "load", "from_arrays", "from_object", "check_closed", "MassProperties", "mass_properties"]


class TriangleMesh(NamedTuple):
    """A triangle mesh.

    Attributes:
        vertices: ``(V, 3)`` float64 positions (m).
        faces: ``(F, 3)`` int64 vertex indices, counter-clockwise seen from
            outside (outward normals), as STL and OBJ files store them.
    """

    vertices: np.ndarray
    faces: np.ndarray

    @property
    def triangles(self) -> np.ndarray:
        """``(F, 3, 3)``: each face's three vertices."""
        return self.vertices[self.faces]


def from_arrays(vertices, faces, scale: float = 1.0) -> TriangleMesh:
    """A `TriangleMesh` from arrays, checked: ``vertices`` ``(V, 3)`` finite
    (in file units, times ``scale`` to get metres), ``faces`` ``(F, 3)``
    integers indexing them."""
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4:
        raise ValueError(f"mesh vertices must be an array of shape (V, 3) with V >= 4, got shape {v.shape}")
    if not np.isfinite(v).all():
        raise ValueError(
            f"mesh vertices must be finite; vertex {int(np.argwhere(~np.isfinite(v))[0, 0])} "
            f"is {v[np.argwhere(~np.isfinite(v))[0, 0]]}"
        )
    if f.ndim != 2 or f.shape[1] != 3 or len(f) < 4:
        raise ValueError(f"mesh faces must be an array of shape (F, 3) with F >= 4 triangles, got shape {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"mesh faces must be integer vertex indices, got dtype {f.dtype}")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"mesh faces index vertices 0..{len(v) - 1}, got indices {f.min()}..{f.max()}")
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive finite number, got {scale!r}")
    return TriangleMesh(v * float(scale), f.astype(np.int64))


def _merge(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shared vertices of a triangle soup ``(F, 3, 3)`` (STL repeats them per
    facet): equal coordinates become one vertex."""
    vertices, index = np.unique(triangles.reshape(-1, 3), axis=0, return_inverse=True)
    return vertices, index.reshape(-1, 3)


def _read_stl(path: Path) -> tuple[np.ndarray, np.ndarray]:
    data = path.read_bytes()
    if len(data) >= 84:
        n = int(np.frombuffer(data, "<u4", 1, 80)[0])
        if len(data) == 84 + 50 * n:
            record = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
            return _merge(np.frombuffer(data, record, n, 84)["v"].astype(float))
    text = data.decode("ascii", errors="replace")
    if not text.lstrip().startswith("solid"):
        raise ValueError(f"{path}: not an STL file (neither binary with a consistent triangle count nor ASCII 'solid')")
    coords = [line.split()[1:4] for line in text.splitlines() if line.strip().startswith("vertex")]
    if not coords or len(coords) % 3:
        raise ValueError(f"{path}: ASCII STL with {len(coords)} vertex lines, not a multiple of 3")
    return _merge(np.asarray(coords, dtype=float).reshape(-1, 3, 3))


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    vertices, faces = [], []
    for line in path.read_text().splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            vertices.append([float(x) for x in parts[1:4]])
        elif parts[0] == "f":
            # "f 1/1/1 2/2/2 3/3/3 4/4/4": 1-based (negative: from the end);
            # polygons are fanned into triangles.
            idx = [int(p.split("/")[0]) for p in parts[1:]]
            idx = [i - 1 if i > 0 else len(vertices) + i for i in idx]
            faces += [[idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1)]
    return np.asarray(vertices, dtype=float).reshape(-1, 3), np.asarray(faces, dtype=np.int64).reshape(-1, 3)


def load(path: str | os.PathLike, scale: float = 1.0) -> TriangleMesh:
    """Read a mesh file: STL (binary or ASCII) or Wavefront OBJ natively; any
    other format through ``trimesh`` if it is installed.  ``scale`` converts
    the file's units to metres (``1e-3`` for a CAD file in mm)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"mesh file not found: {path}")
    suffix = path.suffix.lower()
    if suffix == ".stl":
        vertices, faces = _read_stl(path)
    elif suffix == ".obj":
        vertices, faces = _read_obj(path)
    else:
        try:
            import trimesh
        except ImportError:
            raise ValueError(
                f"{path}: lierk reads .stl and .obj meshes; for {suffix or 'this'} files install trimesh"
            ) from None
        try:
            m = trimesh.load_mesh(path)
        except Exception as e:  # trimesh raises many types for unreadable files
            raise ValueError(f"{path}: trimesh could not read it as a mesh ({type(e).__name__}: {e})") from None
        return from_object(m, scale, what=str(path))
    return from_arrays(vertices, faces, scale)


def from_object(mesh, scale: float = 1.0, what: str = "mesh") -> TriangleMesh:
    """A `TriangleMesh` from a mesh object that has ``vertices`` ``(V, 3)``
    and ``faces`` ``(F, 3)`` (a ``trimesh.Trimesh``, or any object shaped like
    one); a ``trimesh.Scene`` of several geometries is joined into one mesh."""
    if not (hasattr(mesh, "vertices") and hasattr(mesh, "faces")) and hasattr(mesh, "to_geometry"):
        mesh = mesh.to_geometry()  # a trimesh.Scene: its geometries, placed, in one mesh
    elif not (hasattr(mesh, "vertices") and hasattr(mesh, "faces")) and hasattr(mesh, "dump"):
        mesh = mesh.dump(concatenate=True)  # trimesh < 4.5
    if not (hasattr(mesh, "vertices") and hasattr(mesh, "faces")):
        raise ValueError(f"{what}: a {type(mesh).__name__} has no vertices and faces of triangles")
    return from_arrays(np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces), scale)


def check_closed(mesh: TriangleMesh) -> None:
    """Raise a ValueError unless every edge joins exactly two faces that run
    along it in opposite directions: then the surface is closed (watertight)
    and consistently oriented, which the volume integrals need."""
    f = mesh.faces
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    if np.any(directed[:, 0] == directed[:, 1]):
        raise ValueError("mesh has degenerate faces (a vertex repeated in one triangle)")
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected, axis=0, return_counts=True)
    open_edges = int(np.sum(counts == 1))
    if open_edges or np.any(counts > 2):
        raise ValueError(
            f"mesh is not watertight: {open_edges} edges belong to one face only and {int(np.sum(counts > 2))} to more "
            "than two; a solid's mass properties need a closed surface (repair it, e.g. with trimesh or MeshLab)"
        )
    _, counts = np.unique(directed, axis=0, return_counts=True)
    if np.any(counts > 1):
        raise ValueError(
            f"mesh faces are not consistently oriented: {int(np.sum(counts > 1))} edges run the same way in both of "
            "their faces; orient every face counter-clockwise seen from outside"
        )


class MassProperties(NamedTuple):
    """Mass properties of a uniform solid.

    Attributes:
        volume: m^3.
        mass: kg.
        center_of_mass: ``(3,)`` m, in the mesh frame.
        inertia: ``(3, 3)`` kg m^2 about the centre of mass, mesh axes.
    """

    volume: float
    mass: float
    center_of_mass: np.ndarray
    inertia: np.ndarray


def _subexpressions(w0, w1, w2):
    t0 = w0 + w1
    f1 = t0 + w2
    t1 = w0 * w0
    t2 = t1 + w1 * t0
    f2 = t2 + w2 * f1
    f3 = w0 * t1 + w1 * t2 + w2 * f2
    return f1, f2, f3, f2 + w0 * (f1 + w0), f2 + w1 * (f1 + w1), f2 + w2 * (f1 + w2)


def mass_properties(mesh: TriangleMesh, density: float) -> MassProperties:
    """Exact mass properties of the solid the closed ``mesh`` bounds, at
    uniform ``density`` (kg/m^3).  Faces wound inward throughout (negative
    volume) are accepted as the same solid."""
    if not (np.isfinite(density) and density > 0):
        raise ValueError(f"density must be a positive finite number (kg/m^3), got {density!r}")
    check_closed(mesh)
    # About the vertices' mean: the integrals stay well conditioned for a
    # mesh far from its file's origin.
    shift = mesh.vertices.mean(axis=0)
    T = mesh.triangles - shift
    x, y, z = T[..., 0], T[..., 1], T[..., 2]
    d = np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
    fx, fy, fz = (_subexpressions(w[:, 0], w[:, 1], w[:, 2]) for w in (x, y, z))
    ints = np.array(
        [
            np.sum(d[:, 0] * fx[0]) / 6,
            np.sum(d[:, 0] * fx[1]) / 24,
            np.sum(d[:, 1] * fy[1]) / 24,
            np.sum(d[:, 2] * fz[1]) / 24,
            np.sum(d[:, 0] * fx[2]) / 60,
            np.sum(d[:, 1] * fy[2]) / 60,
            np.sum(d[:, 2] * fz[2]) / 60,
            np.sum(d[:, 0] * (y[:, 0] * fx[3] + y[:, 1] * fx[4] + y[:, 2] * fx[5])) / 120,
            np.sum(d[:, 1] * (z[:, 0] * fy[3] + z[:, 1] * fy[4] + z[:, 2] * fy[5])) / 120,
            np.sum(d[:, 2] * (x[:, 0] * fz[3] + x[:, 1] * fz[4] + x[:, 2] * fz[5])) / 120,
        ]
    )
    volume = ints[0]
    scale = np.ptp(mesh.vertices, axis=0).max() ** 3
    if not abs(volume) > 1e-12 * scale:
        raise ValueError(f"mesh encloses no volume ({volume:.3g} m^3 for a bounding size of {scale ** (1 / 3):.3g} m)")
    ints = ints * np.sign(volume)  # inward-wound faces
    volume = abs(volume)
    com = ints[1:4] / volume
    xx, yy, zz = ints[4:7] - volume * com**2
    xy, yz, zx = ints[7:10] - volume * np.array([com[0] * com[1], com[1] * com[2], com[2] * com[0]])
    inertia = density * np.array([[yy + zz, -xy, -zx], [-xy, xx + zz, -yz], [-zx, -yz, xx + yy]])
    return MassProperties(float(volume), float(density * volume), com + shift, inertia)
