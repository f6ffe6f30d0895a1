"""Inertia tensors of rigid bodies, in kg m^2, about the centre of mass.

All tensors are ``(3, 3)`` arrays in the body frame.  Shapes are given by mass
(kg) and dimensions (m).  `composite` combines parts with the parallel-axis
theorem, which is how the report builds its T-handle.

The arithmetic runs in NumPy on concrete values (a scene is built without
compiling anything) and in ``jax.numpy`` when an offset or inertia is traced;
the results are JAX arrays either way.
"""

from __future__ import annotations

import math
import os
from typing import NamedTuple, Sequence

import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

from ._validation import as_jax, check_scalar, is_traced
from ._validation import check_inertia as tensor

__all__ = [
    "tensor",
    "sphere",
    "solid_cylinder",
    "box",
    "Part",
    "composite",
    "tee_handle",
    "tee_handle_parts",
    "parallel_axis",
    "MeshInertia",
    "from_mesh",
]

_AXES = {"x": 0, "y": 1, "z": 2}


def _positive(name: str, value) -> float:
    # The library's one check of a positive number (`check_scalar`), read
    # on the host: a shape's size and mass are concrete numbers.
    return float(check_scalar(value, name, bound="positive"))


def sphere(mass: float, radius: float) -> Array:
    """Solid sphere of ``mass`` (kg) and ``radius`` (m): ``2/5 m r^2`` about
    every axis.  Returns the ``(3, 3)`` tensor (kg m^2) about its centre."""
    m, r = _positive("mass", mass), _positive("radius", radius)
    return as_jax(np.eye(3) * (0.4 * m * r * r))


def solid_cylinder(mass: float, radius: float, length: float, axis: str = "z") -> Array:
    """Solid cylinder of ``mass`` (kg), ``radius`` and ``length`` (m) with its
    symmetry axis along ``axis`` ("x", "y" or "z"): ``m r^2/2`` about that
    axis, ``m (3 r^2 + l^2)/12`` about the other two.  Returns the ``(3, 3)``
    tensor (kg m^2) about its centre of mass."""
    m, r, length = _positive("mass", mass), _positive("radius", radius), _positive("length", length)
    if axis not in _AXES:
        raise ValueError(f"axis must be one of {sorted(_AXES)}, got {axis!r}")
    d = np.full(3, m * (3 * r * r + length * length) / 12.0)
    d[_AXES[axis]] = 0.5 * m * r * r
    return as_jax(np.diag(d))


def box(mass: float, lx: float, ly: float, lz: float) -> Array:
    """Solid box of ``mass`` (kg) with edge lengths ``(lx, ly, lz)`` (m)
    along the body axes: ``m (ly^2 + lz^2)/12`` about x, and so on.  Returns
    the ``(3, 3)`` tensor (kg m^2) about its centre."""
    m = _positive("mass", mass)
    lx, ly, lz = _positive("lx", lx), _positive("ly", ly), _positive("lz", lz)
    return as_jax(np.diag(np.array([ly * ly + lz * lz, lx * lx + lz * lz, lx * lx + ly * ly]) * (m / 12.0)))


def parallel_axis(inertia_cm: ArrayLike, mass: float, offset: ArrayLike) -> Array:
    """Inertia (kg m^2) about a point displaced by ``-offset`` from the centre
    of mass: ``I + m (|d|^2 E - d d^T)`` with ``d = offset`` (m) and ``m =
    mass`` (kg), ``inertia_cm`` the ``(3, 3)`` tensor about the centre of
    mass.  For a pivot at ``p``, ``offset = com - p`` (`lierk.heavy_top`
    does this for a top)."""
    return as_jax(_shifted(jnp if is_traced(inertia_cm, mass, offset) else np, inertia_cm, mass, offset))


def _shifted(xp, inertia_cm, mass, offset):
    """`parallel_axis` in ``xp`` (NumPy or ``jax.numpy``)."""
    dtype = jnp.result_type(float)  # as jax.numpy would compute it
    d = xp.asarray(offset, dtype=dtype)
    return xp.asarray(inertia_cm, dtype=dtype) + mass * (xp.dot(d, d) * xp.eye(3, dtype=dtype) - xp.outer(d, d))


class Part(NamedTuple):
    """One solid of a composite body.

    Attributes:
        mass: kg.
        inertia: ``(3, 3)`` about the part's own centre of mass, in the part's frame.
        offset: ``(3,)`` position of the part's centre of mass in the assembly frame (m).
        rotation: ``(3, 3)`` part frame -> assembly frame (identity if None).
        shape: optional description for drawing, e.g. ``("cylinder", radius, length, axis)``
            or ``("mesh", triangles)`` (``(F, 3, 3)``, m, about the part's centre of mass).
    """

    mass: float
    inertia: ArrayLike
    offset: ArrayLike
    rotation: ArrayLike | None = None
    shape: tuple | None = None


class Composite(NamedTuple):
    """Result of `composite`: total mass (kg), centre of mass ``(3,)`` in the
    assembly frame (m), and inertia ``(3, 3)`` about that centre (kg m^2)."""

    mass: float
    center_of_mass: Array
    inertia: Array


def composite(parts: Sequence[Part]) -> Composite:
    """Combine parts: centre of mass, then each part's inertia rotated into the
    assembly frame and shifted to the common centre (parallel-axis theorem)."""
    if not parts:
        raise ValueError("composite needs at least one part")
    masses = [_positive(f"parts[{i}].mass", p.mass) for i, p in enumerate(parts)]
    total = sum(masses)
    xp = jnp if is_traced([(p.offset, p.inertia, p.rotation) for p in parts]) else np
    dtype = jnp.result_type(float)  # as jax.numpy would compute it
    offsets = [xp.asarray(p.offset, dtype=dtype) for p in parts]
    com = sum(m * o for m, o in zip(masses, offsets)) / total
    inertia = xp.zeros((3, 3), dtype)
    for p, m, o in zip(parts, masses, offsets):
        Q = xp.eye(3, dtype=dtype) if p.rotation is None else xp.asarray(p.rotation, dtype=dtype)
        inertia = inertia + _shifted(xp, Q @ xp.asarray(p.inertia, dtype=dtype) @ Q.T, m, o - com)
    return Composite(total, as_jax(com), as_jax(inertia))


def tee_handle_parts(
    handle_length: float = 0.08,
    handle_radius: float = 0.01,
    shaft_length: float = 0.04,
    shaft_radius: float = 0.01,
    density: float = 6700.0,
) -> list[Part]:
    """The report's T-handle as two solid cylinders (lengths in m, density in kg/m^3).

    The handle lies along y through the origin; the shaft lies along x and
    starts at the handle's surface, so its centre is at
    ``x = handle_radius + shaft_length/2``.
    """
    hl, hr = _positive("handle_length", handle_length), _positive("handle_radius", handle_radius)
    sl, sr = _positive("shaft_length", shaft_length), _positive("shaft_radius", shaft_radius)
    rho = _positive("density", density)
    m_handle = rho * math.pi * hr * hr * hl
    m_shaft = rho * math.pi * sr * sr * sl
    return [
        Part(m_handle, solid_cylinder(m_handle, hr, hl, "y"), [0.0, 0.0, 0.0], None, ("cylinder", hr, hl, "y")),
        Part(m_shaft, solid_cylinder(m_shaft, sr, sl, "x"), [hr + 0.5 * sl, 0.0, 0.0], None, ("cylinder", sr, sl, "x")),
    ]


def tee_handle(**dimensions) -> Array:
    """Inertia of the report's T-handle about its centre of mass (kg m^2).

    With the report's dimensions (handle 8 cm x 1 cm radius, shaft 4 cm x 1 cm
    radius, density 6.7 g/cm^3) this is
    ``diag(9.82271303e-05, 7.22671030e-05, 1.57865031e-04)``: x (along the
    shaft) is the intermediate axis.  Keyword arguments override the dimensions
    of `tee_handle_parts`.
    """
    return composite(tee_handle_parts(**dimensions)).inertia


class MeshInertia(NamedTuple):
    """Result of `from_mesh`.

    Attributes:
        mass: kg.
        center_of_mass: ``(3,)`` m, in the mesh frame.
        inertia: ``(3, 3)`` kg m^2 about the centre of mass, along the mesh
            axes (off-diagonal unless they are principal).
        principal_moments: ``(3,)`` kg m^2, ascending.
        principal_axes: ``(3, 3)`` rotation whose columns are the principal
            axes in the mesh frame: ``inertia = Q diag(moments) Q^T``.
        mesh: the `lierk._mesh.TriangleMesh` (m), for drawing.
    """

    mass: float
    center_of_mass: np.ndarray
    inertia: np.ndarray
    principal_moments: np.ndarray
    principal_axes: np.ndarray
    mesh: object


def from_mesh(mesh, density: float, scale: float = 1.0) -> MeshInertia:
    """Inertia of a uniform solid bounded by a closed triangle mesh.

    Args:
        mesh: a file path (STL or OBJ; any format trimesh reads if it is
            installed: ``pip install lierk[mesh]``), a ``trimesh.Trimesh``
            or ``trimesh.Scene`` (or any object with ``vertices`` ``(V, 3)``
            and ``faces`` ``(F, 3)``), a ``(vertices, faces)`` pair, or the
            `TriangleMesh` of an earlier result.
        density: kg/m^3.
        scale: file units to metres (``1e-3`` for a CAD file in mm); not
            applied to a `TriangleMesh`.

    Exact for the polyhedron (`lierk._mesh.mass_properties`).  A mesh that is
    not watertight, is inconsistently oriented or encloses no volume raises a
    ValueError saying which.

    Example:
        >>> props = lierk.inertia.from_mesh("bracket.stl", density=2700.0, scale=1e-3)
        >>> body = lierk.FreeRigidBody(props.inertia, [0.0, 1.0, 0.1])
    """
    from . import _mesh

    if isinstance(mesh, _mesh.TriangleMesh):
        m = mesh
    elif isinstance(mesh, (str, os.PathLike)):
        m = _mesh.load(mesh, scale)
    elif hasattr(mesh, "faces") or hasattr(mesh, "to_geometry") or hasattr(mesh, "dump"):
        m = _mesh.from_object(mesh, scale)
    else:
        try:
            vertices, faces = mesh
        except (TypeError, ValueError):
            raise ValueError(
                "mesh must be a file path, a trimesh.Trimesh, a (vertices, faces) pair or a TriangleMesh, "
                f"got {type(mesh).__name__}"
            ) from None
        m = _mesh.from_arrays(vertices, faces, scale)
    props = _mesh.mass_properties(m, density)
    moments, axes = np.linalg.eigh(props.inertia)
    if np.linalg.det(axes) < 0:
        axes[:, 2] = -axes[:, 2]
    return MeshInertia(props.mass, props.center_of_mass, props.inertia, moments, axes, m)
