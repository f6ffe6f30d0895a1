"""Figures and animations of a solved trajectory.

Every function builds a `matplotlib.figure.Figure` directly (no pyplot), so
nothing is ever shown, no global figure list grows, and the caller's backend
is left alone; in a notebook ``display(fig)`` shows it.  The figures of a
solve have fixed layouts with room for their labels (none is clipped:
tests/test_plot.py); the sweep's, with colour bars, constrained layout.

Data flow: `Solution` (and, where needed, the problem or the body's parts)
-> figure.  Only the valid saved entries are drawn (``Solution.n_saved``), so
adaptive solutions with padded buffers plot correctly.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any, NamedTuple, Sequence

import jax
import numpy as np
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure

from lierk import so3

from ..inertia import Part, composite

__all__ = [
    "components",
    "euler_angles",
    "invariants",
    "omega_sweep",
    "animate",
    "animation_frames",
    "write_gif",
    "GIF_DPI",
    "GIF_SIZE",
]

# Size of the animation in inches and its dpi: GIF frames are GIF_SIZE * GIF_DPI pixels.
GIF_SIZE = (5.0, 5.0)
GIF_DPI = 80


def _to_euler(R, convention: str) -> np.ndarray:
    """`lierk.so3.to_euler` of ``R`` ``(n, 3, 3)`` in one compiled program."""
    return np.asarray(_to_euler_program(R, convention))


_to_euler_program = jax.jit(so3.to_euler, static_argnums=1)


def _figure(figsize, title: str | None, margins: dict | None = None) -> Figure:
    """A figure of ``figsize`` (inches) with its subplots placed by
    ``margins`` (`Figure.subplots_adjust`'s fractions, for the labels each
    figure draws), or by constrained layout without them.  The figures of a
    solve have fixed layouts: constrained layout measured every label and
    drew each figure twice, most of the time ``lierk simulate`` spent on its
    three figures; tests/test_plot.py checks that no text is clipped."""
    fig = Figure(figsize=figsize, layout=None if margins is not None else "constrained")
    if margins is not None:
        fig.subplots_adjust(**margins)
    if title:
        fig.suptitle(title)
    return fig


def _mark_events(axs, events, legend_ax) -> None:
    """Vertical lines at the times of ``events`` (``{name: times (s)}``) on
    every axis of ``axs``, one style per event, named in ``legend_ax``'s legend."""
    if not events:
        return
    styles = ["--", ":", "-.", (0, (5, 1, 1, 1))]
    for k, (name, times) in enumerate(events.items()):
        for ax in np.ravel(axs):
            for j, tf in enumerate(np.ravel(times)):
                label = name if ax is legend_ax and j == 0 else None
                ax.axvline(tf, color=f"0.{3 + k % 4}", ls=styles[k % 4], lw=0.8, zorder=0, label=label)
    if any(np.size(t) for t in events.values()):
        legend_ax.legend(loc="upper right", fontsize=8)


def components(sol, title: str | None = None, *, figsize=(9.0, 7.0), flips=None, events=None) -> Figure:
    """3x3 grid of the entries ``R_ij(t)`` of the attitude (the report's figures
    14-16): row ``i`` is the space-frame axis, column ``j`` the body axis, so
    column ``j`` is body axis ``j`` seen in space.  All panels share ``[-1, 1]``.
    ``events``: ``{name: times (s)}`` (`lierk.app.scene.Scene.event_times`),
    marked with vertical lines; ``flips``: times of flips, the same as
    ``events={"flip": flips}``."""
    ts, R, _ = sol.trajectory()
    fig = _figure(
        figsize, title, dict(left=0.09, right=0.98, bottom=0.08, top=0.88 if title else 0.94, wspace=0.1, hspace=0.3)
    )
    axs = fig.subplots(3, 3, sharex=True, sharey=True)
    colours = ["tab:red", "tab:blue", "tab:green"]
    for i in range(3):
        for j in range(3):
            ax = axs[i, j]
            ax.plot(ts, R[:, i, j], color=colours[j], lw=0.9)
            ax.set_title(f"$R_{{{i + 1}{j + 1}}}$", fontsize=10)
            ax.axhline(0.0, color="0.8", lw=0.5, zorder=0)
            ax.grid(True, alpha=0.3)
    _mark_events(axs, {**({} if flips is None else {"flip": flips}), **(events or {})}, axs[0, 2])
    axs[0, 0].set_ylim(-1.08, 1.08)
    axs[0, 0].set_yticks([-1.0, -0.5, 0.0, 0.5, 1.0])
    if len(ts):
        axs[0, 0].set_xlim(ts[0], ts[-1])
    for ax in axs[-1, :]:
        ax.set_xlabel("t [s]")
    for ax in axs[:, 0]:
        ax.set_ylabel("component [-]")
    return fig


def euler_angles(
    sol,
    title: str | None = None,
    *,
    degrees: bool = False,
    convention: str = "zyx",
    figsize=(8.0, 6.5),
    events=None,
    angles=None,
) -> Figure:
    """Euler angles (`lierk.so3.to_euler`) against time, one panel each.

    ``convention="zyx"`` (the report's ``R = Rz(phi) Ry(theta) Rx(psi)``) or
    ``"zxz"``, the classical angles of a top ``R = Rz(phi) Rx(theta) Rz(psi)``:
    precession, nutation and spin, so a top's precession and nutation show
    apart from its spin.  ``phi`` and ``psi`` are unwrapped so a steady spin
    shows as a ramp rather than a saw-tooth.  ``events``: as for `components`.
    ``angles``: the ``(n, 3)`` angles if already computed
    (`lierk.app.diagnostics.Diagnostics.euler_angles` in ``convention``), else
    they are computed here."""
    ts, R, _ = sol.trajectory()
    if angles is None:
        angles = _to_euler(R, convention)
    angles = np.unwrap(np.asarray(angles).reshape(-1, 3), axis=0)
    unit = "deg" if degrees else "rad"
    if degrees:
        angles = np.degrees(angles)
    fig = _figure(figsize, title, dict(left=0.14, right=0.97, bottom=0.08, top=0.92 if title else 0.97, hspace=0.12))
    axs = fig.subplots(3, 1, sharex=True)
    names = {
        "zyx": [r"$\phi$ (about space $z$)", r"$\theta$ (about $y$)", r"$\psi$ (about body $x$)"],
        "zxz": [r"precession $\phi$", r"nutation $\theta$", r"spin $\psi$"],
    }[convention]
    for k, ax in enumerate(axs):
        ax.plot(ts, angles[:, k], color=f"C{k}", lw=1.0)
        ax.set_ylabel(f"{names[k]} [{unit}]")
        ax.grid(True, alpha=0.3)
    _mark_events(axs, events, axs[0])
    if len(ts):
        axs[0].set_xlim(ts[0], ts[-1])
    axs[-1].set_xlabel("t [s]")
    return fig


def invariants(sol, problem, title: str | None = None, *, figsize=(10.0, 4.5), quantities=None) -> Figure:
    """The quantities of ``problem.invariants(R, y)`` (energy and ``|L|`` for
    the free body) against time.

    Those the exact flow conserves (all of them, unless the problem has a
    ``conserved()`` method saying otherwise) are drawn as the relative drift
    ``(Q(t) - Q(0)) / |Q(0)|`` on a linear axis symmetric about 0 (at least
    10 machine epsilons each way), with the band of one machine epsilon
    shaded: the legend gives each quantity's largest drift.  The others (e.g. energy under damping) get a second
    panel with the ratio ``Q(t) / Q(0)`` on a linear axis.  ``quantities``:
    the invariants if already computed (`lierk.app.diagnostics.Diagnostics.invariants`),
    else they are computed here."""
    ts, R, y = sol.trajectory()
    if quantities is None:
        from .diagnostics import diagnostics

        quantities = diagnostics(problem, sol).invariants
    quantities = {k: np.asarray(v).reshape(len(ts), -1) for k, v in quantities.items()}
    conserved = problem.conserved() if hasattr(problem, "conserved") else tuple(quantities)
    kept = {k: v for k, v in quantities.items() if k in conserved}
    other = {k: v for k, v in quantities.items() if k not in conserved}
    eps = float(np.finfo(R.dtype).eps)
    tall = bool(kept and other)
    fig = _figure(
        figsize if not tall else (figsize[0], figsize[1] * 1.5),
        title,
        dict(
            left=0.13,
            right=0.66,
            bottom=0.12 if not tall else 0.08,
            top=(0.86 if not tall else 0.9) if title else 0.95,
            hspace=0.1,
        ),
    )
    if not quantities:
        ax = fig.subplots()
        ax.text(0.5, 0.5, "this problem declares no invariants", ha="center", va="center", transform=ax.transAxes)
        ax.set_axis_off()
        return fig
    axs = list(np.atleast_1d(fig.subplots(int(bool(kept)) + int(bool(other)), 1, sharex=True)))
    colour = {k: f"C{i}" for i, k in enumerate(quantities)}

    def lines(group):
        for name, q in group.items():
            for c in range(q.shape[1]):
                label = name if q.shape[1] == 1 else f"{name}[{c}]"
                yield label, colour[name], q[:, c]

    if kept:
        ax = axs[0]
        top = eps
        for label, col, q in lines(kept):
            rel = (q - q[0]) / (abs(q[0]) if q[0] != 0 else 1.0)
            ax.plot(ts, rel, lw=1.0, color=col, label=f"{label}: max |drift| {np.nanmax(np.abs(rel)):.2e}")
            top = max(top, float(np.nanmax(np.abs(rel))))
        # A linear axis: a drift of 1e-9 that changes sign reads as the
        # small wobble it is (a symmetric-log axis drew it as swings of many
        # decades).  Round-off (the grey band) shows when nothing else does.
        ax.axhspan(-eps, eps, color="0.9", zorder=0, label=f"|drift| < eps = {eps:.1e}")
        half = 1.1 * max(top, 10 * eps)
        ax.set_ylim(-half, half)
        ax.ticklabel_format(axis="y", style="sci", scilimits=(0, 0), useMathText=True)
        ax.set_ylabel("conserved: relative drift\n(Q(t) - Q(0)) / |Q(0)| [-]")
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    if other:
        ax = axs[-1]
        for label, col, q in lines(other):
            ratio = q / q[0] if q[0] != 0 else q
            span = f"{np.nanmin(ratio):.3g} .. {np.nanmax(ratio):.3g}"
            ax.plot(ts, ratio, lw=1.0, color=col, ls="--", label=f"{label}: {span}")
        ax.set_ylabel("not conserved here:\nQ(t) / Q(0) [-]")
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    for ax in axs:
        ax.grid(True, alpha=0.3)
        if len(ts):
            ax.set_xlim(ts[0], ts[-1])
    axs[-1].set_xlabel("t [s]")
    return fig


# ----------------------------------------------------------------------------
# Animation


def omega_sweep(sweep, omega0, title: str | None = None) -> Figure:
    """The figure of an `lierk.app.omega_sweep.OmegaSweep` (``lierk sweep``):
    one panel per quantity, a line plot for one varied component of omega0,
    heatmaps for two.

    Args:
        sweep: what `lierk.app.omega_sweep.sweep_omega0` returned; its
            ``values`` per quantity over the grid (NaN where a point failed):
            ``"angle"`` (rad), ``"sensitivity"`` (``||dR(T)/d omega0||_F``,
            s), optionally ``"lyapunov"`` (1/s) and ``"flip_interval"`` (s,
            ``inf``: no flip).
        omega0: ``(3,)`` the scene's own omega0 (rad/s), marked on heatmaps.
        title: the figure's title.
    """
    from matplotlib.colors import LogNorm

    res, varied = sweep.values, sweep.varied
    axes = [sweep.axes[k] for k in varied]

    panels = []
    if "flip_interval" in res:
        panels.append(("flip_interval", "flip interval (exact) [s]", True))
    panels.append(("angle", "final attitude angle |log R(T)| [rad]", False))
    panels.append(("sensitivity", "sensitivity ||dR(T)/d$\\omega_0$||$_F$ [s]", True))
    if "lyapunov" in res:
        panels.append(("lyapunov", "finite-time Lyapunov exponent [1/s]", False))
    labels = [f"$\\omega_{{0,{'xyz'[k]}}}$ [rad/s]" for k in varied]

    if len(varied) == 1:
        fig = _figure((7.0, 2.4 * len(panels) + 0.8), title)
        axs = fig.subplots(len(panels), 1, sharex=True, squeeze=False)[:, 0]
        for ax, (key, label, log) in zip(axs, panels):
            v = np.where(np.isfinite(res[key]), res[key], np.nan)
            ax.plot(axes[0], v, ".-", lw=1.0, ms=3)
            if log:
                ax.set_yscale("log")
            ax.set_ylabel(label, fontsize=9)
            ax.grid(True, alpha=0.3)
        axs[-1].set_xlabel(labels[0])
        return fig

    fig = _figure((4.6 * len(panels), 4.6), title)
    axs = fig.subplots(1, len(panels), squeeze=False)[0]
    x, y = axes
    for ax, (key, label, log) in zip(axs, panels):
        v = np.asarray(res[key], dtype=float)
        finite = v[np.isfinite(v) & (v > 0)] if log else v[np.isfinite(v)]
        # Robust colour limits: one extreme cell (the sensitivity is ~1e16 at an
        # exact equilibrium) must not turn the rest of the map one colour.
        # Cells beyond the 1st/99th percentiles are clipped and outlined.
        lo, hi = (
            (np.percentile(finite, 1, method="higher"), np.percentile(finite, 99, method="lower"))
            if finite.size
            else (None, None)
        )
        norm = LogNorm(lo, hi) if log and finite.size and lo < hi else None
        masked = np.ma.masked_invalid(np.where(v > 0, v, np.nan) if log else v)
        cmap = "viridis" if key != "sensitivity" else "magma"
        im = ax.pcolormesh(
            x,
            y,
            masked.T,
            shading="nearest",
            norm=norm,
            cmap=cmap,
            **({} if log or lo is None or not lo < hi else dict(vmin=lo, vmax=hi)),
        )
        im.cmap = im.cmap.with_extremes(bad="0.75")
        if lo is not None and lo < hi:
            clipped = np.isfinite(v) & ((v > hi) | (v < lo))
            if clipped.any():
                xx, yy = np.meshgrid(x, y, indexing="ij")
                ax.plot(
                    xx[clipped],
                    yy[clipped],
                    "s",
                    ms=5,
                    mfc="none",
                    mec="c",
                    mew=0.8,
                    label=f"clipped ({int(clipped.sum())} cells)",
                )
                ax.legend(loc="upper right", fontsize=6)
        ax.plot([omega0[varied[0]]], [omega0[varied[1]]], "w+", ms=10, mew=2, label="scene's $\\omega_0$")
        ax.set_xlabel(labels[0])
        ax.set_ylabel(labels[1])
        ax.set_aspect("equal" if np.ptp(x) and 0.33 < np.ptp(y) / np.ptp(x) < 3 else "auto")
        fig.colorbar(im, ax=ax, label=label, shrink=0.85)
        if key == "flip_interval" and not np.isfinite(v).all():
            ax.text(
                0.02,
                0.98,
                "grey: no flip (lierk.exact.flip_interval)",
                transform=ax.transAxes,
                fontsize=7,
                va="top",
                color="k",
                bbox=dict(fc="w", alpha=0.7, lw=0),
            )
    axs[0].legend(loc="lower right", fontsize=7)
    return fig


def _cylinder_mesh(radius: float, length: float, axis: str, n: int = 16):
    """Quads ``(F, 4, 3)`` and stripe index per face of a closed cylinder."""
    k = "xyz".index(axis)
    a, b = [i for i in range(3) if i != k]
    th = np.linspace(0.0, 2 * np.pi, n + 1)
    ring = np.zeros((n + 1, 3))
    ring[:, a], ring[:, b] = radius * np.cos(th), radius * np.sin(th)
    lo, hi = ring.copy(), ring.copy()
    lo[:, k], hi[:, k] = -length / 2, length / 2
    faces = [np.stack([lo[i], lo[i + 1], hi[i + 1], hi[i]]) for i in range(n)]
    stripe = [i % 2 for i in range(n)]
    # End caps as wedges (quads with a repeated centre), striped like the side
    # so a spin about the symmetry axis is visible.
    for cap in (lo, hi):
        centre = np.zeros(3)
        centre[k] = cap[0, k]
        faces += [np.stack([centre, cap[i], cap[i + 1], centre]) for i in range(n)]
        stripe += [i % 2 for i in range(n)]
    return np.array(faces), np.array(stripe)


def _box_mesh(lx: float, ly: float, lz: float):
    h = np.array([lx, ly, lz]) / 2
    faces = []
    for k in range(3):
        a, b = [i for i in range(3) if i != k]
        for s in (-1.0, 1.0):
            quad = np.zeros((4, 3))
            quad[:, k] = s * h[k]
            quad[:, a] = np.array([-1, 1, 1, -1]) * h[a]
            quad[:, b] = np.array([-1, -1, 1, 1]) * h[b]
            faces.append(quad)
    return np.array(faces), np.array([0, 0, 1, 1, 0, 0])


def _sphere_mesh(radius: float, n: int = 16):
    th = np.linspace(0.0, np.pi, n // 2 + 1)
    ph = np.linspace(0.0, 2 * np.pi, n + 1)

    def p(t, f):
        return radius * np.array([np.sin(t) * np.cos(f), np.sin(t) * np.sin(f), np.cos(t)])

    faces, stripe = [], []
    for i in range(len(th) - 1):
        for j in range(n):
            faces.append(np.stack([p(th[i], ph[j]), p(th[i], ph[j + 1]), p(th[i + 1], ph[j + 1]), p(th[i + 1], ph[j])]))
            stripe.append((i + j) % 2)
    return np.array(faces), np.array(stripe)


def _part_mesh(part: Part):
    shape = part.shape
    kind = shape[0] if shape else None
    if kind == "cylinder":
        faces, stripe = _cylinder_mesh(float(shape[1]), float(shape[2]), str(shape[3]))
    elif kind == "box":
        faces, stripe = _box_mesh(*(float(s) for s in shape[1:4]))
    elif kind == "sphere":
        faces, stripe = _sphere_mesh(float(shape[1]))
    elif kind == "mesh":
        # Triangles as quads with the last corner repeated (one face array).
        tri = np.asarray(shape[1], dtype=float)
        faces, stripe = np.concatenate([tri, tri[:, 2:]], axis=1), np.zeros(len(tri), int)
    else:
        warnings.warn(f"cannot draw a part of shape {shape!r}; it is left out of the animation", stacklevel=3)
        return None
    Q = np.eye(3) if part.rotation is None else np.asarray(part.rotation, dtype=float)
    return faces @ Q.T + np.asarray(part.offset, dtype=float), stripe


def equivalent_box(inertia) -> list[Part]:
    """A uniform box with the principal moments of ``inertia`` (up to mass,
    which only scales it), for drawing a body given only by its inertia."""
    inertia = np.asarray(inertia, dtype=float)
    inertia = np.diag(inertia) if inertia.ndim == 1 else inertia
    moments, axes = np.linalg.eigh(inertia)
    if np.linalg.det(axes) < 0:
        axes[:, -1] *= -1
    # Box: I_x = m (ly^2 + lz^2)/12 etc., so lx^2 = 6 (I_y + I_z - I_x) / m.
    total = moments.sum()
    sq = 6.0 * np.maximum(total - 2.0 * moments, 1e-3 * total)
    lengths = np.sqrt(sq / sq.max())
    return [Part(1.0, np.diag(moments), np.zeros(3), axes, ("box", *lengths))]


def animate(
    sol,
    parts: Sequence[Part] | None,
    path,
    L=None,
    *,
    frames: int = 120,
    fps: int = 20,
    title: str | None = None,
    inertia=None,
    origin=None,
    trail: bool = True,
) -> Path:
    """Write a GIF of the body turning in the space frame.

    The body is drawn from ``parts`` (`lierk.inertia.Part` with ``shape``
    ``("cylinder", radius, length, axis)``, ``("box", lx, ly, lz)``,
    ``("sphere", radius)`` or ``("mesh", triangles (F, 3, 3))``, the
    triangles about the part's centre; every face is drawn, so a mesh of
    many thousand faces makes a slow GIF), with the body point ``origin`` (``(3,)``, body
    frame, m; default the parts' centre of mass, e.g. a top's pivot) pinned at
    the space origin: a body point ``x`` is drawn at ``R (x - origin)``.  With
    ``parts=None`` a box with the principal moments of ``inertia`` is drawn, or
    only the axes.  Body axes ``x_b, y_b, z_b`` are the columns of ``R``; the
    faint trail follows the tip of the body axis that starts closest to ``L``.  ``L`` is the spatial angular
    momentum, ``(3,)`` or ``(n_saved, 3)``, drawn as a black arrow scaled to
    the body size (its direction is what matters).

    Args:
        sol: an unbatched `Solution` saving many steps.
        path: output file (``.gif``).
        frames: number of frames, spread evenly over the saved entries.
        fps: frames per second of the GIF.

    Returns:
        ``path`` as a `Path`.  The GIF is ``GIF_SIZE * GIF_DPI`` pixels.
    """
    images = animation_frames(sol, parts, L, frames=frames, title=title, inertia=inertia, origin=origin, trail=trail)
    return write_gif(images, path, fps)


def animation_frames(
    sol, parts, L=None, *, frames: int = 120, title: str | None = None, inertia=None, origin=None, trail: bool = True
) -> list[np.ndarray]:
    """The frames of `animate`'s GIF (same arguments), RGB ``(h, w, 3)``
    uint8 each, ``GIF_SIZE * GIF_DPI`` pixels; `write_gif` writes them."""
    ts, R, _ = sol.trajectory()
    return _frames(_animation(ts, R, parts, L, frames=frames, title=title, inertia=inertia, origin=origin, trail=trail))


class _Animation(NamedTuple):
    """A figure to animate: ``update(k)`` moves the ``moving`` artists of the
    3-D axes ``ax`` to frame ``k`` of ``n_frames``."""

    fig: Figure
    ax: Any
    update: Any
    moving: list
    n_frames: int


def _animation(ts, R, parts, L, *, frames, title, inertia, origin, trail) -> _Animation:
    """The figure of `animate` and how to move it from frame to frame."""
    from matplotlib.ticker import MaxNLocator
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    if len(ts) == 0:
        raise ValueError("the solution has no saved states to animate")
    idx = np.unique(np.linspace(0, len(ts) - 1, max(int(frames), 1)).round().astype(int))

    if parts is None and inertia is not None:
        parts = equivalent_box(inertia)
    meshes, colours = [], []
    if parts:
        if origin is None:
            origin = composite(list(parts)).center_of_mass
        origin = np.asarray(origin, dtype=float)
        palette = [("#4c72b0", "#8fb0e0"), ("#dd8452", "#f2c19e"), ("#55a868", "#a3d6b0"), ("#8172b3", "#c1b7e3")]
        for k, part in enumerate(parts):
            mesh = _part_mesh(part)
            if mesh is None:
                continue
            faces, stripe = mesh
            meshes.append(faces - origin)
            pair = palette[k % len(palette)]
            colours.append(np.array([to_rgb(pair[s]) for s in stripe]))
    faces = np.concatenate(meshes) if meshes else np.zeros((0, 4, 3))
    base_colour = np.concatenate(colours) if colours else np.zeros((0, 3))
    size = float(np.abs(faces).max()) if len(faces) else 1.0
    arm = 1.8 * size

    if L is not None:
        L = np.asarray(L, dtype=float)
        L = np.broadcast_to(L, (len(ts), 3)) if L.ndim == 1 else L[: len(ts)]
        Lmax = np.linalg.norm(L, axis=-1).max()
        L_dir = L / Lmax if Lmax > 0 else L

    # A fixed layout: constrained layout would lay out (draw) every frame twice.
    fig = Figure(figsize=GIF_SIZE, dpi=GIF_DPI)
    ax = fig.add_axes((0.03, 0.02, 0.9, 0.9), projection="3d")
    lim = 1.6 * size
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.set_zlim(-lim, lim)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x [m]", labelpad=-6)
    ax.set_ylabel("y [m]", labelpad=-6)
    ax.set_zlabel("z [m]", labelpad=-6)
    ax.tick_params(labelsize=6, pad=-2)
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        axis.set_major_locator(MaxNLocator(3))
    ax.view_init(elev=22, azim=-55)
    if title:
        fig.suptitle(title, fontsize=9)

    body = Poly3DCollection(faces, edgecolor="none")
    ax.add_collection3d(body)
    axis_colours = ["tab:red", "tab:green", "tab:blue"]
    axis_lines = [ax.plot([], [], [], color=c, lw=2.0, label=f"${n}_b$")[0] for c, n in zip(axis_colours, "xyz")]
    # Trail the body axis that starts closest to L: the spin axis, whose tip
    # shows flips, precession and nutation rather than the spin itself.
    trail_axis = int(np.argmax(np.abs(R[0].T @ L[0]))) if L is not None else 0
    trail_line = ax.plot([], [], [], color=axis_colours[trail_axis], lw=0.6, alpha=0.35)[0] if trail else None
    L_line = ax.plot([], [], [], color="k", lw=2.5, label="L (direction)")[0] if L is not None else None
    L_head = ax.plot([], [], [], "ko", ms=4)[0] if L is not None else None
    time_text = ax.text2D(0.02, 0.02, "", transform=ax.transAxes, fontsize=8)
    ax.legend(loc="upper right", fontsize=7)
    light = np.array([0.4, -0.5, 0.75])
    light /= np.linalg.norm(light)

    def draw(frame):
        i = idx[frame]
        Ri = R[i]
        if len(faces):
            world = faces @ Ri.T
            body.set_verts(world)
            n = np.cross(world[:, 1] - world[:, 0], world[:, 2] - world[:, 0])
            # Wedge faces of caps repeat the centre; use the other diagonal there.
            n2 = np.cross(world[:, 2] - world[:, 0], world[:, 3] - world[:, 1])
            n = np.where(np.linalg.norm(n, axis=1, keepdims=True) > 0, n, n2)
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
            shade = 0.45 + 0.55 * np.abs(n @ light)
            body.set_facecolor(np.clip(base_colour * shade[:, None], 0, 1))
        for k, line in enumerate(axis_lines):
            tip = arm * Ri[:, k]
            line.set_data_3d([0, tip[0]], [0, tip[1]], [0, tip[2]])
        if trail_line is not None:
            tips = arm * R[: i + 1, :, trail_axis]
            trail_line.set_data_3d(tips[:, 0], tips[:, 1], tips[:, 2])
        if L_line is not None:
            tip = arm * L_dir[i]
            L_line.set_data_3d([0, tip[0]], [0, tip[1]], [0, tip[2]])
            L_head.set_data_3d([tip[0]], [tip[1]], [tip[2]])
        time_text.set_text(f"t = {ts[i]:.2f} s")
        return []

    moving = [a for a in (body, *axis_lines, trail_line, L_line, L_head, time_text) if a is not None]
    return _Animation(fig, ax, draw, moving, len(idx))


def _frames(animation: _Animation) -> list[np.ndarray]:
    """The RGB frames ``(h, w, 3)`` (uint8) of ``animation``, by blitting:
    everything that does not move (panes, grid, ticks, labels, title,
    legend) is drawn once, and each frame restores that picture and draws
    only the moving artists on it, in the order a full draw would (by zorder;
    the body's is set from its depth), with the legend pasted back over
    them.  The pixels are a full draw's (`tests/test_plot.py`), at a fifth
    of the time."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig, ax, update, moving, n = animation
    canvas = FigureCanvasAgg(fig)
    for a in moving:
        a.set_animated(True)
    canvas.draw()
    background = canvas.copy_from_bbox(fig.bbox)
    legend = canvas.copy_from_bbox(ax.get_legend().get_window_extent())
    moving = sorted(moving, key=lambda a: a.get_zorder())
    images = []
    for frame in range(n):
        update(frame)
        canvas.restore_region(background)
        for a in moving:
            if hasattr(a, "do_3d_projection"):
                a.do_3d_projection()
            ax.draw_artist(a)
        canvas.restore_region(legend)
        images.append(np.array(canvas.buffer_rgba())[..., :3])
    return images


def write_gif(images: list[np.ndarray], path, fps: int = 20) -> Path:
    """Write a looping GIF of RGB frames ``(h, w, 3)`` (uint8), ``fps`` per
    second, to ``path`` (its folder is made if needed); returns it as a `Path`.

    One 256-colour palette serves every frame: it is fitted (median cut) to
    eight frames spread over the run and each frame is mapped to it, which
    is several times faster than fitting a palette per frame (Pillow's default) and
    makes a file half the size; the colours differ from per-frame palettes
    by at most a few levels."""
    from PIL import Image

    sample = images[:: max(1, len(images) // 8)]
    palette = Image.fromarray(np.concatenate(sample, axis=1)).quantize(256, method=Image.Quantize.MEDIANCUT)
    frames = [Image.fromarray(im).quantize(palette=palette, dither=Image.Dither.NONE) for im in images]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames[0].save(path, format="GIF", save_all=True, append_images=frames[1:], duration=int(1000 / fps), loop=0)
    return path
