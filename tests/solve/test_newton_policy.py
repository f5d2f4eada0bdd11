"""Newton policy as one object (:class:`fem3d.physics.terms.base.NewtonPolicy`): what a term
asks of the minimiser, combined over the step's active terms; IPC contact's barrier sets it
from the scene's ``contact.newton_start`` and ``contact.first_step``."""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.physics.contact import ContactModel, PlaneObstacle
from fem3d.physics.terms.base import NewtonPolicy, Term, TermGroup
from fem3d.physics.terms.contact import ContactTerm
from fem3d.solve.schemes.newmark import CONTACT_ALPHA, newmark_gamma

TET_X = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
TET_T = np.array([[0, 1, 2, 3]])


class _Stiff(Term):
    """A position term that asks for the stiff treatment, active or not."""

    newton_policy = NewtonPolicy(stiff=True)

    def __init__(self, active: bool) -> None:
        self._active = active

    @property
    def active(self) -> bool:
        return self._active


def contact_term(**keys) -> ContactTerm:
    cm = ContactModel(TET_X, TET_T, planes=[PlaneObstacle([0, -1, 0], [0, 1, 0])], dhat=1e-3)
    return ContactTerm(cm, **keys)


def test_combine_turns_a_field_on_when_any_policy_has_it():
    assert NewtonPolicy.combine([]) == NewtonPolicy()
    combined = NewtonPolicy.combine([NewtonPolicy(stiff=True), NewtonPolicy(),
                                     NewtonPolicy(accept_first_step=True)])
    assert combined == NewtonPolicy(stiff=True, restart_when_clamped=False,
                                    accept_first_step=True)
    group = TermGroup([_Stiff(True), Term()])
    assert group.newton_policy == NewtonPolicy(stiff=True)
    assert Term().newton_policy == NewtonPolicy()


@pytest.mark.parametrize("newton_start, first_step", [("clamped", "confirm"), ("q_t", "accept"),
                                                      ("q_t", "confirm")])
def test_the_contact_term_sets_its_policy_from_the_scene_keys(newton_start, first_step):
    term = contact_term(newton_start=newton_start, first_step=first_step)
    want = NewtonPolicy(stiff=True, restart_when_clamped=newton_start == "q_t",
                        accept_first_step=first_step == "accept")
    assert term.barrier.newton_policy == want
    assert term.newton_policy == want  # the group the objective sees
    assert term.friction.newton_policy == NewtonPolicy()


def test_newmark_damps_only_while_a_stiff_term_is_active():
    assert newmark_gamma([contact_term()]) == 0.5 + CONTACT_ALPHA
    assert newmark_gamma([_Stiff(True)]) == 0.5 + CONTACT_ALPHA
    assert newmark_gamma([_Stiff(False)]) == 0.5
