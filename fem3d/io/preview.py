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
from fem3d.io.frames.base import check_faces, check_vertices
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
        Fc = _net_faces(Fc)
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


def _net_faces(F: np.ndarray) -> np.ndarray:
    """The faces ``F`` with coincident ones summed as oriented triangles: a pair of opposite
    orientation cancels, so a closed oriented surface stays one (:func:`_outward_sign`)."""
    G = np.take_along_axis(F, (np.argmin(F, axis=1)[:, None] + np.arange(3)) % 3, axis=1)
    sign = np.where(G[:, 1] < G[:, 2], 1, -1)  # smallest index first: orientation kept
    key = np.stack([G[:, 0], G[:, 1:].min(axis=1), G[:, 1:].max(axis=1)], axis=1)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    net = np.bincount(inv.ravel(), weights=sign, minlength=uniq.shape[0]).astype(np.int64)
    keep = net != 0
    out, net = uniq[keep], net[keep]
    out[net < 0] = out[net < 0][:, [0, 2, 1]]
    return np.repeat(out, np.abs(net), axis=0)


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
    Faces are drawn by a vectorised NumPy z-buffer (the nearest surface at each pixel
    centre; no matplotlib), shaded per face with two-sided Lambert lighting from the face
    normals (light from the upper left of the camera). The back faces of a closed surface
    are skipped (its front faces hide them).

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
    Cost grows with the pixels the faces' bounding boxes cover and the number of faces:
    60 frames at 400 px take about 1.3 s of one core for the bunny skin (decimated from
    17.6k to 11k faces), 0.9 s for the armadillo skin decimated to 12k faces and 1.7 s for
    all its 52k faces (matplotlib's Agg took 5-6 s, 4 s and 24 s). Pillow merges
    consecutive identical frames (summing their durations), so a GIF of a still shape has
    fewer frames than were drawn.
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
    n_body = F.shape[0]
    facing = _outward_sign(seq[0], F)
    F, seq, base, backdrop = _with_meshes(F, seq, base, meshes, [ts[int(i)] for i in pick], toward)
    facing = np.concatenate([facing, np.zeros(F.shape[0] - n_body)])  # obstacles: all drawn

    proj = np.stack([right, up, toward], axis=1)  # world -> (u, v, depth toward viewer)
    light = 0.55 * toward + 0.45 * up - 0.35 * right
    light /= np.linalg.norm(light)

    cu, cv, half = _view_box(seq, proj, planes, view_bounds, margin)
    ground = _plane_tiles(planes, seq[0], proj, light, half) if planes else None
    images = _draw_frames(seq, F, proj, light, base, size, (cu, cv, half), ground, backdrop,
                          facing)
    if first_frame_png is not None:
        atomic_write(first_frame_png, lambda p: images[0].save(p, format="PNG"))
    return _save_gif(images, path_gif, fps)


#: Preview colours: mesh obstacles, and the two tiles of a plane's checkerboard.
OBSTACLE_RGB = (0.55, 0.62, 0.72)
PLANE_RGB = ((0.80, 0.80, 0.78), (0.62, 0.62, 0.60))


def _view_box(seq: Sequence[np.ndarray], proj: np.ndarray, planes: Sequence[ObstacleMesh],
              view_bounds: str, margin: float) -> tuple[float, float, float]:
    """The fixed view's centre (u, v) and half width, padded by ``margin``."""
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
    return 0.5 * (umin + umax), 0.5 * (vmin + vmax), half


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


def _outward_sign(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Per face: +1 (or -1) when the face's normal points out of (into) the solid its
    connected part bounds, 0 when the faces are not the oriented boundary of a solid.

    The faces bound a solid when every directed edge ``a -> b`` is matched by as many
    ``b -> a`` (closed and consistently oriented, non-manifold clusters included); the side
    comes from the sign of each part's enclosed volume. A face whose normal, times this
    sign, points away from the camera is hidden by the part's own front faces: the
    z-buffer may skip it (half the pixels of a closed surface).
    """
    n = V.shape[0]
    if F.shape[0] == 0:
        return np.zeros(0)
    a, b = F.ravel(), F[:, [1, 2, 0]].ravel()
    if not np.array_equal(np.sort(a * n + b), np.sort(b * n + a)):
        return np.zeros(F.shape[0])
    from scipy.sparse.csgraph import connected_components

    graph = sp.coo_matrix((np.ones(a.size), (a, b)), shape=(n, n))
    _, part = connected_components(graph, directed=False)
    tri = V[F]
    vol = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))
    part_vol = np.bincount(part[F[:, 0]], weights=vol)
    return np.sign(part_vol)[part[F[:, 0]]]


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
    camera (outward from its centre) are left out: they would hide what is inside."""
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


#: Bits of a z-buffer key (:func:`_rasterize`): layer | quantised depth | face index.
_FACE_BITS = 24
_DEPTH_BITS = 30
#: Pixel candidates per vectorised batch (bounds the memory of one batch to ~40 MB).
_BATCH = 1 << 19


def _rasterize(xy: np.ndarray, z: np.ndarray, ids: np.ndarray, layer: int, buf: np.ndarray,
               size: int) -> None:
    """Draw triangles into a z-buffer of keys, vectorised over the pixels they cover.

    Every pixel centre inside a triangle (edges included, so neighbours leave no seam) gets
    ``key = layer << 54 | depth << 24 | id``; the largest key wins (a higher layer, then the
    nearer surface, then the higher id), through ``np.maximum.at``.

    Parameters
    ----------
    xy : (f, 3, 2) float64
        Corners in pixels (x right, y down; pixel ``(i, j)`` has its centre at ``(i+.5, j+.5)``).
    z : (f, 3) float64
        Corner depths in [0, 1], 1 nearest the viewer.
    ids : (f,) int64
        Face index of each triangle (< 2**24), what the buffer keeps.
    layer : int
        0-3; a higher layer is drawn over a lower one whatever the depths.
    buf : (size * size,) int64
        The keys, -1 where nothing is drawn yet; updated in place.
    size : int
    """
    a, b, c = xy[:, 0], xy[:, 1], xy[:, 2]
    area2 = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    lo = np.clip(np.ceil(xy.min(axis=1) - 0.5), 0, size).astype(np.int64)
    hi = np.clip(np.floor(xy.max(axis=1) - 0.5), -1, size - 1).astype(np.int64)
    w = np.maximum(hi[:, 0] - lo[:, 0] + 1, 0)
    h = np.maximum(hi[:, 1] - lo[:, 1] + 1, 0)
    count = np.where(np.abs(area2) > 1e-12, w * h, 0)
    keep = np.flatnonzero(count)
    if keep.size == 0:
        return
    a, b, c, area2, z = a[keep], b[keep], c[keep], area2[keep], z[keep]
    lo, w, count, ids = lo[keep], w[keep], count[keep], ids[keep]
    # barycentric weights and depth as affine functions of the pixel centre: one row a face
    inv = 1.0 / area2
    coef = np.empty((9, keep.size))  # rows: 1-D gathers are ~10x faster than of (n, 9)
    for k, (p, q) in enumerate(((b, c), (c, a))):  # w0 from edge bc, w1 from edge ca
        coef[3 * k] = (p[:, 1] - q[:, 1]) * inv
        coef[3 * k + 1] = (q[:, 0] - p[:, 0]) * inv
        coef[3 * k + 2] = (p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0]) * inv
    dz0, dz1 = z[:, 0] - z[:, 2], z[:, 1] - z[:, 2]  # depth = z2 + w0 dz0 + w1 dz1
    coef[6:9] = dz0 * coef[0:3] + dz1 * coef[3:6]
    coef[8] += z[:, 2]
    top = (np.int64(layer) << (_DEPTH_BITS + _FACE_BITS)) | ids.astype(np.int64)
    lo32, w32 = lo.astype(np.int32), w.astype(np.int32)
    ends = np.cumsum(count)
    cuts = np.searchsorted(ends, np.arange(_BATCH, int(ends[-1]), _BATCH), side="right")
    for f0, f1 in zip(np.r_[0, cuts], np.r_[cuts, keep.size], strict=True):
        if f1 <= f0:
            continue
        n = count[f0:f1]
        face = np.repeat(np.arange(f0, f1, dtype=np.int32), n)
        local = np.arange(face.size, dtype=np.int32) - np.repeat(
            (np.cumsum(n) - n).astype(np.int32), n)
        wf = w32[face]
        row = local // wf
        px = lo32[face, 0] + (local - row * wf)
        py = lo32[face, 1] + row
        x, y = px + 0.5, py + 0.5
        k = [coef[j].take(face) for j in range(6)]
        w0 = k[0] * x + k[1] * y + k[2]
        w1 = k[3] * x + k[4] * y + k[5]
        inside = np.flatnonzero((w0 >= -1e-9) & (w1 >= -1e-9) & (w0 + w1 <= 1.0 + 1e-9))
        x, y, face = x[inside], y[inside], face[inside]
        k = [coef[j].take(face) for j in range(6, 9)]
        depth = np.clip(k[0] * x + k[1] * y + k[2], 0.0, 1.0)
        q = (depth * ((1 << _DEPTH_BITS) - 1)).astype(np.int64) << _FACE_BITS
        np.maximum.at(buf, py[inside] * size + px[inside], top[face] | q)


def _draw_frames(seq: Sequence[np.ndarray], F: np.ndarray, proj: np.ndarray,
                 light: np.ndarray, base: np.ndarray, size: int,
                 box: tuple[float, float, float],
                 ground: tuple[np.ndarray, np.ndarray] | None = None,
                 backdrop: np.ndarray | None = None,
                 facing: np.ndarray | None = None) -> list[Image.Image]:
    """Draw every frame of ``seq`` with a vectorised z-buffer (:func:`_rasterize`).

    Layers, bottom to top: the ground quads (in their order, far first), the backdrop faces,
    every other face by its depth at each pixel.

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
        Faces drawn under all others (what is left of a container: its floor and far walls,
        which lie behind or under the bodies).
    facing : (n_faces,) float64, optional
        :func:`_outward_sign`: faces whose normal times this is turned away from the camera
        are skipped (hidden by their solid's front faces); 0: always drawn.

    Returns
    -------
    list of PIL.Image.Image
        RGB images.
    """
    cu, cv, half = box
    scale = size / (2.0 * half)

    def to_pixels(P2: np.ndarray) -> np.ndarray:  # (u, v) -> (x right, y down) in pixels
        return np.stack([(P2[..., 0] - (cu - half)) * scale,
                         ((cv + half) - P2[..., 1]) * scale], axis=-1)

    n_ground = 0 if ground is None else ground[0].shape[0]
    if F.shape[0] + 2 * n_ground >= 1 << _FACE_BITS:
        raise ValueError(f"render_preview: too many faces ({F.shape[0]}); lower max_faces")
    under = np.zeros(F.shape[0], dtype=bool) if backdrop is None else np.asarray(backdrop)
    face_ids = np.arange(F.shape[0], dtype=np.int64) + 2 * n_ground
    empty = np.full(size * size, -1, dtype=np.int64)
    ground_rgb = np.zeros((2 * n_ground, 3))
    if ground is not None:  # two triangles a quad; depth by the order (far first)
        quads, rgb = ground
        tri = to_pixels(np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]))
        rank = np.tile(np.arange(n_ground) / max(n_ground, 1), 2)
        _rasterize(tri, np.repeat(rank[:, None], 3, axis=1),
                   np.arange(2 * n_ground, dtype=np.int64), 0, empty, size)
        ground_rgb = np.concatenate([rgb, rgb])
    colour = base if base.ndim == 2 else np.broadcast_to(base, (F.shape[0], 3))
    images: list[Image.Image] = []
    for V in seq:
        n = _unit_normals(V[F])
        shade = 0.25 + 0.75 * np.abs(n @ light)
        rgb = np.clip(shade[:, None] * colour, 0.0, 1.0)
        P = V @ proj
        zmin, zmax = float(P[:, 2].min()), float(P[:, 2].max())
        z = (P[F, 2] - zmin) / max(zmax - zmin, 1e-300)
        xy = to_pixels(P[F][:, :, :2])
        seen = np.ones(F.shape[0], dtype=bool) if facing is None else facing * (n @ proj[:, 2]) >= 0
        buf = empty.copy()
        for layer, sel in ((1, under & seen), (2, ~under & seen)):
            if sel.any():
                _rasterize(xy[sel], z[sel], face_ids[sel], layer, buf, size)
        table = np.vstack([ground_rgb, rgb, np.ones((1, 3))])  # the last row: white paper
        # one uint32 per colour: a 1-D gather, ~10x faster than of (n, 3) rows
        packed = np.zeros((table.shape[0], 4), dtype=np.uint8)
        packed[:, :3] = (table * 255.0 + 0.5).astype(np.uint8)
        face = np.where(buf >= 0, buf & ((1 << _FACE_BITS) - 1), table.shape[0] - 1)
        pixels = packed.view(np.uint32).ravel().take(face).view(np.uint8)
        images.append(Image.fromarray(pixels.reshape(size, size, 4)[:, :, :3].copy()))
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
