"""Finite elements as objects: what an element owns, asked for by everything above the mesh.

An :class:`Element` knows its nodes per element and their layout (corners first, then edge
nodes), its shape functions in barycentric coordinates (skinning, picking), the generated
kernel modules behind it (rest shape, mass, material energies), its faces and the linear
triangles that draw or collide its surface, and its cell type in VTU files. Assembly, the
sparsity pattern, the mass matrix, skinning, outputs and contact take an element and never
assume four nodes; a new element is one class here plus one line in :data:`ELEMENTS`.

Node layout of every tetrahedral element: the four corners ``0..3`` (positively oriented),
then the nodes of :data:`TET_EDGES` (VTK's and meshio's ``tetra10`` order: edges ``01, 12,
02, 03, 13, 23``). A face's nodes are its three corners (outward right-hand order, as in
:data:`fem3d.mesh.tetmesh.TET_FACES`) then its edges ``ab, bc, ca``.
"""

from __future__ import annotations

import numpy as np

from fem3d.kernels.backend import resolve_backend
from fem3d.kernels.dispatch import kernel_module
from fem3d.mesh.tetmesh import TET_FACES, boundary_face_index, boundary_faces

__all__ = ["ELEMENTS", "Element", "MixedElementError", "MixedElements", "P1Tet", "P2Tet",
           "TET_EDGES", "element", "element_names"]

#: Corner pairs of a tet's six edges, in the order of the edge nodes ``4..9`` of a P2 tet.
TET_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]], dtype=np.int64)


def _edge_node(a: int, b: int) -> int:
    """Local node (4..9) on the edge of corners ``a, b``."""
    pair = sorted((a, b))
    return 4 + next(i for i, e in enumerate(TET_EDGES.tolist()) if e == pair)


class Element:
    """A tetrahedral Lagrange element (subclassed per order).

    Attributes
    ----------
    name : str
        Registry name (``"p1"``, ``"p2"``): the scene's ``bodies[i].element``.
    order : int
        Polynomial degree of the shape functions.
    n_nodes : int
        Nodes per element (4, 10).
    cell_type : str
        meshio's cell type (``"tetra"``, ``"tetra10"``).
    vtk_type : int
        VTK's cell type (10 ``VTK_TETRA``, 24 ``VTK_QUADRATIC_TETRA``).
    face_nodes : (4, n_face_nodes) int64
        Local nodes of each face, corners first (outward orientation).
    face_triangles : (t, 3) int64
        The linear triangles of one face, as indices into a row of :attr:`face_nodes`,
        oriented like the face.
    geometry_module : str
        Generated kernel module of the rest shape and the mass matrix.
    material_prefix : str
        Prefix of the generated material modules on this element (``""``: ``neo_hookean``;
        ``"p2_"``: ``p2_neo_hookean``, quadrature kernels over the element's points).
    """

    name: str = ""
    order: int = 0
    n_nodes: int = 0
    cell_type: str = ""
    vtk_type: int = 0
    face_nodes: np.ndarray = np.zeros((0, 0), dtype=np.int64)
    face_triangles: np.ndarray = np.zeros((0, 3), dtype=np.int64)
    geometry_module: str = ""
    material_prefix: str = ""

    def __repr__(self) -> str:
        return f"<element {self.name}: {self.n_nodes}-node tetrahedron>"

    @property
    def n_dofs(self) -> int:
        """DOFs per element, ``3 n_nodes``."""
        return 3 * self.n_nodes

    @property
    def n_entries(self) -> int:
        """Entries of an element matrix, ``n_dofs ** 2``."""
        return self.n_dofs * self.n_dofs

    def corners(self, T: np.ndarray) -> np.ndarray:
        """The corner nodes ``(m, 4)`` of elements ``T (m, n_nodes)`` (a view)."""
        return np.asarray(T)[:, :4]

    def element_dofs(self, T: np.ndarray) -> np.ndarray:
        """Global DOFs of each element's nodes, node-major.

        Parameters
        ----------
        T : (m, n_nodes) int

        Returns
        -------
        (m, 3 n_nodes) int64
            ``[3 T[e,0], 3 T[e,0]+1, 3 T[e,0]+2, 3 T[e,1], ...]``.
        """
        T = np.asarray(T, dtype=np.int64)
        return (3 * T[:, :, None] + np.arange(3)).reshape(-1, self.n_dofs)

    def check_connectivity(self, T: np.ndarray) -> str | None:
        """What is wrong with the shape of ``T`` for this element, or None."""
        if T.ndim != 2 or T.shape[1] != self.n_nodes or T.shape[0] < 1:
            return (f"elements must have shape (m >= 1, {self.n_nodes}) for element "
                    f"{self.name!r}, got {T.shape}")
        return None

    def boundary_faces(self, T: np.ndarray) -> np.ndarray:
        """The faces only one element has, outward, with all their nodes.

        Parameters
        ----------
        T : (m, n_nodes) int64

        Returns
        -------
        (f, n_face_nodes) int64
            Corners first (right-hand normal outward), in the order of the elements.
        """
        T = np.asarray(T, dtype=np.int64)
        if self.n_nodes == 4:
            return boundary_faces(T)
        tet, face = boundary_face_index(T)
        return np.ascontiguousarray(T[tet[:, None], self.face_nodes[face]])

    def surface_triangles(self, T: np.ndarray) -> np.ndarray:
        """Linear triangles through the boundary faces' nodes (display, contact).

        Parameters
        ----------
        T : (m, n_nodes) int64

        Returns
        -------
        (t, 3) int64
            Each boundary face split into :attr:`face_triangles` (one per face for P1: the
            faces themselves), outward.
        """
        faces = self.boundary_faces(T)
        if self.face_triangles.shape[0] == 1:
            return faces
        return np.ascontiguousarray(faces[:, self.face_triangles].reshape(-1, 3))

    def shape_values(self, lam: np.ndarray) -> np.ndarray:
        """Shape functions at points given by their barycentric coordinates.

        Parameters
        ----------
        lam : (..., 4) float64
            Barycentric coordinates with respect to the element's corners.

        Returns
        -------
        (..., n_nodes) float64
            Sums to one; exact for every polynomial of degree :attr:`order` (straight-sided
            elements).
        """
        raise NotImplementedError

    def geometry(self, backend: str | None = None):
        """The generated geometry kernels (``rest_shape``, ``mass_matrix``, ...)."""
        return kernel_module(self.geometry_module, resolve_backend(backend))

    def material_kernels(self, material: str, backend: str | None = None):
        """The generated kernels of ``material`` on this element (``energy``, ``gradient``,
        ``hessian``, ... taking ``(x_e, dphi_dX, vol, *inputs, params)``)."""
        return kernel_module(self.material_prefix + material, resolve_backend(backend))

    def rest_shape(self, geo, X_e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The rest-shape arrays the material kernels take, from the geometry kernels.

        Parameters
        ----------
        geo : KernelModule
            :meth:`geometry`.
        X_e : (m, n_nodes, 3) float64
            Rest node positions.

        Returns
        -------
        dphi_dX : float64
            Shape-function gradients (P1 ``(m, 4, 3)``; P2 ``(m, nq, 10, 3)``, per quadrature
            point).
        vol : float64
            Volume weights (P1: the volumes ``(m,)``; P2: ``weight * det J`` per point,
            ``(m, nq)``; all positive for a valid element).
        """
        return geo.rest_shape(X_e)

    def volumes(self, vol: np.ndarray) -> np.ndarray:
        """Element volumes ``(m,)`` from :meth:`rest_shape`'s ``vol``."""
        return vol

    def mass_matrices(self, geo, X: np.ndarray, T: np.ndarray, volumes: np.ndarray,
                      rho: float, rho_e: np.ndarray | None, a: int, b: int) -> np.ndarray:
        """The consistent mass matrices of elements ``a .. b - 1``: the generated
        ``mass_matrix`` of their volumes (exact where the map from the reference tet is
        affine). M is linear in rho: a per-element density scales the element's volume.

        Parameters
        ----------
        geo : KernelModule
            :meth:`geometry`.
        X : (n, 3) float64
            Rest node positions.
        T : (m, n_nodes) int64
        volumes : (m,) float64
            :meth:`volumes`.
        rho : float
            Density (used when ``rho_e`` is None).
        rho_e : (m,) float64 or None
            Per-element density.
        a, b : int
            The elements' range.

        Returns
        -------
        (b - a, 3 n_nodes, 3 n_nodes) float64
        """
        if rho_e is None:
            return geo.mass_matrix(volumes[a:b], (rho,))
        return geo.mass_matrix(volumes[a:b] * rho_e[a:b], (1.0,))

    def deformed_volumes(self, geo, q: np.ndarray, T: np.ndarray, dphi_dX: np.ndarray,
                         slots: np.ndarray) -> np.ndarray:
        """The inversion measure of every element at positions ``q`` (the line search's
        guard): positive when the element is not inverted anywhere.

        Parameters
        ----------
        geo : KernelModule
            :meth:`geometry`.
        q : (n, 3) or (3n,) float64
        T : (m, n_nodes) int64
        dphi_dX : float64
            :meth:`rest_shape`'s gradients.
        slots : (m,) int32
            ``0 .. m - 1`` (the fused kernel's map).

        Returns
        -------
        (m,) float64
            P1: the signed deformed volumes, ``det([x1-x0, x2-x0, x3-x0]) / 6`` (generated
            ``tet.deformed_volume``).
        """
        if geo.has_assemble("deformed_volume"):  # C: gather and evaluate in one pass
            out = np.zeros(T.shape[0])
            return geo.deformed_volume_assemble(q, T, (), slots, out)
        return geo.deformed_volume(_gather(q, T))


class P1Tet(Element):
    """The linear tetrahedron: 4 corner nodes, barycentric shape functions, one quadrature
    point (F is constant per element), lumpable 12 x 12 consistent mass."""

    name = "p1"
    order = 1
    n_nodes = 4
    cell_type = "tetra"
    vtk_type = 10
    face_nodes = TET_FACES
    face_triangles = np.array([[0, 1, 2]], dtype=np.int64)
    geometry_module = "tet"

    def shape_values(self, lam: np.ndarray) -> np.ndarray:
        """The barycentric coordinates themselves (``lam``, not copied)."""
        return lam


def _gather(q: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``q[T]``: ``(m, n_nodes, 3)`` node positions of every element."""
    return np.take(np.asarray(q, dtype=np.float64).reshape(-1, 3), T, axis=0)


def _p2_face_nodes() -> np.ndarray:
    rows = []
    for a, b, c in TET_FACES.tolist():
        rows.append([a, b, c, _edge_node(a, b), _edge_node(b, c), _edge_node(c, a)])
    return np.array(rows, dtype=np.int64)


class P2Tet(Element):
    """The quadratic tetrahedron: 4 corners and 6 edge nodes (:data:`TET_EDGES`), shape
    functions ``l_i (2 l_i - 1)`` at the corners and ``4 l_a l_b`` on the edges; each face's
    6 nodes draw and collide as 4 linear triangles (corner, edge, edge ... and the middle
    one of the three edge nodes)."""

    name = "p2"
    order = 2
    n_nodes = 10
    cell_type = "tetra10"
    vtk_type = 24
    face_nodes = _p2_face_nodes()
    face_triangles = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]], dtype=np.int64)
    geometry_module = "p2_tet"
    material_prefix = "p2_"

    def rest_shape(self, geo, X_e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(dN_dX (m, nq, 10, 3), w_detJ (m, nq))`` of the generated ``p2_tet.rest_shape``."""
        dN_dX, _, w_detJ = geo.rest_shape(X_e)
        return dN_dX, w_detJ

    def volumes(self, vol: np.ndarray) -> np.ndarray:
        """``sum_q w_q det J_q``: the element volumes ``(m,)``."""
        return vol.sum(axis=1)

    def mass_matrices(self, geo, X: np.ndarray, T: np.ndarray, volumes: np.ndarray,
                      rho: float, rho_e: np.ndarray | None, a: int, b: int) -> np.ndarray:
        """:meth:`Element.mass_matrices`: straight-edged elements (each edge node at its
        edge's midpoint, as :func:`fem3d.mesh.quadratic.lift_to_p2` puts it) from their
        volume, any other from the generated ``curved_mass_matrix`` (``det J``, a cubic
        there, interpolated exactly: no quadrature error)."""
        blocks = super().mass_matrices(geo, X, T, volumes, rho, rho_e, a, b)
        X_e = _gather(X, T[a:b])
        midpoints = 0.5 * (X_e[:, TET_EDGES[:, 0]] + X_e[:, TET_EDGES[:, 1]])
        curved = np.flatnonzero((X_e[:, 4:] != midpoints).any(axis=(1, 2)))
        if curved.size:
            params = (rho,) if rho_e is None else rho_e[a:b][curved, None]
            blocks[curved] = geo.curved_mass_matrix(X_e[curved], params)
        return blocks

    def deformed_volumes(self, geo, q: np.ndarray, T: np.ndarray, dphi_dX: np.ndarray,
                         slots: np.ndarray) -> np.ndarray:
        """The smallest ``det F`` over the quadrature points (generated
        ``p2_tet.deformation_jacobian``), ``(m,)``: positive when no point is inverted."""
        return geo.deformation_jacobian(_gather(q, T), dphi_dX).min(axis=1)

    def shape_values(self, lam: np.ndarray) -> np.ndarray:
        """``l_i (2 l_i - 1)`` (corners), ``4 l_a l_b`` (edge ``ab``), ``(..., 10)``."""
        lam = np.asarray(lam, dtype=np.float64)
        corner = lam * (2.0 * lam - 1.0)
        edge = 4.0 * lam[..., TET_EDGES[:, 0]] * lam[..., TET_EDGES[:, 1]]
        return np.concatenate([corner, edge], axis=-1)


#: The elements by name: the scene's ``bodies[i].element`` choices.
ELEMENTS: dict[str, Element] = {e.name: e for e in (P1Tet(), P2Tet())}


def element_names() -> tuple[str, ...]:
    """Names of the registered elements."""
    return tuple(ELEMENTS)


def element(name: str | Element) -> Element:
    """The registered element ``name`` (an :class:`Element` is returned as it is).

    Raises
    ------
    ValueError
        Unknown name (the message lists the available ones).
    """
    if isinstance(name, Element):
        return name
    try:
        return ELEMENTS[name]
    except KeyError:
        raise ValueError(f"unknown element {name!r}; available: "
                         f"{', '.join(ELEMENTS)}") from None


class MixedElementError(TypeError):
    """An element-shaped attribute (``T``, ``element``, ``dphi_dX``, ...) of a model or of scene
    arrays whose bodies mix elements was used as if there were one element."""


class MixedElements:
    """Stands in for an element-shaped attribute of a model or of scene arrays whose bodies
    mix elements (P1 and P2): the elements are in blocks, one per element kind, and any use
    of this stand-in (an attribute, an index, a conversion to an array, a length, a truth
    value) raises :class:`MixedElementError` naming the attribute. Code that handles mixed
    elements iterates the blocks (``model.element_blocks()``, ``arrays.blocks``); code that
    does not fails loudly here instead of computing with the wrong element.

    Parameters
    ----------
    what : str
        The attribute (``"model.T"``).
    names : sequence of str
        The elements of the blocks (``("p1", "p2")``).
    """

    __slots__ = ("_what", "_names")

    def __init__(self, what: str, names) -> None:
        object.__setattr__(self, "_what", what)
        object.__setattr__(self, "_names", tuple(names))

    def _fail(self, *_args, **_kwargs):
        raise MixedElementError(
            f"{self._what}: the bodies mix elements ({', '.join(self._names)}), so there is "
            "no single one; iterate the element blocks (model.element_blocks(), "
            "arrays.blocks)")

    def __getattr__(self, name: str):
        self._fail()

    __getitem__ = __len__ = __iter__ = __bool__ = __array__ = __call__ = _fail
    __add__ = __radd__ = __sub__ = __mul__ = __rmul__ = _fail

    def __repr__(self) -> str:
        return f"<mixed elements {'+'.join(self._names)}: {self._what}>"
