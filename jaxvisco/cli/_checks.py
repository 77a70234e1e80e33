"""Checks on a finished run: `energy_warning`, the warning that an integrator created
energy (the energy balance ``H + dissipated - external work`` rose), and `_warn_energy`,
which prints it for a results file's data; `print_notes` prints the deprecation notes
of a command's options and scene file.
"""

import sys

import numpy as np


def energy_warning(t, energy, dissipated, external_work, label, tol=0.05):
    """A one-line warning when the integrator created energy, else None.

    The energy created by time t is ``H(t) + dissipated(t) - external_work(t) - H(0)``
    (zero for an exact energy balance, negative where a scheme dissipates numerically);
    nothing supplies it. Its maximum over the frames is compared with `tol` times the
    energy scale ``max(|H(0)|, max |external_work|)``. An energy-stable scheme (eG(k))
    never warns; cG(k), Newmark or the midpoint rule do with a step too large for them.
    Frames with non-finite values are ignored.
    """
    t, H = np.asarray(t, dtype=float), np.asarray(energy, dtype=float)
    D = np.broadcast_to(np.asarray(dissipated, dtype=float), H.shape)
    W = np.broadcast_to(np.asarray(external_work, dtype=float), H.shape)
    if H.size == 0:
        return None
    H0 = H[0]
    created = H + D - W - H0
    ok = np.isfinite(created) & np.isfinite(t)
    if not np.isfinite(H0) or not ok.any():
        return None
    scale = max(abs(H0), float(np.max(np.abs(W[ok]))))
    i = int(np.flatnonzero(ok)[np.argmax(created[ok])])
    if scale == 0.0 or not created[i] > tol * scale:
        return None
    rose = f"H rose {H[i] / H0:.3g}-fold" if H0 > 0 else "H rose"
    unit = "|H0|" if scale == abs(H0) else "max |external work|"
    return (f"{label}: {rose} from H0 = {H0:.6g} to {H[i]:.6g} at t = {t[i]:.6g}; the integrator created an energy "
            f"of {created[i]:.3g} ({created[i] / scale:.3g} x {unit}) that neither the loads' work nor the dissipation "
            "supplies, so the step is likely too large for this scheme (eG(k) is energy-stable).")


def _warn_energy(r, label):
    """Print `energy_warning` for the results `r` (`read_results`) to stderr, if it warns."""
    H = r["energy"]
    msg = energy_warning(r["t"], H, r.get("dissipated", np.zeros_like(H)), r.get("external_work", np.zeros_like(H)),
                         label)
    if msg is not None:
        print(f"jaxvisco: warning: {msg}", file=sys.stderr, flush=True)


def print_notes(args):
    """Print the notes on deprecated names that the options (and scene file) of `args`
    used, one `jaxvisco: warning:` line each (once the options were accepted)."""
    for note in getattr(args, "deprecated", None) or ():
        print(f"jaxvisco: warning: {note}.", file=sys.stderr, flush=True)
