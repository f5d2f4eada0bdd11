"""From a scene description (:mod:`fem3d.scene.spec`) to arrays: meshes, selections, pulls.

:func:`build_arrays` reads every body's mesh (a tet mesh, or a closed surface tetrahedralized
by :mod:`fem3d.mesh.tetrahedralize`), applies its transform, evaluates its selectors on the
transformed rest positions and concatenates the bodies into one mesh (:class:`SceneArrays`).
It is the first stage of :func:`fem3d.scene.build.build`, which makes the runtime objects
(model, motions, obstacles, contact) from its result; it stands alone because reading a scene
needs it without the physics (:func:`fem3d.scene.load.mesh_scene` measures a mesh by
:func:`rest_positions`).

The built-in scenes are files: ``data/scenes/bunny.toml`` and ``data/scenes/arma.toml`` (the
assignment's two scenes: see their comments). :func:`top_vertex` and :func:`hand_vertex` are
the rules their scripted pulls' vertices were chosen by.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from fem3d.errors import InputError, ParameterError
from fem3d.io.files import check_input_file
from fem3d.mesh.element import ELEMENTS, Element, MixedElements
from fem3d.mesh.formats import read_surface_mesh, read_tet_mesh
from fem3d.mesh.quadratic import has_p2_cells, lift_to_p2, read_p2_mesh
from fem3d.mesh.skin import build_skinning_matrix, check_skin_placement
from fem3d.mesh.tetrahedralize import tetrahedralize_file
from fem3d.physics.constraints import pick_nearest_vertices
from fem3d.physics.springs import Pull
from fem3d.scene.spec import SURFACE_SUFFIXES, BodySpec, Scene, Selector

__all__ = ["SceneArrays", "ElementBlock", "BodyMesh", "ScriptedPull", "build_arrays", "body_mesh",
           "rest_positions", "select_vertices", "transform_points", "rotation_matrix",
           "default_spring_k", "top_vertex", "hand_vertex", "is_surface_file"]


def default_spring_k(E: float, height: float) -> float:
    """``interaction.spring_k`` left out: ``0.15 E h`` (``E`` the first body's Young's
    modulus, ``h`` the extent along y of the rest mesh)."""
    return 0.15 * E * height


def top_vertex(X: np.ndarray) -> int:
    """Index of the vertex with the largest y (ties: lowest index)."""
    return int(np.argmax(X[:, 1]))


def hand_vertex(X: np.ndarray) -> int:
    """The vertex with the largest x among those above mid-height (the armadillo's hand)."""
    y = X[:, 1]
    upper = np.flatnonzero(y > 0.5 * (y.min() + y.max()))
    return int(upper[np.argmax(X[upper, 0])])


def is_surface_file(path: str | os.PathLike[str]) -> bool:
    """Whether a body mesh file is a surface to tetrahedralize (by its suffix)."""
    return Path(path).suffix.lower() in SURFACE_SUFFIXES


# ------------------------------------------------------------------------------ geometry
def rotation_matrix(rotate_deg: Sequence[float]) -> np.ndarray:
    """``Rz Ry Rx`` for angles in degrees about x, y, z, ``(3, 3) float64``."""
    ax, ay, az = (math.radians(float(a)) for a in rotate_deg)
    cx, sx, cy, sy, cz, sz = (math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay),
                              math.cos(az), math.sin(az))
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def transform_points(X: np.ndarray, transform) -> np.ndarray:
    """``R (scale X) + translate`` (:class:`fem3d.scene.spec.TransformSpec`); the identity
    transform returns ``X`` unchanged, bit for bit."""
    X = np.asarray(X, dtype=np.float64)
    s, rot, tr = float(transform.scale), tuple(transform.rotate_deg), tuple(transform.translate)
    out = X
    if s != 1.0:
        out = out * s
    if any(a != 0 for a in rot):
        out = out @ rotation_matrix(rot).T
    if any(c != 0 for c in tr):
        out = out + np.asarray(tr, dtype=np.float64)
    return out


@dataclass(frozen=True, eq=False)
class BodyMesh:
    """One body's meshes in its own (untransformed) frame.

    Attributes
    ----------
    X : (n, 3) float64
        Nodes (P2: the vertices, then the edge nodes).
    T : (m, k) int64
        Elements of the body's ``element`` (a linear mesh lifted to P2 for ``"p2"``).
    skin_V : (k, 3) float64 or None
    skin_F : (f, 3) int64 or None
    path : str
        The tet mesh actually read (for a surface: the cached fTetWild output).
    """

    X: np.ndarray
    T: np.ndarray
    skin_V: np.ndarray | None
    skin_F: np.ndarray | None
    path: str


def _stat_key(p: Path) -> tuple[str, int, int]:
    st = p.stat()
    return (str(p.resolve()), st.st_mtime_ns, st.st_size)


@lru_cache(maxsize=16)
def _read_tet(key: tuple[str, int, int]):
    return read_tet_mesh(key[0])


@lru_cache(maxsize=16)
def _read_surface(key: tuple[str, int, int]):
    return read_surface_mesh(key[0])


def _in_key(scene: Scene, key: str, exc: InputError) -> InputError:
    return scene.error(key, str(exc))


def body_mesh(scene: Scene, i: int) -> BodyMesh:
    """Read (or tetrahedralize, cached) body ``i``'s meshes.

    Raises
    ------
    InputError
        ``FILE: bodies[i].mesh: ...`` naming the mesh file's own problem.
    """
    body: BodySpec = scene.bodies[i]
    path = scene.path(body.mesh)
    key = f"bodies[{i}].mesh"
    if not (path.exists() or path.is_symlink()):
        raise scene.error(key, f"no such file {path}")
    try:  # a FIFO or device (would block), a folder, a symlink loop
        check_input_file(path, "mesh")
    except InputError as exc:
        raise scene.error(key, f"{path}: {exc.reason}") from None
    skin_V = skin_F = None
    quadratic = has_p2_cells(path)
    if quadratic and body.element != "p2":
        raise scene.error(f"bodies[{i}].element", f"{path.name} has 10-node (quadratic) "
                          "tets: set element = \"p2\"")
    try:
        if quadratic:
            X, T = read_p2_mesh(path)
            tet_path = path
        elif is_surface_file(path):
            X, T, tet_path = tetrahedralize_file(
                path, edge_length=body.tetrahedralize.edge_length,
                epsilon=body.tetrahedralize.epsilon,
                stop_quality=body.tetrahedralize.stop_quality)
            skin_V, skin_F = _read_surface(_stat_key(path))
        else:
            mesh = _read_tet(_stat_key(path))
            X, T, tet_path = mesh.X, mesh.T, str(mesh.path)
    except InputError as exc:
        raise _in_key(scene, key, exc) from None
    if body.element == "p2" and T.shape[1] == 4:
        X, T = lift_to_p2(X, T)
    if body.skin is not None:
        skin_path = scene.path(body.skin)
        try:
            skin_V, skin_F = _read_surface(_stat_key(skin_path))
        except FileNotFoundError:
            raise scene.error(f"bodies[{i}].skin", f"no such file {skin_path}") from None
        except InputError as exc:
            raise _in_key(scene, f"bodies[{i}].skin", exc) from None
        try:  # a display mesh in another frame would be skinned into nonsense
            check_skin_placement(skin_V, X, T, path=skin_path)
        except InputError as exc:
            raise _in_key(scene, f"bodies[{i}].skin", exc) from None
    return BodyMesh(X=X, T=T, skin_V=skin_V, skin_F=skin_F, path=str(tet_path))


def rest_positions(scene: Scene, i: int) -> np.ndarray:
    """Body ``i``'s rest positions after its transform, ``(n_i, 3) float64``."""
    return transform_points(body_mesh(scene, i).X, scene.bodies[i].transform)


def _read_ids(path: Path, scene: Scene, key: str) -> np.ndarray:
    try:
        text = path.read_text()
    except OSError as exc:
        raise scene.error(key, f"cannot read {path} ({exc.strerror or exc})") from None
    words = []
    for line in text.splitlines():
        words += line.split("#", 1)[0].replace(",", " ").split()
    try:
        ids = np.array([int(w) for w in words], dtype=np.int64)
    except ValueError:
        raise scene.error(key, f"{path} must hold whitespace-separated vertex ids") from None
    return ids


def select_vertices(scene: Scene, X: np.ndarray, sel: Selector, key: str) -> np.ndarray:
    """Vertices of one body (rest positions ``X (n, 3)``, transformed) chosen by ``sel``.

    Returns
    -------
    (k,) int64
        Sorted, unique, never empty.

    Raises
    ------
    InputError
        ``FILE: key: selects no vertex ...`` or an id out of range.
    """
    n = X.shape[0]
    kind = sel.kind
    if kind == "lowest_y":
        y0 = float(X[:, 1].min())
        ids = np.flatnonzero(X[:, 1] <= y0 + sel.lowest_y.tol)
        info = f"lowest y {y0:.6g}"
    elif kind == "box":
        lo, hi = (np.asarray(b, dtype=np.float64) for b in sel.box)
        ids = np.flatnonzero(((X >= lo) & (X <= hi)).all(axis=1))
        info = "bounding box " + _bbox(X)
    elif kind == "half_space":
        p, nrm = (np.asarray(a, dtype=np.float64) for a in
                  (sel.half_space.point, sel.half_space.normal))
        ids = np.flatnonzero((X - p) @ nrm >= 0)
        info = "bounding box " + _bbox(X)
    elif kind == "sphere":
        c = np.asarray(sel.sphere.center, dtype=np.float64)
        d2 = ((X - c) ** 2).sum(axis=1)
        ids = np.flatnonzero(d2 <= sel.sphere.radius ** 2)
        info = f"the nearest vertex is {math.sqrt(float(d2.min())):.4g} away"
    elif kind in ("vertices", "vertices_file"):
        if kind == "vertices":
            ids = np.asarray(sel.vertices, dtype=np.int64)
        else:
            ids = _read_ids(scene.path(sel.vertices_file), scene, f"{key}.vertices_file")
        bad = ids[(ids < 0) | (ids >= n)]
        if bad.size:
            raise scene.error(f"{key}.{kind}", f"vertex id {int(bad[0])} out of range [0, {n})")
        info = "the list is empty"
    elif kind == "nearest_to":
        nt = sel.nearest_to
        p = np.asarray(nt.point, dtype=np.float64)
        centre = int(np.argmin(((X - p) ** 2).sum(axis=1)))
        ids = pick_nearest_vertices(X, X[centre], nt.radius)
        info = ""
    else:  # near_vertex
        nv = sel.near_vertex
        if nv.vertex >= n:
            raise scene.error(f"{key}.near_vertex.vertex",
                              f"vertex {nv.vertex} out of range [0, {n})")
        ids = pick_nearest_vertices(X, X[nv.vertex], nv.radius)
        info = ""
    ids = np.unique(np.asarray(ids, dtype=np.int64))
    if ids.size == 0:
        raise scene.error(f"{key}.{kind}", f"selects no vertex ({info})")
    return ids


def _bbox(X: np.ndarray) -> str:
    lo, hi = X.min(axis=0), X.max(axis=0)
    return "[" + ", ".join(f"{a:.4g}" for a in lo) + "] - [" + ", ".join(
        f"{b:.4g}" for b in hi) + "]"


@dataclass(frozen=True, eq=False)
class ScriptedPull:
    """A scene's scripted pull (:class:`fem3d.scene.spec.PullSpec`) in numbers: the runtime
    springs and the time window they act in.

    Attributes
    ----------
    pull : fem3d.physics.springs.Pull
        The springs: global vertex ids, targets, one stiffness.
    start, duration : float
        Attached at ``start``, released ``duration`` seconds later.
    """

    pull: Pull
    start: float
    duration: float

    def active(self, t: float, dt: float) -> bool:
        """Whether the pull acts during the step that starts at ``t``."""
        eps = 1e-9 * dt
        return self.start - eps <= t < self.start + self.duration - eps

    @property
    def vertices(self) -> np.ndarray:
        """``(k,) int64`` pulled vertices (:attr:`Pull.vertices`)."""
        return self.pull.vertices

    @property
    def targets(self) -> np.ndarray:
        """``(k, 3) float64`` spring targets (:attr:`Pull.targets`)."""
        return self.pull.targets

    @property
    def k(self) -> float | np.ndarray:
        """Stiffness (:attr:`Pull.k`)."""
        return self.pull.k


@dataclass(frozen=True, eq=False)
class SceneArrays:
    """A scene in arrays (all bodies concatenated).

    Attributes
    ----------
    X : (n, 3) float64
        Rest positions of the nodes (transformed).
    T : (m, k) int64
        Elements of :attr:`element`.
    v0 : (n, 3) float64
        Initial velocities (linear + angular about each body's vertex centroid).
    fixed : (n_fixed,) int64
        Pinned vertices (sorted): those with a fixed DOF.
    pulls : list of ScriptedPull
    body_vertices, body_tets : list of slice
        Each body's range of vertices / tets.
    skin_V : (k, 3) float64 or None
        Display mesh (rest), None when no body has a skin (then the display is the tet
        mesh's boundary).
    skin_F : (f, 3) int64 or None
    skin_bodies : list of (slice, slice)
        Each body's range of display vertices and faces.
    skin_identity : list of bool
        Bodies whose display vertices are their simulation vertices (no skin of their own).
    pick_radius, spring_k, height : float
        Resolved interaction values (``spring_k`` None when it defaults to ``0.15 E h`` and
        the first body gives no ``E``: :func:`fem3d.scene.build.build` takes the model's);
        ``height`` the extent along y of the rest mesh.
    mesh_paths : list of str
    fixed_dofs : (k,) int64 or None
        The fixed DOFs (``3 vertex + axis``, sorted; a pin's ``dofs``); None: every DOF of
        :attr:`fixed`.
    element : Element
        The finite element of every body (``bodies[].element``).
    blocks : tuple of ElementBlock
        The elements by block: each run of consecutive bodies on one element (one block, all
        of :attr:`T`, when every body has the same element). When the bodies mix elements,
        :attr:`T` and :attr:`element` are :class:`~fem3d.mesh.element.MixedElements`, which
        raise on any use.
    """

    X: np.ndarray
    T: np.ndarray
    v0: np.ndarray
    fixed: np.ndarray
    pulls: list[ScriptedPull]
    body_vertices: list[slice]
    body_tets: list[slice]
    skin_V: np.ndarray | None
    skin_F: np.ndarray | None
    skin_bodies: list[tuple[slice, slice]]
    skin_identity: list[bool]
    pick_radius: float
    spring_k: float | None
    height: float
    mesh_paths: list[str] = field(default_factory=list)
    fixed_dofs: np.ndarray | None = None
    element: Element = ELEMENTS["p1"]
    blocks: tuple[ElementBlock, ...] = ()

    @property
    def is_mixed(self) -> bool:
        """Whether the bodies mix elements."""
        return len(self.blocks) > 1

    def surface_triangles(self) -> np.ndarray:
        """``(f, 3) int64`` the linear triangles of the boundary of every block (the display
        surface, the collision mesh: :meth:`Element.surface_triangles`)."""
        tris = [b.element.surface_triangles(b.T) for b in self.blocks]
        return tris[0] if len(tris) == 1 else np.concatenate(tris)

    def body_elements(self, i: int) -> np.ndarray:
        """``(m_i, k) int64`` body ``i``'s elements, in the scene's node numbering."""
        b = next(b for b in self.blocks if i in b.bodies)
        s = self.body_tets[i]
        return b.T[s.start - b.tets.start:s.stop - b.tets.start]

    def body_element(self, i: int) -> Element:
        """The element of body ``i``."""
        return next(b.element for b in self.blocks if i in b.bodies)

    def skinning_matrix(self) -> sp.csr_matrix | None:
        """``(k, n)`` the display vertices from the simulation's (``W @ q``): each body's
        skin bound to its elements (:func:`fem3d.mesh.skin.build_skinning_matrix`), the
        identity for a body shown as itself; None without a skin."""
        if self.skin_V is None:
            return None
        blocks = []
        for i, (vs, _) in enumerate(self.skin_bodies):
            bv = self.body_vertices[i]
            if self.skin_identity[i]:
                blocks.append(sp.identity(bv.stop - bv.start, format="csr"))
            else:
                blocks.append(build_skinning_matrix(self.X[bv], self.body_elements(i) - bv.start,
                                                    self.skin_V[vs],
                                                    element=self.body_element(i)))
        return blocks[0] if len(blocks) == 1 else sp.block_diag(blocks, format="csr")


@dataclass(frozen=True, eq=False)
class ElementBlock:
    """The elements of a run of consecutive bodies on one finite element.

    Attributes
    ----------
    element : Element
    T : (m_b, k) int64
        The block's elements, in the scene's node numbering.
    tets : slice
        Their range in the scene's element order (the bodies' :attr:`SceneArrays.body_tets`).
    bodies : range
        The bodies of the block.
    """

    element: Element
    T: np.ndarray
    tets: slice
    bodies: range


def _surface_of(T: np.ndarray, n: int, element: Element) -> tuple[np.ndarray, np.ndarray]:
    return np.arange(n), element.surface_triangles(T)


def _element_blocks(scene: Scene, Ts: list[np.ndarray],
                    body_t: list[slice]) -> tuple[ElementBlock, ...]:
    """Consecutive bodies on one element, each run one block (its ``T`` concatenated)."""
    runs: list[list[int]] = []
    for i, body in enumerate(scene.bodies):
        if runs and scene.bodies[runs[-1][0]].element == body.element:
            runs[-1].append(i)
        else:
            runs.append([i])
    blocks = []
    for run in runs:
        T = Ts[run[0]] if len(run) == 1 else np.concatenate([Ts[i] for i in run])
        blocks.append(ElementBlock(ELEMENTS[scene.bodies[run[0]].element], T,
                                   slice(body_t[run[0]].start, body_t[run[-1]].stop),
                                   range(run[0], run[-1] + 1)))
    return tuple(blocks)


def build_arrays(scene: Scene) -> SceneArrays:
    """Every body's mesh, selection and pull of ``scene`` in numbers.

    Raises
    ------
    InputError
        ``FILE: key.path: ...`` for a missing or bad mesh, a selector that selects nothing,
        a vertex id out of range.
    """
    Xs, Ts, v0s, fixed, skins = [], [], [], [], []
    body_v, body_t = [], []
    nv = nt = 0
    meshes = []
    for i, body in enumerate(scene.bodies):
        bm = body_mesh(scene, i)
        meshes.append(bm)
        X = transform_points(bm.X, body.transform)
        T = np.asarray(bm.T, dtype=np.int64)
        v = np.broadcast_to(np.asarray(body.velocity, dtype=np.float64), X.shape).copy()
        if any(w != 0 for w in body.angular_velocity):
            w = np.asarray(body.angular_velocity, dtype=np.float64)
            v += np.cross(w, X - X.mean(axis=0))
        for j, pin in enumerate(body.pins):
            ids = select_vertices(scene, X, pin.select, f"bodies[{i}].pins[{j}].select")
            fixed.append((3 * (ids + nv)[:, None] + np.array(pin.axes)).reshape(-1))
        skin = None
        if bm.skin_V is not None:
            skin = (transform_points(bm.skin_V, body.transform),
                    np.asarray(bm.skin_F, dtype=np.int64))
        skins.append(skin)
        Xs.append(X)
        Ts.append(T if nv == 0 else T + nv)  # the first body's: the mesh's (read-only) array
        v0s.append(v)
        body_v.append(slice(nv, nv + X.shape[0]))
        body_t.append(slice(nt, nt + T.shape[0]))
        nv += X.shape[0]
        nt += T.shape[0]
    X = Xs[0] if len(Xs) == 1 else np.concatenate(Xs)
    blocks = _element_blocks(scene, Ts, body_t)
    if len(blocks) == 1:
        T, element = blocks[0].T, blocks[0].element
    else:
        names = dict.fromkeys(b.element.name for b in blocks)
        T, element = MixedElements("arrays.T", names), MixedElements("arrays.element", names)
    v0 = np.concatenate(v0s)
    fixed_dofs = (np.unique(np.concatenate(fixed)) if fixed else np.zeros(0, np.int64))
    fixed_ids = np.unique(fixed_dofs // 3)
    height = float(X[:, 1].max() - X[:, 1].min())

    # display mesh: bodies' skins, or (for a body without one) its own boundary
    skin_V = skin_F = None
    skin_bodies: list[tuple[slice, slice]] = []
    identity = [s is None for s in skins]
    if not all(identity):
        Vs, Fs = [], []
        kv = kf = 0
        for i, s in enumerate(skins):
            if s is None:
                idx, F = _surface_of(Ts[i] - body_v[i].start, Xs[i].shape[0],
                                     ELEMENTS[scene.bodies[i].element])
                s = (Xs[i][idx], F)
            Vs.append(s[0])
            Fs.append(s[1] + kv)
            skin_bodies.append((slice(kv, kv + s[0].shape[0]), slice(kf, kf + s[1].shape[0])))
            kv += s[0].shape[0]
            kf += s[1].shape[0]
        skin_V = Vs[0] if len(Vs) == 1 else np.concatenate(Vs)
        skin_F = Fs[0] if len(Fs) == 1 else np.concatenate(Fs)
    else:
        skin_bodies = [(body_v[i], body_t[i]) for i in range(len(Xs))]

    E0 = scene.bodies[0].material.E
    pick_radius = scene.interaction.pick_radius
    if pick_radius is None:
        pick_radius = 0.01 * height
    spring_k = scene.interaction.spring_k
    if spring_k is None and E0 is not None:
        spring_k = default_spring_k(E0, height)
        if not spring_k > 0:
            raise scene.error("interaction.spring_k", "the mesh has no height to derive it")

    pulls = []
    for j, p in enumerate(scene.pulls):
        Xb = Xs[p.body]
        ids = select_vertices(scene, Xb, p.select, f"pulls[{j}].select")
        if p.offset is not None:
            off = np.asarray(p.offset, dtype=np.float64)
        else:
            off = np.asarray(p.target, dtype=np.float64) - Xb[ids].mean(axis=0)
        if p.stiffness is None and spring_k is None:
            raise scene.error(f"pulls[{j}].stiffness", "give it (interaction.spring_k, its "
                              "default, is 0.15 E h and bodies[0] has no E)")
        try:
            springs = Pull.make(ids + body_v[p.body].start, Xb[ids] + off,
                                float(spring_k if p.stiffness is None else p.stiffness),
                                X.shape[0])
        except ParameterError as exc:
            raise scene.error(f"pulls[{j}]", str(exc)) from None
        pulls.append(ScriptedPull(springs, start=float(p.start), duration=float(p.duration)))
    return SceneArrays(
        X=X, T=T, v0=v0, fixed=fixed_ids, pulls=pulls, body_vertices=body_v, body_tets=body_t,
        skin_V=skin_V, skin_F=skin_F, skin_bodies=skin_bodies, skin_identity=identity,
        pick_radius=float(pick_radius), spring_k=None if spring_k is None else float(spring_k),
        height=height,
        mesh_paths=[m.path for m in meshes], fixed_dofs=fixed_dofs, element=element,
        blocks=blocks,
    )
