"""Pictures of a run, drawn offscreen (Agg, no display): the energy plot and the preview GIF.

- :func:`plot_energy` - kinetic, potential and total energy against time, as a PNG.
- :func:`render_preview` - a shaded animation of a triangle mesh, as a GIF.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
from PIL import Image

from fem3d.io.energy import energy_columns
from fem3d.io.files import PathLike, atomic_write
from fem3d.io.frames import check_faces, check_vertices
from fem3d.io.obstacles import ObstacleMesh, plane_square

__all__ = ["plot_energy", "render_preview"]


def plot_energy(data: Any, png_path: PathLike, *, title: str | None = None) -> Path:
    """Plot kinetic, potential (split into strain and gravity when the log has the split,
    with the pull springs' energy) and total energy against time into a PNG (Agg).

    Parameters
    ----------
    data : path of an energy CSV, EnergyLog, mapping or array (see
        :func:`fem3d.io.energy.energy_columns`)
    png_path : str or PathLike
    title : str, optional
    """
    # matplotlib is imported where used: only pictures need it, and it takes ~0.3 s to import
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    cols = energy_columns(data)
    fig = Figure(figsize=(7, 4), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.plot(cols["t"], cols["kinetic"], label="kinetic")
    if "strain" in cols:  # the split layout: V = strain + gravity, each its own line
        ax.plot(cols["t"], cols["strain"], label="strain (elastic)")
        ax.plot(cols["t"], cols["gravity"], label="gravity (potential)")
        if np.nanmax(np.abs(cols["pull"]), initial=0.0) > 0.0:
            ax.plot(cols["t"], cols["pull"], label="pull springs", linestyle="--")
        ax.plot(cols["t"], cols["potential"], label="V = strain + gravity", linestyle=":")
    else:
        ax.plot(cols["t"], cols["potential"], label="potential")
    ax.plot(cols["t"], cols["total"], label="total = kinetic + V", color="k", linewidth=1.5)
    ax.set_xlabel("time t [s]")
    ax.set_ylabel("energy")
    if title:
        ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return atomic_write(png_path, lambda p: fig.savefig(p, format="png"))


# --------------------------------------------------------------------------------------
# preview GIF


def _cluster_decimate(V0: np.ndarray, faces: np.ndarray, max_faces: int) -> tuple[Any, np.ndarray]:
    """Vertex-clustering decimation on a uniform grid at the rest shape.

    Returns a sparse ``(n_clusters, n_vertices)`` averaging matrix ``A`` and the faces on the
    clusters, so every frame decimates as ``A @ V``. Closed surfaces stay closed (no holes,
    unlike drawing a subset of faces); orientation is kept.
    """
    lo, hi = V0.min(axis=0), V0.max(axis=0)
    diag = float(np.linalg.norm(hi - lo)) or 1.0
    used = np.unique(faces)
    res = max(4.0, np.sqrt(max_faces / 2.0))  # cells along the diagonal; refined below
    best = None
    for _ in range(8):
        cell = diag / res
        key = np.floor((V0[used] - lo) / cell).astype(np.int64)
        _, cl_used = np.unique(key, axis=0, return_inverse=True)
        cl = np.full(V0.shape[0], -1, dtype=np.int64)
        cl[used] = cl_used.reshape(-1)
        Fc = cl[faces]
        ok = (Fc[:, 0] != Fc[:, 1]) & (Fc[:, 1] != Fc[:, 2]) & (Fc[:, 0] != Fc[:, 2])
        Fc = Fc[ok]
        Fc = Fc[np.unique(np.sort(Fc, axis=1), axis=0, return_index=True)[1]]
        if Fc.shape[0] <= max_faces:
            best = (cl, Fc)
            if Fc.shape[0] >= 0.7 * max_faces:
                break
            res *= min(2.0, np.sqrt(max_faces / max(Fc.shape[0], 1)) * 0.95)
        else:
            res *= max(0.5, np.sqrt(max_faces / Fc.shape[0]) * 0.95)
    if best is None:
        best = (cl, Fc)
    cl, Fc = best
    n_cl = int(cl.max()) + 1
    rows = cl[used]
    counts = np.bincount(rows, minlength=n_cl).astype(np.float64)
    A = sp.csr_matrix((1.0 / counts[rows], (rows, used)), shape=(n_cl, V0.shape[0]))
    return A, Fc


def _camera(elev_deg: float, azim_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal camera axes (right, up, toward-viewer) for a y-up world."""
    e, a = np.radians(elev_deg), np.radians(azim_deg)
    toward = np.array([np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)])
    right = np.cross([0.0, 1.0, 0.0], toward)
    norm = np.linalg.norm(right)
    if norm < 1e-9:  # looking straight down or up: any horizontal axis will do
        right, norm = np.array([np.cos(a), 0.0, -np.sin(a)]), 1.0
    right /= norm
    up = np.cross(toward, right)
    return right, up, toward


def render_preview(
    frames: Sequence[np.ndarray],
    faces: np.ndarray,
    path_gif: PathLike,
    fps: float = 20.0,
    *,
    max_frames: int = 60,
    max_faces: int = 12000,
    size: int = 400,
    elev: float = 15.0,
    azim: float = 30.0,
    color: tuple[float, float, float] = (0.78, 0.72, 0.62),
    margin: float = 0.15,
    view_bounds: str = "first",
    first_frame_png: PathLike | None = None,
    obstacles: Sequence[ObstacleMesh] = (),
    times: Sequence[float] | None = None,
) -> Path:
    """Render a shaded animation of a triangle mesh offscreen and save it as a GIF.

    Orthographic camera from ``elev`` / ``azim`` (degrees, ``y`` up), fixed for the whole
    clip, with the view box from the first frame (or all frames, ``view_bounds``) plus
    ``margin``, and equal aspect.
    Faces are depth-sorted (painter's algorithm) and drawn as a 2-D matplotlib
    ``PolyCollection`` on an Agg canvas, shaded per face with two-sided Lambert lighting
    from the face normals (light from the upper left of the camera).

    Parameters
    ----------
    frames : sequence of (n_vertices, 3) float64
        Vertex positions over time; at most ``max_frames`` evenly spaced ones are drawn
        (first and last included).
    faces : (n_faces, 3) int
    path_gif : str or PathLike
    fps : float
        Playback rate of the GIF.
    max_frames : int
    max_faces : int
        Meshes with more faces are decimated once (vertex clustering on a grid at the first
        frame, applied to every frame as a sparse average), keeping the surface closed.
    size : int
        Image width and height in pixels.
    elev, azim : float
        Camera elevation and azimuth in degrees (``azim = 0`` looks along ``-z``).
    color : (3,) float
        Base RGB colour.
    margin : float
        Relative padding around the projected bounding box.
    view_bounds : {"first", "all"}
        Fit the (fixed) view to the first frame, or to every drawn frame (nothing leaves
        the picture, e.g. a pulled arm).
    first_frame_png : str or PathLike, optional
        Also save the first rendered frame as a PNG (to look at).
    obstacles : sequence of ObstacleMesh, optional
        Drawn with the bodies: a plane as a grey checkerboard square (12 x 12 tiles) three
        view widths wide around the view's centre, behind everything (the camera looks at
        its free side); a mesh obstacle in blue-grey, depth-sorted with the bodies, at the
        frame's time (mesh obstacles count in the view box). A mesh obstacle that holds the
        bodies (an open box, a bowl: its horizontal bounds contain theirs) is drawn cut away:
        without its upright faces on the camera's side, which would hide what is inside.
    times : sequence of float, optional
        Time of each frame (moving obstacles); default: every frame at ``t = 0``.

    Returns
    -------
    Path
        ``path_gif``.

    Notes
    -----
    Cost is dominated by Agg drawing, about 6-8 microseconds per face per frame on one core
    (the full 52k-face armadillo skin: 0.4 s a frame, 24 s for 60 frames). Meshes above
    ``max_faces`` (12k by default) are therefore decimated: the armadillo skin then takes
    about 4 s for 60 frames at 400 px; the sim surface (a few hundred faces) renders at
    well over 20 frames per second. Pillow merges consecutive identical frames (summing
    their durations), so a GIF of a still shape has fewer frames than were drawn.
    The armadillo faces ``-z``: pass ``azim=210`` to see its front.
    """
    faces = check_faces(faces)
    if len(frames) == 0:
        raise ValueError("render_preview needs at least one frame")
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    pick = np.unique(np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).round())
    seq = [check_vertices(frames[int(i)], faces, int(i)) for i in pick]

    if faces.shape[0] > max_faces:
        A, F = _cluster_decimate(seq[0], faces, max_faces)
        seq = [A @ V for V in seq]
    else:
        F = faces
    base = np.asarray(color, dtype=np.float64)
    right, up, toward = _camera(elev, azim)
    planes = [ob for ob in obstacles if ob.plane is not None]
    meshes = [ob for ob in obstacles if ob.plane is None]
    ts = [0.0] * len(frames) if times is None else [float(x) for x in times]
    F, seq, base, backdrop = _with_meshes(F, seq, base, meshes, [ts[int(i)] for i in pick], toward)

    proj = np.stack([right, up, toward], axis=1)  # world -> (u, v, depth toward viewer)
    light = 0.55 * toward + 0.45 * up - 0.35 * right
    light /= np.linalg.norm(light)

    if view_bounds not in ("first", "all"):
        raise ValueError(f"view_bounds must be 'first' or 'all', got {view_bounds!r}")
    P0 = seq[0] @ proj if view_bounds == "first" else np.vstack(seq) @ proj
    for ob in planes:  # the ground under the bodies is in view (where they will land)
        point, normal = ob.plane
        n = np.asarray(normal, dtype=np.float64)
        foot = seq[0] - ((seq[0] - np.asarray(point)) @ n)[:, None] * n
        P0 = np.vstack([P0, foot @ proj])
    umin, vmin = P0[:, 0].min(), P0[:, 1].min()
    umax, vmax = P0[:, 0].max(), P0[:, 1].max()
    half = 0.5 * max(umax - umin, vmax - vmin, 1e-300) * (1.0 + 2.0 * margin)
    cu, cv = 0.5 * (umin + umax), 0.5 * (vmin + vmax)

    ground = _plane_tiles(planes, seq[0], proj, light, half) if planes else None
    images = _draw_frames(seq, F, proj, light, base, size, (cu, cv, half), ground, backdrop)
    if first_frame_png is not None:
        atomic_write(first_frame_png, lambda p: images[0].save(p, format="PNG"))
    return _save_gif(images, path_gif, fps)


#: Preview colours: mesh obstacles, and the two tiles of a plane's checkerboard.
OBSTACLE_RGB = (0.55, 0.62, 0.72)
PLANE_RGB = ((0.80, 0.80, 0.78), (0.62, 0.62, 0.60))


def _with_meshes(F: np.ndarray, seq: list[np.ndarray], base: np.ndarray,
                 meshes: Sequence[ObstacleMesh], times: Sequence[float], toward: np.ndarray
                 ) -> tuple[np.ndarray, list[np.ndarray], np.ndarray, np.ndarray]:
    """The bodies' faces and frames with the mesh obstacles' appended, each in its own colour
    (a container's near walls cut away, :func:`_cut_away`), per-face base colours ``(f, 3)``,
    and which faces are a container's (the backdrop: what is left of it lies behind or under
    the bodies)."""
    n = seq[0].shape[0]
    faces, cols = [F], [np.broadcast_to(base, (F.shape[0], 3))]
    backdrop = [np.zeros(F.shape[0], dtype=bool)]
    off = n
    for ob in meshes:
        Fo, holds = _cut_away(check_faces(ob.faces), ob.positions(times[0]), seq[0], toward)
        faces.append(Fo + off)
        cols.append(np.broadcast_to(np.asarray(OBSTACLE_RGB), (Fo.shape[0], 3)))
        backdrop.append(np.full(Fo.shape[0], holds))
        off += ob.vertices.shape[0]
    seq = [np.vstack([V] + [ob.positions(t) for ob in meshes])
           for V, t in zip(seq, times, strict=True)]
    return np.vstack(faces), seq, np.vstack(cols), np.concatenate(backdrop)


def _unit_normals(tri: np.ndarray) -> np.ndarray:
    """Unit normals ``(f, 3)`` of triangles ``(f, 3, 3)`` (zero for degenerate ones)."""
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nn = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, nn, out=np.zeros_like(n), where=nn > 0)


def _cut_away(F: np.ndarray, X: np.ndarray, bodies: np.ndarray,
              toward: np.ndarray) -> tuple[np.ndarray, bool]:
    """The faces ``F`` of a mesh obstacle at ``X`` worth drawing, and whether it holds the
    bodies (its horizontal bounds contain theirs: an open box, a bowl). All faces, unless it
    does and the camera is not straight above; then its upright faces turned toward the
    camera (outward from its centre) are left out: a painter's algorithm cannot see
    through them."""
    flat = np.array([toward[0], 0.0, toward[2]])  # toward the viewer, in the ground plane
    lo, hi = X.min(axis=0), X.max(axis=0)
    b_lo, b_hi = bodies.min(axis=0), bodies.max(axis=0)
    xz = [0, 2]
    holds = bool((lo[xz] <= b_lo[xz]).all() and (b_hi[xz] <= hi[xz]).all())
    if not holds or np.linalg.norm(flat) < 1e-9:  # not a container, or looked at from above
        return F, holds
    tri = X[F]
    n = _unit_normals(tri)
    outward = tri.mean(axis=1) - 0.5 * (lo + hi)
    n *= np.where(np.einsum("ij,ij->i", n, outward) < 0.0, -1.0, 1.0)[:, None]
    near = (np.abs(n[:, 1]) < 0.5) & (n @ flat > 0.0)
    return F[~near], True


def _plane_tiles(planes: Sequence[ObstacleMesh], V0: np.ndarray, proj: np.ndarray,
                 light: np.ndarray, half_view: float) -> tuple[np.ndarray, np.ndarray]:
    """The planes as checkerboards: projected quads ``(k, 4, 2)`` and their shaded RGB
    ``(k, 3)``, far first, around the bodies' first-frame centre, three view widths wide."""
    center = 0.5 * (V0.min(axis=0) + V0.max(axis=0))
    polys, rgbs, depth = [], [], []
    cells = 12
    for ob in planes:
        point, normal = ob.plane
        V, Fq = plane_square(point, normal, center, 3.0 * half_view, cells=cells)
        P = V @ proj
        quads = np.stack([Fq[0::2, 0], Fq[0::2, 1], Fq[0::2, 2], Fq[1::2, 2]], axis=1)
        i, j = np.divmod(np.arange(cells * cells), cells)
        tile = np.asarray(PLANE_RGB)[(i + j) % 2]
        n = np.asarray(normal, dtype=np.float64)
        rgbs.append(np.clip((0.45 + 0.55 * abs(float(n @ light))) * tile, 0.0, 1.0))
        polys.append(P[quads][:, :, :2])
        depth.append(P[quads, 2].mean(axis=1))
    order = np.argsort(np.concatenate(depth), kind="stable")
    return np.concatenate(polys)[order], np.concatenate(rgbs)[order]


def _draw_frames(seq: Sequence[np.ndarray], F: np.ndarray, proj: np.ndarray,
                 light: np.ndarray, base: np.ndarray, size: int,
                 box: tuple[float, float, float],
                 ground: tuple[np.ndarray, np.ndarray] | None = None,
                 backdrop: np.ndarray | None = None) -> list[Image.Image]:
    """Draw every frame of ``seq`` on one Agg canvas (see :func:`render_preview`).

    Parameters
    ----------
    seq : sequence of (n_vertices, 3) float64
    F : (n_faces, 3) int
    proj : (3, 3) float64
        World -> (u, v, depth toward the viewer).
    light : (3,) float64
        Unit direction toward the light.
    base : (3,) or (n_faces, 3) float64
        Base RGB colour (of every face, or per face).
    size : int
        Image width and height in pixels.
    box : (cu, cv, half)
        Centre and half width of the (square) view in the image plane.
    ground : ((k, 4, 2), (k, 3)) float64, optional
        Quads drawn behind every face (the planes, :func:`_plane_tiles`) and their colours.
    backdrop : (n_faces,) bool, optional
        Faces sorted by their farthest vertex instead of their centre (a container's floor
        and far walls: a large floor triangle partly under a body would otherwise be drawn
        over the body's foot).

    Returns
    -------
    list of PIL.Image.Image
        RGB images.
    """
    # matplotlib is imported where used: only pictures need it, and it takes ~0.3 s to import
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import PolyCollection
    from matplotlib.figure import Figure

    cu, cv, half = box
    dpi = 100
    fig = Figure(figsize=(size / dpi, size / dpi), dpi=dpi, facecolor="white")
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(cu - half, cu + half)
    ax.set_ylim(cv - half, cv + half)
    ax.set_aspect("equal")
    ax.set_axis_off()
    if ground is not None:
        ax.add_collection(PolyCollection(ground[0], closed=True, facecolors=ground[1],
                                         edgecolors=ground[1], linewidths=0.25,
                                         antialiaseds=False))
    coll = PolyCollection([], closed=True, linewidths=0.25, antialiaseds=False)
    ax.add_collection(coll)

    images: list[Image.Image] = []
    for V in seq:
        n = _unit_normals(V[F])
        shade = 0.25 + 0.75 * np.abs(n @ light)
        rgb = np.clip(shade[:, None] * (base if base.ndim == 2 else base[None, :]), 0.0, 1.0)
        P = V @ proj
        depth = P[F, 2].mean(axis=1)
        if backdrop is not None:
            depth[backdrop] = P[F[backdrop], 2].min(axis=1)
        order = np.argsort(depth, kind="stable")  # far first
        coll.set_verts(P[F[order]][:, :, :2])
        coll.set_facecolor(rgb[order])
        coll.set_edgecolor(rgb[order])  # hides hairline seams between faces
        canvas.draw()
        rgba = np.asarray(canvas.buffer_rgba())
        images.append(Image.fromarray(rgba[:, :, :3].copy()))
    return images


def _save_gif(images: Sequence[Image.Image], path_gif: PathLike, fps: float) -> Path:
    """Write ``images`` atomically as a looping GIF on the first image's palette."""
    pal = images[0].quantize(colors=255, method=Image.Quantize.MEDIANCUT)
    pimgs = [pal] + [im.quantize(palette=pal, dither=Image.Dither.NONE) for im in images[1:]]
    duration = max(20, int(round(1000.0 / fps)))
    return atomic_write(
        path_gif,
        lambda p: pimgs[0].save(
            p,
            format="GIF",
            save_all=True,
            append_images=pimgs[1:],
            duration=duration,
            loop=0,
            optimize=False,
            disposal=1,
        ),
    )
