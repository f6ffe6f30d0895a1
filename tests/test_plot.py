"""Figures show the solution's data in the documented conventions, and the
files they write decode with the documented sizes."""

import matplotlib.image
import numpy as np
import pytest
from helpers import OMEGA_GENERIC, TEE
from PIL import Image

import lierk
from lierk import Damping, RigidBodyWithEffects, so3
from lierk.app import plot
from lierk.app.diagnostics import diagnostics
from lierk.app.omega_sweep import OmegaSweep


@pytest.fixture(scope="module")
def flip():
    """The T-handle off its axes, 3 s at dt = 0.01 s, every step saved."""
    problem = lierk.FreeRigidBody(TEE, OMEGA_GENERIC)
    sol = lierk.solve(problem, lierk.RKMK4(), 3.0, dt=0.01, saveat=lierk.SaveAt(t0=True, steps=True))
    return problem, sol


def test_components_plot_every_entry_against_time(flip, tmp_path):
    _, sol = flip
    fig = plot.components(sol, "T-handle - RKMK4")
    axs = np.array(fig.axes).reshape(3, 3)
    for i in range(3):
        for j in range(3):
            ax = axs[i, j]
            assert ax.get_title() == f"$R_{{{i + 1}{j + 1}}}$"
            (line,) = ax.get_lines()[:1]
            np.testing.assert_array_equal(line.get_xdata(), np.asarray(sol.ts))
            np.testing.assert_array_equal(line.get_ydata(), np.asarray(sol.R)[:, i, j])
            lo, hi = ax.get_ylim()
            assert lo <= -1.0 and hi >= 1.0
    assert all(ax.get_xlabel() == "t [s]" for ax in axs[-1])
    assert fig.get_suptitle() == "T-handle - RKMK4"
    path = tmp_path / "c.png"
    fig.savefig(path, dpi=100)
    img = matplotlib.image.imread(path)
    assert img.shape[:2] == (700, 900)  # figsize (9, 7) at 100 dpi


@pytest.mark.parametrize("name", ["components", "euler_angles", "invariants", "invariants_two_panels"])
def test_no_label_of_a_solves_figure_is_clipped(flip, name):
    # The figures of a solve have fixed layouts (constrained layout drew each
    # twice and was most of `lierk simulate`'s figure time): every text, a
    # long title, the panels' labels, tick labels and the legends outside
    # the axes, must lie inside the figure.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.text import Text

    problem, sol = flip
    title = "a title as long as a scene's own: T-handle, spin about x"
    if name == "components":
        fig = plot.components(sol, title, events={"flip": [0.5, 2.0], "tilt": [1.0]})
    elif name == "euler_angles":
        fig = plot.euler_angles(sol, title, degrees=True, convention="zxz")
    elif name == "invariants":
        fig = plot.invariants(sol, problem, title)
    else:
        # A heavy top: energy conserved, |L| not, so two panels.
        top = RigidBodyWithEffects([5.0, 5.0, 1.0], [0.3, 0.0, 5.0], effects=(lierk.Gravity([0.0, 0.0, 0.5], 1.0),))
        fig = plot.invariants(
            lierk.solve(top, lierk.RKMK4(), 1.0, dt=0.01, saveat=lierk.SaveAt(t0=True, steps=True)), top, title
        )
        assert len(fig.axes) == 2
    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw(renderer)
    assert sum(1 for t in fig.findobj(Text) if t.get_visible() and t.get_text().strip()) > 10
    # Everything drawn (titles, labels, tick labels, legends outside the
    # axes), in inches, inside the figure.
    drawn = fig.get_tightbbox(renderer)
    width, height = fig.get_size_inches()
    tol = 0.01
    assert drawn.x0 >= -tol and drawn.y0 >= -tol and drawn.x1 <= width + tol and drawn.y1 <= height + tol, (
        drawn,
        width,
        height,
    )


@pytest.mark.parametrize("degrees", [False, True])
def test_euler_angles_rebuild_R_and_are_unwrapped(flip, degrees):
    _, sol = flip
    fig = plot.euler_angles(sol, "t", degrees=degrees)
    angles = np.stack([ax.get_lines()[0].get_ydata() for ax in fig.axes], axis=-1)
    unit = "deg" if degrees else "rad"
    assert all(f"[{unit}]" in ax.get_ylabel() for ax in fig.axes)
    rad = np.radians(angles) if degrees else angles
    # R = Rz(phi) Ry(theta) Rx(psi), the report's convention, at every saved time.
    np.testing.assert_allclose(so3.from_euler(rad[:, 0], rad[:, 1], rad[:, 2]), sol.R, atol=1e-12)
    # Unwrapped: a 0.01 s step turns by ~0.01 rad, so no jump comes near pi.
    assert np.abs(np.diff(rad, axis=0)).max() < 0.5


def test_invariants_show_relative_drift_of_the_free_body(flip):
    problem, sol = flip
    fig = plot.invariants(sol, problem, "t")
    (ax,) = fig.axes
    # Linear, so that a small drift changing sign is not drawn as swings of decades.
    assert ax.get_yscale() == "linear"
    # The invariants of the diagnostics program (the numbers `lierk simulate`
    # prints; problem.invariants called op by op differs in the last bits).
    q = diagnostics(problem, sol).invariants
    lines = {ln.get_label().split(":")[0]: ln for ln in ax.get_lines()}
    assert set(lines) == set(q)
    for name, values in q.items():
        values = np.asarray(values)
        np.testing.assert_allclose(lines[name].get_ydata(), (values - values[0]) / abs(values[0]), rtol=0, atol=1e-18)
    # RKMK4 at dt = 0.01 s: energy drift well below 1e-8 but not zero.
    drift = np.abs(lines["energy"].get_ydata()).max()
    assert 0 < drift < 1e-8
    lo, hi = ax.get_ylim()
    top = max(np.abs(ln.get_ydata()).max() for ln in lines.values())
    assert lo == -hi and top <= hi <= 1.2 * max(top, 10 * np.finfo(float).eps)


def test_invariants_put_dissipated_quantities_on_their_own_axis():
    problem = RigidBodyWithEffects(TEE, OMEGA_GENERIC, effects=(Damping(2e-5),))
    sol = lierk.solve(problem, lierk.RKMK4(), 5.0, dt=0.01, saveat=lierk.SaveAt(t0=True, steps=10))
    fig = plot.invariants(sol, problem, "damped")
    assert problem.conserved() == ()
    (ax,) = fig.axes  # nothing is conserved, so only the ratio panel
    energy = next(ln for ln in ax.get_lines() if ln.get_label().startswith("energy"))
    e = np.asarray(problem.invariants(sol.R, sol.y)["energy"])
    np.testing.assert_allclose(energy.get_ydata(), e / e[0])
    assert energy.get_ydata()[-1] < 0.99  # damping removes energy


def test_trajectory_drops_adaptive_padding():
    problem = lierk.FreeRigidBody(TEE, OMEGA_GENERIC)
    sol = lierk.solve(problem, lierk.DP54(), 2.0, rtol=1e-6, saveat=lierk.SaveAt(steps=True), max_steps=200)
    n = int(sol.n_saved)
    assert n < sol.ts.shape[0]
    ts, R, _ = sol.trajectory()
    assert ts.shape == (n,) and R.shape == (n, 3, 3)
    assert np.isfinite(ts).all() and np.isfinite(R).all()
    fig = plot.components(sol)
    assert len(fig.axes[0].get_lines()[0].get_xdata()) == n


def test_equivalent_box_has_the_principal_moments_up_to_scale():
    inertia = np.array([[3.0, 0.4, 0.0], [0.4, 2.0, 0.1], [0.0, 0.1, 4.0]])
    (part,) = plot.equivalent_box(inertia)
    _, lx, ly, lz = part.shape
    box = np.asarray(lierk.inertia.box(1.0, lx, ly, lz))
    Q = np.asarray(part.rotation)
    drawn = Q @ box @ Q.T
    np.testing.assert_allclose(drawn / np.trace(drawn), inertia / np.trace(inertia), atol=1e-12)
    assert np.linalg.det(Q) == pytest.approx(1.0)


def test_animation_has_the_requested_frames_and_size(flip, tmp_path):
    problem, sol = flip
    path = plot.animate(sol, lierk.inertia.tee_handle_parts(), tmp_path / "a.gif", L=problem.L, frames=5, fps=10)
    with Image.open(path) as im:
        assert im.format == "GIF"
        assert im.n_frames == 5
        assert im.size == tuple(int(s * plot.GIF_DPI) for s in plot.GIF_SIZE)
        im.seek(0)
        first = np.asarray(im.convert("RGB"))
        im.seek(4)
        last = np.asarray(im.convert("RGB"))
    # The body turns by ~3 rad in 3 s: the picture changes (measured: 4.8% of
    # the pixels), and not only the time label: at rest, 0.013% change.
    assert _changed(first, last) > 0.03
    rest = lierk.solve(
        lierk.FreeRigidBody(TEE, np.zeros(3)), lierk.RKMK4(), 3.0, dt=0.5, saveat=lierk.SaveAt(t0=True, steps=True)
    )
    path = plot.animate(rest, lierk.inertia.tee_handle_parts(), tmp_path / "rest.gif", L=problem.L, frames=5, fps=10)
    with Image.open(path) as im:
        im.seek(0)
        first = np.asarray(im.convert("RGB"))
        im.seek(4)
        last = np.asarray(im.convert("RGB"))
    assert _changed(first, last) < 0.002


@pytest.mark.parametrize("parts", ["tee", "none"])
def test_blitted_frames_are_the_pixels_of_full_draws(flip, parts):
    # Each frame draws only what moves over a saved background; a full draw
    # of the same figure per frame must give the very same pixels (the body
    # hides the lines behind it, the legend covers what passes under it).
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    problem, sol = flip
    parts = lierk.inertia.tee_handle_parts() if parts == "tee" else None
    ts, R, _ = sol.trajectory()

    def make():
        return plot._animation(ts, R, parts, problem.L, frames=4, title="t", inertia=None, origin=None, trail=True)

    blitted = plot._frames(make())
    full = make()
    canvas = FigureCanvasAgg(full.fig)
    for k, frame in enumerate(blitted):
        full.update(k)
        canvas.draw()
        np.testing.assert_array_equal(frame, np.asarray(canvas.buffer_rgba())[..., :3])
    assert _changed(blitted[0], blitted[-1]) > 0.01


def _changed(a, b) -> float:
    """The fraction of pixels whose colour differs visibly (RGB sum > 60)."""
    return float((np.abs(a.astype(int) - b.astype(int)).sum(axis=-1) > 60).mean())


def test_animation_draws_a_body_known_only_by_its_inertia(flip, tmp_path):
    problem, sol = flip
    with_box = plot.animate(sol, None, tmp_path / "box.gif", frames=2, inertia=TEE)
    axes_only = plot.animate(sol, None, tmp_path / "axes.gif", frames=2)
    other_box = plot.animate(sol, None, tmp_path / "other.gif", frames=2, inertia=np.diag([1.0, 2.0, 3.0]) * 1e-4)
    with Image.open(with_box) as a, Image.open(axes_only) as b, Image.open(other_box) as c:
        a, b, c = (np.asarray(x.convert("RGB")) for x in (a, b, c))
    # Measured: the box covers 10% of the picture, and another inertia's box
    # differs from it in 4%.
    assert _changed(a, b) > 0.05
    assert _changed(a, c) > 0.02


def test_demo_writes_one_grid_per_case_and_the_flip_interval(tmp_path, capsys):
    from lierk.app import demo

    paths = demo.run(tmp_path, t1=1.0)
    assert sorted(paths) == ["a", "b", "c"]
    for path in paths.values():
        with Image.open(path) as im:
            assert im.format == "PNG" and im.size == (900, 700)
    out = capsys.readouterr().out
    # The exact flip interval of case a (Landau-Lifshitz 2K/lambda) for the report's T-handle.
    assert "flip every 23.63 s" in out
    assert all(str(p) in out for p in paths.values())


def test_top_angles_are_precession_nutation_spin(flip):
    _, sol = flip
    fig = plot.euler_angles(sol, "t", convention="zxz")
    assert [ax.get_ylabel().split(" [")[0] for ax in fig.axes] == [
        r"precession $\phi$",
        r"nutation $\theta$",
        r"spin $\psi$",
    ]
    angles = np.stack([ax.get_lines()[0].get_ydata() for ax in fig.axes], axis=-1)
    np.testing.assert_allclose(so3.from_euler(angles[:, 0], angles[:, 1], angles[:, 2], "zxz"), sol.R, atol=1e-12)


def test_flips_are_marked_on_every_component_panel(flip):
    _, sol = flip
    fig = plot.components(sol, flips=[0.5, 2.0])
    for ax in fig.axes:
        marks = [ln for ln in ax.get_lines() if ln.get_linestyle() == "--"]
        assert sorted(float(ln.get_xdata()[0]) for ln in marks) == [0.5, 2.0]


def test_sweep_heatmap_colour_limits_ignore_one_extreme_cell():
    # A grid through an exact equilibrium has one sensitivity of ~1e16; with
    # min/max limits every other cell was the same colour.
    x, y = np.linspace(-1, 1, 9), np.linspace(-1, 1, 7)
    sens = np.outer(1.0 + x**2, 1.0 + y**2)
    sens[4, 3] = 1.78e16
    values = {"angle": np.outer(np.cos(x), np.sin(y)), "sensitivity": sens}
    sweep = OmegaSweep(axes=(x, y, np.zeros(1)), values=values, failed=np.zeros(sens.shape, bool), t1=1.0)
    fig = plot.omega_sweep(sweep, np.zeros(3), "t")
    mesh = fig.axes[1].collections[0]
    assert mesh.norm.vmax < 10 and mesh.norm.vmin >= 1.0
    marks = [ln for ln in fig.axes[1].get_lines() if ln.get_label().startswith("clipped")]
    assert marks and (4 * 0.25 - 1.0, 3 / 3 - 1.0) in set(zip(marks[0].get_xdata(), marks[0].get_ydata()))
