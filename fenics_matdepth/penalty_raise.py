"""Raising the penalty where a surface would pass through a body (``solve_time_steps``'s
``max_penalty``).

Where even the smallest time step cannot keep a boundary vertex from leaving a body through
its far side (the collision detection's exit cap holds it and Newton fails), the penalty is
too weak for the layer: `fenics_matdepth.contact.ccd.penalty_needed` estimates the one that
would store the kinetic energy at the overlap reached. :class:`PenaltyRaise` raises the
contact's penalty to twice that (at most ``max_penalty``) and takes the time stepping back to
the last accepted state at which no pair overlapped, from where the impact is solved again.

Why back to a state without contact: the contact energy at a given overlap scales with the
penalty, so raising it during a contact multiplies the energy stored there (by the factor;
at the pass-through above by several hundred on the cube of docs/dynamics.md, more than the
kinetic energy). Where nothing overlaps the contact energy is zero under any penalty, and the
state and its energy are the same: the raise creates no energy. Where no such state was
passed since the run began (bodies resting on each other throughout), nothing is raised and
the stepping stops with the message as before. Friction's history is not rewound: with
friction nothing is raised.
"""

from __future__ import annotations

import warnings

import numpy as np

from fenics_matdepth.contact.ccd import penalty_needed

__all__ = ["PENALTY_MARGIN", "PenaltyRaise"]

#: The raised penalty is this times the estimate ``contact.ccd.penalty_needed`` gives (the estimate
#: stores the kinetic energy at the overlap reached, the layer's far face: the margin keeps
#: the surface short of it).
PENALTY_MARGIN = 2.0


class PenaltyRaise:
    """The last contact-free accepted state of a time stepping, and the penalty raise that
    goes back to it (used by ``solve_time_steps(..., max_penalty=...)``).

    Args:
        contact: the problem's contact operator.
        integrator: the time integrator (``u_prev``, ``v_prev``, ``a_prev``, ``t``).
        max_penalty: the largest penalty allowed (F/L^3).
        step_contact: the step's contact force term (its previous force is part of the
            state), or None.
    """

    def __init__(self, contact, integrator, max_penalty: float, step_contact=None):
        if not (np.isfinite(max_penalty) and max_penalty > 0.0):
            raise ValueError(f"max_penalty must be a positive number, got {max_penalty}")
        self.contact, self.integrator = contact, integrator
        self.max_penalty = float(max_penalty)
        self.step_contact = step_contact
        self.saved: dict | None = None
        #: ``(t at the pass-through, t gone back to, penalty before, penalty after)`` per raise
        self.raises: list[tuple[float, float, float, float]] = []

    def keep(self, step: int, step_dt: float) -> None:
        """After an accepted step (``step``, the integrator advanced): keep its state if no
        contact pair overlaps there (collective)."""
        if self.contact.diagnostics().get("active_pairs", 0) > 0:
            return
        integrator = self.integrator
        force = getattr(self.step_contact, "force", None)
        self.saved = {
            "step": step, "t": integrator.t, "step_dt": step_dt,
            "u": integrator.u_prev.x.array.copy(), "v": integrator.v_prev.x.array.copy(),
            "a": integrator.a_prev.x.array.copy(),
            "force": force.getArray().copy() if force is not None else None,
        }  # fmt: skip

    def attempt(self, t: float, kinetic_energy: float) -> tuple[int, float, float] | None:
        """Raise the penalty and restore the kept state, or None where that cannot be done (no
        contact-free state kept, friction, the penalty needed above ``max_penalty``). The
        contact must hold the last accepted state (at ``t``, with ``kinetic_energy``).

        Returns:
            ``(step, t, step_dt)`` of the state restored (collective).
        """
        contact, saved = self.contact, self.saved
        if saved is None or contact.friction is not None:
            return None
        needed = penalty_needed(contact, kinetic_energy)
        if needed is None:
            return None
        before = contact.penalty
        after = min(PENALTY_MARGIN * needed, self.max_penalty)
        if not after > needed or not after > before:
            return None
        contact.penalty = after
        integrator = self.integrator
        integrator.u_prev.x.array[:] = saved["u"]
        integrator.v_prev.x.array[:] = saved["v"]
        integrator.a_prev.x.array[:] = saved["a"]
        integrator.u.x.array[:] = saved["u"]
        integrator.t = saved["t"]
        force = getattr(self.step_contact, "force", None)
        if force is not None and saved["force"] is not None:
            force.setArray(saved["force"])
        contact.update()
        self.raises.append((t, saved["t"], before, after))
        if contact.comm.rank == 0:
            warnings.warn(
                f"a surface would pass through a body at t = {t:.6g}: the contact penalty is "
                f"raised from {before:.3g} to {after:.3g} ({PENALTY_MARGIN:g} times the "
                f"{needed:.3g} the overlap reached needs) and the time stepping goes back to "
                f"t = {saved['t']:.6g}, the last state without contact (no energy is created "
                "there); pass a penalty of about this size to avoid the repeat",
                RuntimeWarning,
                stacklevel=4,
            )
        return saved["step"], saved["t"], saved["step_dt"]
