"""One MPI rank's share of a scene: what rank 0 cuts from the whole scene for each rank
(:func:`read_whole`, :func:`cut_share`: a :class:`SharePart` of plain data, sent to the rank),
and the rank's share built from its part (:func:`build_share`, instead of
:func:`fem3d.scene.build.build`): its model and loads over the vertices of its own tets.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np

from fem3d.errors import InputError
from fem3d.physics.constraints import Constraints
from fem3d.physics.model import Model
from fem3d.scene.arrays import SceneArrays, build_arrays
from fem3d.scene.build import (
    Built,
    ModelInputs,
    PinMotion,
    SelectedLoad,
    _built,
    _constraints,
    _loads,
    _material_groups,
    _simple_material,
    check_static_support,
    damping_from_scene,
    loads_of,
    model_inputs,
    model_of,
    pin_groups,
    pin_motions,
    refuse_mixed_elements,
    select_loads,
    surface_load_specs,
    with_psd_projection,
)
from fem3d.scene.local import LocalNumbering
from fem3d.scene.spec import Scene

__all__ = ["Share", "WholeScene", "SharePart", "read_whole", "cut_share", "build_share"]


class Share(Protocol):
    """A share of the tets (one MPI rank's, :class:`fem3d.parallel.run.RankShare`) that
    :func:`build_share` makes the model of, instead of the whole, over the vertices of its
    tets alone (:class:`~fem3d.scene.local.LocalNumbering`), from its :class:`SharePart`."""

    def part(self, read: Callable[[], WholeScene],
             cut: Callable[[WholeScene, np.ndarray, np.ndarray, int], SharePart]) -> SharePart:
        """Collective: this share's part of the scene. The share that reads calls ``read``,
        partitions the tets, and cuts each share's part (``cut(whole, tets, owner, rank)``:
        the share's sorted tets, each vertex's owning share) and hands it over; an
        :class:`InputError` it meets is raised by every share."""

    def hold(self, numbering: LocalNumbering, constraints: Constraints) -> None:
        """Collective: the share holds the vertices of ``numbering`` and the local
        ``constraints``' free DOFs (each vertex owned by exactly one share)."""

    def summary(self, model: Model) -> Model:
        """``model`` (the share's) with the whole model's summary ``E, nu, rho``."""

    def agree(self, failure: str) -> None:
        """Raise :class:`InputError` on every share when any share's ``failure`` (its
        message; ``""``: none) is not empty."""


class WholeScene(NamedTuple):
    """The whole scene in arrays and what is selected on it once (the share that reads it
    cuts every share's :class:`SharePart` from it)."""

    arrays: SceneArrays
    constraints: Constraints
    groups: tuple[list, np.ndarray] | None  # material groups and densities (None: one plain body)
    alpha: float | np.ndarray
    beta: float | np.ndarray
    motions: list[PinMotion]
    pin_groups: tuple
    loads: list[SelectedLoad]


@dataclass(frozen=True, eq=False)
class SharePart:
    """One MPI rank's part of a scene in its own numbering, cut by the rank that reads the
    scene (:func:`cut_share`; plain data, sent to the rank): what :func:`build` makes the
    rank's share of.

    Attributes
    ----------
    numbering : LocalNumbering
    arrays : SceneArrays
        :meth:`LocalNumbering.arrays`.
    fixed_dofs : (k,) int64
        The held DOFs, local numbers.
    inputs : ModelInputs
    alpha, beta : float or ndarray
        Rayleigh coefficients (per local vertex / per tet of the share).
    damps : bool
        Whether the scene damps anywhere (every share keeps the damping term then).
    loads : list of LoadSpec
    motions : list of PinMotion
        Slots among the share's pinned vertices.
    pin_groups : tuple
        Each pin's key and its DOFs on the vertices this rank owns (local numbers).
    """

    numbering: LocalNumbering
    arrays: SceneArrays
    fixed_dofs: np.ndarray
    inputs: ModelInputs
    alpha: float | np.ndarray
    beta: float | np.ndarray
    damps: bool
    loads: list
    motions: list
    pin_groups: tuple


def read_whole(scene: Scene, backend: str | None = None) -> WholeScene:
    """The whole scene in arrays, checked, with what :func:`cut_share` selects once.

    Raises
    ------
    InputError
        As :func:`build`.
    """
    a = build_arrays(scene)
    whole = _constraints(scene, a)
    check_static_support(scene, a, whole)
    simple = len(scene.bodies) == 1 and _simple_material(scene.bodies[0].material)
    alpha, beta = damping_from_scene(scene, a)
    return WholeScene(a, whole, None if simple else _material_groups(scene, a), alpha, beta,
                      pin_motions(scene, a, whole.fixed_vertices), pin_groups(scene, a),
                      select_loads(scene, a, backend))


def cut_share(scene: Scene, whole: WholeScene, backend: str | None, tets: np.ndarray,
              owner: np.ndarray, rank: int) -> SharePart:
    """Share ``rank``'s part of ``whole``: its tets ``tets`` (sorted) over their vertices,
    ``owner`` each scene vertex's owning share.

    Raises
    ------
    InputError
        A load that selects no whole boundary face, or a follower pressure on an open patch
        (the checks see the whole load).
    """
    a = whole.arrays
    numbering = LocalNumbering.of_tets(a.T, tets)
    owned = owner[numbering.vertices] == rank
    fixed = numbering.dof_ids(whole.constraints.fixed_dofs)
    local_fixed = np.unique(fixed // 3)
    slots = numbering.fixed_slots(whole.constraints.fixed_vertices, local_fixed)
    motions = []
    for m in whole.motions:
        held = slots[m.slots] >= 0
        if held.any():
            motions.append(PinMotion(slots[m.slots][held], m.rest[held], m.keyframes))
    alpha, beta = whole.alpha, whole.beta
    return SharePart(
        numbering=numbering, arrays=numbering.arrays(a, owned), fixed_dofs=fixed,
        inputs=model_inputs(scene, a, numbering, whole.groups),
        alpha=alpha if np.ndim(alpha) == 0 else alpha[numbering.vertices],
        beta=beta if np.ndim(beta) == 0 else beta[tets],
        damps=bool(np.any(np.asarray(alpha) != 0) or np.any(np.asarray(beta) != 0)),
        loads=surface_load_specs(scene, a, backend, numbering, owner == rank, whole.loads),
        motions=motions,
        pin_groups=tuple((key, _owned_dofs(numbering.dof_ids(d), owned))
                         for key, d in whole.pin_groups))


def _owned_dofs(dofs: np.ndarray, owned: np.ndarray) -> np.ndarray:
    """The local DOFs ``dofs`` of vertices this rank owns (``owned``: per local vertex): a
    pin's reaction counts each DOF once, on its owner."""
    return dofs[owned[dofs // 3]]


def build_share(scene: Scene, backend: str | None, share: Share) -> Built:
    """:func:`build` of one MPI rank's share: its :class:`SharePart` (cut by the rank that
    reads the scene), its model and loads built here."""
    refuse_mixed_elements(scene, "mpiexec runs")
    part = share.part(lambda: read_whole(scene, backend),
                      lambda whole, tets, owner, rank: cut_share(scene, whole, backend, tets,
                                                                 owner, rank))
    # a share's own checks (its elements' Jacobians) may fail on one rank alone: every
    # rank learns of it before the next collective call, which would otherwise wait
    try:
        model, failure = model_of(scene, part.inputs, backend), ""
    except InputError as exc:
        model, failure = None, str(exc)
    share.agree(failure)
    model = with_psd_projection(share.summary(model), scene.simulation.psd_projection)
    constraints = Constraints.from_fixed_dofs(model.X, part.fixed_dofs)
    share.hold(part.numbering, constraints)
    loads = _loads(scene, model, part.alpha, part.beta, loads_of(model, part.loads),
                   part.damps)
    return _built(scene, part.arrays, model, constraints, part.alpha, part.beta, loads,
                  part.motions, part.pin_groups)
