"""``jaxvisco plot``: `plot_figure`, the figure of a results file (energy, energy
balance error, drift of the linear and angular momentum, `momentum_drift`), and `_plot`,
the subcommand that writes it as a PNG.
"""

import os

import numpy as np


def momentum_drift(values):
    """`values` (n,) or (n, d) over the frames minus their initial value: ``J(t) - J(0)``."""
    values = np.asarray(values, dtype=float)
    return values - values[:1]


def plot_figure(r, title=""):
    """The `jaxvisco plot` figure of the results dict `r` (`read_results`): H and
    H + dissipated − external work, the energy balance error, and the drift of the linear
    and angular momentum from their initial values (conserved quantities are shown as
    drifts, without axis offset notation, so round-off is not mistaken for motion)."""
    import matplotlib.pyplot as plt

    t, H = r["t"], r["energy"]
    D = r.get("dissipated", np.zeros_like(H))
    W = r.get("external_work", np.zeros_like(H))
    H0 = H[0] if len(H) else 0.0
    worked = bool(np.any(W != 0))
    # The energy scale: |H0| for a free body; a loaded body may start at rest (H0 = 0),
    # so it is the largest energy reached or work done.
    scale = max(float(np.max(np.abs(H), initial=0.0)), float(np.max(np.abs(W), initial=0.0))) or 1.0
    fig, axs = plt.subplots(2, 2, figsize=(11, 7))
    ax = axs[0, 0]
    ax.plot(t, H, label="H")
    if worked:
        ax.plot(t, H + D - W, "--", label="H + dissipated − external work (= H0)")
        ax.plot(t, W, ":", label="external work W (loads, moving supports)")
    else:
        ax.plot(t, H + D, "--", label="H + dissipated (= H0)")
    ax.set_title("energy")
    ax.legend()
    ax = axs[0, 1]
    err = np.abs(H + D - W - H0) / scale
    ax.semilogy(t, np.maximum(err, 1e-17))
    ax.set_title("energy balance error |H + D − W − H0| / max(|H|, |W|)" if worked
                 else "energy balance error |H + D − H0| / max |H|")
    acted = worked or int(r.get("attrs", {}).get("held_components", 0)) > 0
    for ax, key, sym, name in ((axs[1, 0], "linear_momentum", "L", "linear"),
                               (axs[1, 1], "angular_momentum", "J", "angular")):
        ax.set_title(f"{name} momentum {sym} − {sym}(0) (loads, supports act)" if acted
                     else f"{name} momentum drift {sym} − {sym}(0)")
        values = r.get(key)
        if values is None or len(values) == 0:
            continue
        values = np.asarray(values, dtype=float)
        drift = momentum_drift(values)
        if values.ndim == 1:  # 2D angular momentum: J_z
            values, drift, comps = values[:, None], drift[:, None], "z"
        else:
            comps = "xyz"[:values.shape[1]]
        for i, c in enumerate(comps):
            ax.plot(t, drift[:, i], label=f"{sym}_{c} − {sym}_{c}(0),  {sym}_{c}(0) = {values[0, i]:.10g}")
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.legend(fontsize=8)
    for a in axs.flat:
        a.set_xlabel("t")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return fig


def _plot(args):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import jaxvisco as jv

    r = jv.read_results(args.results)
    out = args.out or os.path.splitext(args.results)[0] + ".png"
    fig = plot_figure(r, f"{os.path.basename(args.results)}: {r['attrs'].get('integrator', '')} "
                         f"({r['attrs'].get('status', '')})")
    fig.savefig(out, dpi=110)
    plt.close(fig)
    print(f"wrote {out}")
    return 0
