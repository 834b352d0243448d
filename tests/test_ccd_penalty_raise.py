"""``PenaltyRaise`` (``solve_time_steps(..., max_penalty=...)``) on stand-ins for the contact and
the integrator: what it keeps, what it restores, when it refuses.

The run on a model is in ``tests/test_ccd_thin.py``; here each rule alone. The contact's
energy at the state reached is E_c = 1 and the kinetic energy K = 9, so the penalty needed
(``penalty_needed``: eps (K + E_c) / E_c) is 10 eps, and the raise asks for twice that.
"""

from __future__ import annotations

import types
import warnings

import numpy as np
import pytest

from fenics_matdepth.penalty_raise import PENALTY_MARGIN, PenaltyRaise


class _Contact:
    """Stand-in: one penalty, an energy, the active pairs, serial."""

    def __init__(self, active: int = 0, friction=None):
        self.penalty, self.active, self.friction = 1.0, active, friction
        self.comm = types.SimpleNamespace(rank=0)
        self.updates = 0

    def energy(self) -> float:
        return 1.0

    def diagnostics(self) -> dict:
        return {"active_pairs": self.active}

    def update(self) -> None:
        self.updates += 1


def _field(values):
    return types.SimpleNamespace(x=types.SimpleNamespace(array=np.array(values, dtype=float)))


def _integrator(value: float, t: float):
    return types.SimpleNamespace(
        u=_field([value] * 3), u_prev=_field([value] * 3), v_prev=_field([2 * value] * 3),
        a_prev=_field([3 * value] * 3), t=t,
    )  # fmt: skip


def test_raise_restores_the_last_state_without_contact():
    """The state kept is the last accepted one without an overlapping pair (a later one with
    contact does not replace it); the raise sets twice the needed penalty (20), restores u, v,
    a and t of that state, updates the contact there and warns with both penalties."""
    contact = _Contact()
    integrator = _integrator(1.0, 0.5)
    raiser = PenaltyRaise(contact, integrator, max_penalty=100.0)
    raiser.keep(3, 0.01)
    contact.active = 4  # the next state is in contact: not kept
    integrator.u_prev.x.array[:] = integrator.v_prev.x.array[:] = 7.0
    integrator.t = 0.7
    raiser.keep(4, 0.02)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        back = raiser.attempt(0.7, kinetic_energy=9.0)
    assert back == (3, 0.5, 0.01)
    assert contact.penalty == PENALTY_MARGIN * 10.0
    assert integrator.t == 0.5 and contact.updates == 1
    for field, value in (("u", 1.0), ("u_prev", 1.0), ("v_prev", 2.0), ("a_prev", 3.0)):
        assert np.all(getattr(integrator, field).x.array == value), field
    assert raiser.raises == [(0.7, 0.5, 1.0, 20.0)]
    assert any("raised from 1 to 20" in str(w.message) for w in caught), caught


@pytest.mark.parametrize(
    "case", ["no state without contact", "friction", "max_penalty below the need"]
)
def test_raise_refused(case):
    """Nothing is raised or restored where no contact-free state was kept (bodies in contact
    from the start), with friction (its history is not kept), or where ``max_penalty`` is
    below the penalty needed (10): the stepping then stops as without the option."""
    contact = _Contact(active=4 if case == "no state without contact" else 0)
    if case == "friction":
        contact.friction = object()
    integrator = _integrator(1.0, 0.5)
    raiser = PenaltyRaise(contact, integrator, 5.0 if case.startswith("max") else 100.0)
    raiser.keep(3, 0.01)
    integrator.t = 0.7
    assert raiser.attempt(0.7, kinetic_energy=9.0) is None
    assert contact.penalty == 1.0 and integrator.t == 0.7 and raiser.raises == []


def test_max_penalty_must_be_positive():
    with pytest.raises(ValueError, match="max_penalty must be a positive number"):
        PenaltyRaise(_Contact(), _integrator(0.0, 0.0), max_penalty=-1.0)
