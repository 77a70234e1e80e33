"""`simulate`'s keywords before the diffrax-shaped signature, as deprecated aliases.

Until 0.2 `simulate(scene, integrator, t_end, dt, t0=..., save_every=..., save_gamma=...,
stop_at_equilibrium=..., max_halvings=..., differentiable=..., checkpoint_every=...)`.
Each old keyword maps onto the new arguments; one `DeprecationWarning` names the
replacements. They go in the next release.
"""

import warnings

import numpy as np

from ._adjoint import RecursiveCheckpointAdjoint
from ._event import Equilibrium
from ._saveat import SaveAt
from ._schedule import AbstractFixedSteps, ConstantStepSize, Schedule, StepTo

_NEW = dict(t_end="t1=", dt="dt0= (a number), stepsize_controller=Schedule([...]) or StepTo(ts)",
            save_every="saveat=SaveAt(every=n)", save_gamma="saveat=SaveAt(gamma=True)",
            stop_at_equilibrium="event=Equilibrium(tol)", max_halvings="ConstantStepSize(max_halvings=m) (or the "
            "Schedule/StepTo argument)", differentiable="nothing (every run is differentiable)",
            checkpoint_every="adjoint=RecursiveCheckpointAdjoint(checkpoints=n) (stored states; or max_bytes=)")


def translate(old, t1, dt0, saveat, stepsize_controller, event, adjoint, where="simulate", accepted=tuple(_NEW)):
    """The new arguments from the old keywords in `old` (a dict; `accepted`: the old
    names `where` took); raises on unknown keywords and on an old keyword given together
    with its replacement."""
    unknown = sorted(set(old) - set(accepted))
    if unknown:
        raise TypeError(f"{where}() got unexpected keyword argument(s) {unknown}; see help(jaxvisco.{where}) for "
                        "the accepted ones.")
    warnings.warn(f"{where}(): " + "; ".join(f"{k}= is deprecated, use {_NEW[k]}" for k in old) + ".",
                  DeprecationWarning, stacklevel=3)

    def conflict(name, new_name, new_value):
        if name in old and new_value is not None:
            raise TypeError(f"{where}(): give {new_name} or the deprecated {name}, not both.")

    conflict("t_end", "t1", t1)
    t1 = old.get("t_end", t1)
    if "dt" in old:
        conflict("dt", "dt0", dt0)
        dt = old["dt"]
        if isinstance(dt, StepTo) or (dt is not None and not isinstance(dt, bool) and np.ndim(dt) != 0):
            if stepsize_controller is not None:
                raise ValueError(f"simulate(): with a stepsize_controller, dt is the first step to try (a number) or "
                                 f"None; schedules and StepTo fix the steps themselves, got dt = {dt!r}.")
            stepsize_controller = dt if isinstance(dt, StepTo) else Schedule(dt)
        else:
            dt0 = dt
    if "save_every" in old or "save_gamma" in old:
        base = SaveAt() if saveat is None else saveat
        if base.ts is not None:
            saveat = SaveAt(base.ts, gamma=bool(old.get("save_gamma", base.gamma)))
            if old.get("save_every", 1) != 1:
                raise ValueError("simulate(): save_every applies to frames at steps, not to SaveAt(ts).")
        else:
            saveat = SaveAt(every=old.get("save_every", base.every), gamma=bool(old.get("save_gamma", base.gamma)))
    if old.get("stop_at_equilibrium") is not None:
        conflict("stop_at_equilibrium", "event", event)
        event = Equilibrium(old["stop_at_equilibrium"])
    if "max_halvings" in old:
        m = old["max_halvings"]
        ctrl = ConstantStepSize() if stepsize_controller is None else stepsize_controller
        if isinstance(ctrl, StepTo):
            stepsize_controller = StepTo(ctrl.ts, max_halvings=m)
        elif isinstance(ctrl, Schedule):
            stepsize_controller = Schedule(ctrl.pieces, max_halvings=m)
        elif isinstance(ctrl, AbstractFixedSteps):
            stepsize_controller = ConstantStepSize(max_halvings=m)
    if old.get("checkpoint_every") is not None:
        conflict("checkpoint_every", "adjoint", adjoint)
        with warnings.catch_warnings():  # one warning per call: the one above names it
            warnings.simplefilter("ignore", DeprecationWarning)
            adjoint = RecursiveCheckpointAdjoint(checkpoint_every=old["checkpoint_every"])
    return t1, dt0, saveat, stepsize_controller, event, adjoint
