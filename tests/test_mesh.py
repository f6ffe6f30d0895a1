"""Inertia from closed triangle meshes: exact for polyhedra (a box and an
offset, rotated box against the closed form; a cylinder mesh against the
inscribed prism and, refined, the cylinder), files read back, and every
defective mesh refused with a message that says what is wrong."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import lierk
import lierk._mesh


def box_mesh(lx, ly, lz):
    v = np.array([[x, y, z] for x in (-lx / 2, lx / 2) for y in (-ly / 2, ly / 2) for z in (-lz / 2, lz / 2)])
    # Outward, counter-clockwise: two triangles per face of the cube's index layout.
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = np.array([[a, b, c] for a, b, c, d in quads] + [[a, c, d] for a, b, c, d in quads])
    return v, f


def cylinder_mesh(radius, length, n):
    """A closed prism with n sides inscribed in the cylinder (axis z)."""
    phi = 2 * np.pi * np.arange(n) / n
    ring = np.stack([radius * np.cos(phi), radius * np.sin(phi)], 1)
    v = np.concatenate(
        [
            np.c_[ring, np.full(n, -length / 2)],
            np.c_[ring, np.full(n, length / 2)],
            [[0, 0, -length / 2], [0, 0, length / 2]],
        ]
    )
    f = []
    for i in range(n):
        j = (i + 1) % n
        f += [[i, j, n + j], [i, n + j, n + i], [2 * n, j, i], [2 * n + 1, n + i, n + j]]
    return v, np.array(f)


def test_box_is_exact_and_moves_and_turns_with_the_mesh():
    rho, dims = 2700.0, (0.3, 0.2, 0.1)
    mass = rho * np.prod(dims)
    v, f = box_mesh(*dims)
    p = lierk.inertia.from_mesh((v, f), density=rho)
    np.testing.assert_allclose(p.mass, mass, rtol=1e-14)
    np.testing.assert_allclose(p.inertia, np.asarray(lierk.inertia.box(mass, *dims)), rtol=1e-13, atol=1e-18)
    np.testing.assert_allclose(
        p.principal_moments, np.sort(np.diag(np.asarray(lierk.inertia.box(mass, *dims)))), rtol=1e-13
    )
    # Turned by Q and moved by c: centre c, inertia Q I Q^T about it.
    Q, c = Rotation.from_rotvec([0.3, -0.7, 1.1]).as_matrix(), np.array([5.0, -3.0, 20.0])
    p2 = lierk.inertia.from_mesh((v @ Q.T + c, f), density=rho)
    np.testing.assert_allclose(p2.center_of_mass, c, atol=1e-12)
    np.testing.assert_allclose(p2.inertia, Q @ p.inertia @ Q.T, rtol=1e-9, atol=1e-12 * np.max(p.inertia))
    np.testing.assert_allclose(
        p2.principal_axes @ np.diag(p2.principal_moments) @ p2.principal_axes.T,
        p2.inertia,
        atol=1e-12 * np.max(p.inertia),
    )
    assert np.linalg.det(p2.principal_axes) > 0


def test_cylinder_mesh_is_the_inscribed_prism_and_converges_to_the_cylinder():
    r, length, rho = 0.05, 0.3, 1000.0
    for n in (6, 256):
        p = lierk.inertia.from_mesh(cylinder_mesh(r, length, n), density=rho)
        # Regular n-gon prism: area n r^2 sin(2 pi/n)/2, and a polar moment
        # per unit mass of r^2 (1 + 2 cos^2(pi/n))/6 (the cylinder's r^2/2 as n grows).
        area = 0.5 * n * r * r * np.sin(2 * np.pi / n)
        mass = rho * area * length
        axial = mass * r * r * (1 + 2 * np.cos(np.pi / n) ** 2) / 6
        np.testing.assert_allclose(p.mass, mass, rtol=1e-13)
        np.testing.assert_allclose(p.inertia[2, 2], axial, rtol=1e-13)
        transverse = axial / 2 + mass * length**2 / 12
        np.testing.assert_allclose(np.diag(p.inertia)[:2], [transverse, transverse], rtol=1e-12)
    cyl = np.diag(np.asarray(lierk.inertia.solid_cylinder(rho * np.pi * r * r * length, r, length)))
    np.testing.assert_allclose(np.diag(p.inertia), cyl, rtol=3e-4)


def write_stl(path, triangles, binary):
    if binary:
        rec = np.zeros(len(triangles), np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")]))
        rec["v"] = triangles
        path.write_bytes(b"\0" * 80 + np.uint32(len(triangles)).tobytes() + rec.tobytes())
    else:
        lines = ["solid test"]
        for t in triangles:
            lines += [
                "facet normal 0 0 0",
                "outer loop",
                *[f"vertex {x:.9e} {y:.9e} {z:.9e}" for x, y, z in t],
                "endloop",
                "endfacet",
            ]
        path.write_text("\n".join(lines + ["endsolid test"]) + "\n")


@pytest.mark.parametrize("kind", ["binary-stl", "ascii-stl", "obj"])
def test_files_read_back_to_the_same_inertia(tmp_path, kind):
    v, f = box_mesh(300.0, 200.0, 100.0)  # millimetres
    if kind == "obj":
        path = tmp_path / "box.obj"
        path.write_text(
            "".join(f"v {x} {y} {z}\n" for x, y, z in v) + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f)
        )
    else:
        path = tmp_path / "box.stl"
        write_stl(path, v[f], binary=kind == "binary-stl")
    p = lierk.inertia.from_mesh(path, density=2700.0, scale=1e-3)
    ref = lierk.inertia.from_mesh(box_mesh(0.3, 0.2, 0.1), density=2700.0)
    np.testing.assert_allclose(p.inertia, ref.inertia, rtol=1e-6)
    np.testing.assert_allclose(p.mass, ref.mass, rtol=1e-6)


def test_trimesh_objects_scenes_and_formats_are_accepted(tmp_path):
    """A user's mesh is usually a trimesh object: a Trimesh, a Scene of
    several placed geometries, or a file only trimesh reads (PLY here)."""
    trimesh = pytest.importorskip("trimesh")
    rho, (lx, ly, lz) = 2700.0, (0.3, 0.2, 0.1)
    exact = rho * lx * ly * lz / 12 * np.array([ly**2 + lz**2, lx**2 + lz**2, lx**2 + ly**2])
    box = trimesh.creation.box(extents=(lx, ly, lz))
    np.testing.assert_allclose(np.diag(lierk.inertia.from_mesh(box, rho).inertia), exact, rtol=1e-12)
    # Two boxes placed side by side along x: the parallel-axis composite.
    scene = trimesh.Scene()
    for dx in (-lx / 2, lx / 2):
        scene.add_geometry(box, transform=trimesh.transformations.translation_matrix([dx, 0.0, 0.0]))
    two = lierk.inertia.from_mesh(scene, rho)
    ref = lierk.inertia.from_mesh(box_mesh(2 * lx, ly, lz), rho)
    np.testing.assert_allclose(two.inertia, ref.inertia, rtol=1e-12, atol=1e-15)
    box.export(tmp_path / "box.ply")
    from_file = lierk.inertia.from_mesh(tmp_path / "box.ply", rho, scale=1.0)
    np.testing.assert_allclose(np.diag(from_file.inertia), exact, rtol=1e-6)
    with pytest.raises(ValueError, match="a trimesh.Trimesh, .* got PointCloud"):
        lierk.inertia.from_mesh(trimesh.PointCloud(np.eye(3)), rho)


def test_inward_faces_are_the_same_solid():
    v, f = box_mesh(0.3, 0.2, 0.1)
    a = lierk.inertia.from_mesh((v, f), 1000.0)
    b = lierk.inertia.from_mesh((v, f[:, ::-1]), 1000.0)
    np.testing.assert_allclose(b.inertia, a.inertia, rtol=1e-14)


def test_defective_meshes_are_refused_saying_why(tmp_path):
    v, f = box_mesh(0.3, 0.2, 0.1)
    with pytest.raises(ValueError, match="not watertight: 3 edges"):
        lierk.inertia.from_mesh((v, f[:-1]), 1000.0)
    flipped = f.copy()
    flipped[0] = flipped[0, ::-1]
    with pytest.raises(ValueError, match="not consistently oriented"):
        lierk.inertia.from_mesh((v, flipped), 1000.0)
    flat = v.copy()
    flat[:, 2] = 0.0
    with pytest.raises(ValueError, match="no volume|degenerate"):
        lierk.inertia.from_mesh((flat, f), 1000.0)
    with pytest.raises(ValueError, match="density must be a positive"):
        lierk.inertia.from_mesh((v, f), -1.0)
    bad = v.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="vertex 3"):
        lierk.inertia.from_mesh((bad, f), 1000.0)
    with pytest.raises(ValueError, match="index vertices 0..7"):
        lierk.inertia.from_mesh((v, f + 1), 1000.0)
    with pytest.raises(ValueError, match="not found"):
        lierk.inertia.from_mesh(tmp_path / "missing.stl", 1000.0)
    (tmp_path / "junk.stl").write_bytes(b"\x01\x02 not a mesh")
    with pytest.raises(ValueError, match="not an STL file"):
        lierk.inertia.from_mesh(tmp_path / "junk.stl", 1000.0)


def test_a_mesh_scene_is_the_mesh_body_and_its_animation_draws_it(tmp_path):
    import tomllib
    import warnings

    from PIL import Image

    import lierk.app.plot
    import lierk.app.scene

    v, f = box_mesh(300.0, 200.0, 100.0)
    (tmp_path / "parts").mkdir()
    write_stl(tmp_path / "parts" / "box.stl", v[f] + np.array([50.0, 0.0, 0.0]), binary=True)
    text = """
[body]
kind = "mesh"
file = "parts/box.stl"
density = 2700.0
scale = 1e-3
[initial]
omega = [0.3, 2.0, 0.1]
[run]
solver = "RKMK4"
dt = 0.01
t1 = 1.0
"""
    (tmp_path / "box.toml").write_text(text)
    scene = lierk.app.scene.load(tmp_path / "box.toml")
    box = np.asarray(lierk.inertia.box(2700.0 * 0.3 * 0.2 * 0.1, 0.3, 0.2, 0.1))
    np.testing.assert_allclose(scene.problem.inertia, box, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(scene.center_of_mass, [0.05, 0.0, 0.0], atol=1e-9)
    with pytest.raises(ValueError, match="body.file 'missing.stl'"):
        lierk.app.scene.from_dict(tomllib.loads(text.replace("parts/box.stl", "missing.stl")), directory=tmp_path)
    sol = lierk.solve(scene.problem, lierk.RKMK4(), 1.0, dt=0.01, saveat=lierk.SaveAt(t0=True, steps=10))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # "cannot draw a part" would be a warning
        gif = lierk.app.plot.animate(sol, scene.body_parts, tmp_path / "box.gif", frames=3, origin=scene.fixed_point)
    im = Image.open(gif)
    frames = []
    for k in range(im.n_frames):
        im.seek(k)
        frames.append(np.asarray(im.convert("RGB"), dtype=int))
    assert len(frames) == 3
    assert np.mean(np.any(frames[0] != frames[2], axis=-1)) > 0.01  # the box turned
