"""One test of a material, as an identification sees it: `Experiment`."""

import csv
import os
from typing import Optional, Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._integrate._saveat import SaveAt
from .._integrate._schedule import AbstractStepSizeController, ConstantStepSize
from .._integrate._simulate import simulate
from .._integrate._solution import FAILED
from .._scene import Scene
from .._solver._newton import NewtonKrylov
from .._time_element._time_element import AbstractTimeElement
from ._observe import AbstractObservable


def read_csv(path: str | os.PathLike) -> tuple[list, np.ndarray]:
    """Read a data file: a header row of column names, then rows of numbers, the first
    column time; lines starting with `#` are comments.

    **Arguments:**

    - `path`: the CSV file.

    **Returns:**

    `(names, values)`: the column names and a `(rows, columns)` float64 array.

    **Raises:**

    `ValueError` for a file without a header and a row, a row that holds anything but
    numbers, or rows of another length than the header.
    """
    with open(path, newline="") as f:
        rows = [r for r in csv.reader(f) if r and not r[0].lstrip().startswith("#")]
    if len(rows) < 2:
        raise ValueError(f"{path}: a data file needs a header row and at least one row of numbers.")
    names = [c.strip() for c in rows[0]]
    try:
        values = np.array([[float(v) for v in r] for r in rows[1:]])
    except ValueError as e:
        raise ValueError(f"{path}: every row after the header must hold numbers only ({e}).") from None
    if values.ndim != 2 or values.shape[1] != len(names):
        raise ValueError(f"{path}: every row must have the header's {len(names)} columns.")
    return names, values


class Experiment(eqx.Module):
    """One test of a material: a scene run with a time element, what is measured in it and
    the measured data. `identify` fits parameters to one or several of them.

    **Arguments:**

    - `scene`: the test's `Scene` (specimen, supports, loads, material).
    - `integrator`: its time element, `cG(k)`, `eG(k)`, `Midpoint()` or `Newmark()`.
    - `times`: the data's sample times `(m,)`, non-decreasing, within `[t0, t1]`; the
      run saves its frames there (`SaveAt(ts)`).
    - `data`: the measurements `(m, c)` (or `(m,)` for one column): one column per
      observed quantity.
    - `observe`: an observable or a list of them (`ReactionForce`, `Displacement`,
      `Extensometer`, `Quantity`, `Custom`), whose columns in order make up the `c`
      columns of `data`.
    - `sigma`: the noise level (standard deviation) of each column, `(c,)` or one number:
      residuals are divided by it. None (default): each column is divided by its own
      root mean square, and `identify` estimates the noise level from the residuals.
    - `t0` (default 0), `t1` (default the last sample time), `dt0`,
      `stepsize_controller`: the run's times and steps, as in `simulate`.
    - `root_finder`: the Newton solver, as in `simulate`; default
      `NewtonKrylov(rtol=1e-11)`, a decade tighter than `simulate`'s, so that at a fit's
      optimum the residuals are the data's misfit rather than Newton's tolerance.
    - `name`: the experiment's name in reports and plots (distinct within a fit).

    **Raises:**

    `TypeError` for a scene, integrator or observable of the wrong kind; `ValueError`
    for times that are not finite and non-decreasing or outside `[t0, t1]`, data of
    the wrong shape or not finite, or a `sigma` that is not positive.

    **Example:**

    ```python
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    import jaxvisco as jv

    test = jv.scenes.specimen("relaxation", elements=(2, 1, 1), t1=0.6)
    times = np.linspace(0.0, 0.6, 7)
    force = np.zeros((7, 1))                       # the load cell's record
    e = jv.Experiment(test.scene, jv.eG(2), times, force, jv.ReactionForce(test.grip, "x"),
                      dt0=test.dt0, name="relaxation")
    print(e.labels)                                # ['force']
    ```
    """

    scene: Scene
    integrator: AbstractTimeElement
    times: tuple = eqx.field(static=True)
    data: jnp.ndarray
    observe: tuple
    sigma: Optional[jnp.ndarray]
    t0: float = eqx.field(static=True)
    t1: float = eqx.field(static=True)
    dt0: Optional[float] = eqx.field(static=True)
    stepsize_controller: AbstractStepSizeController
    root_finder: NewtonKrylov
    name: str = eqx.field(static=True)

    def __init__(self, scene, integrator, times, data, observe, sigma=None, *, t0=0.0, t1=None, dt0=None,
                 stepsize_controller=None, root_finder=None, name="experiment"):
        if not isinstance(scene, Scene):
            raise TypeError(f"Experiment {name!r}: scene must be a Scene, got {type(scene).__name__}.")
        if not isinstance(integrator, AbstractTimeElement):
            raise TypeError(f"Experiment {name!r}: integrator must be cG(k), eG(k), Midpoint() or Newmark(), "
                            f"got {integrator!r}.")
        observe = tuple(observe) if isinstance(observe, (list, tuple)) else (observe,)
        for o in observe:
            if not isinstance(o, AbstractObservable):
                raise TypeError(f"Experiment {name!r}: observe must hold observables (ReactionForce, Displacement, "
                                f"Extensometer, Quantity, Custom), got {o!r}.")
        ts = np.asarray(times, dtype=float).ravel()
        if ts.size == 0 or not np.all(np.isfinite(ts)) or np.any(np.diff(ts) < 0):
            raise ValueError(f"Experiment {name!r}: times must be finite and non-decreasing.")
        d = np.asarray(data, dtype=float)
        d = d[:, None] if d.ndim == 1 else d
        c = sum(o.columns for o in observe)
        if d.shape != (ts.size, c):
            raise ValueError(f"Experiment {name!r}: data must have shape (len(times), columns of observe) = "
                             f"({ts.size}, {c}), got {d.shape}.")
        if not np.all(np.isfinite(d)):
            raise ValueError(f"Experiment {name!r}: data must be finite.")
        if sigma is not None:
            s = np.broadcast_to(np.asarray(sigma, dtype=float), (c,))
            if not np.all((s > 0) & np.isfinite(s)):
                raise ValueError(f"Experiment {name!r}: sigma must be positive and finite, got {sigma!r}.")
            sigma = jnp.asarray(s)
        t1 = float(ts[-1]) if t1 is None else float(t1)
        if ts[0] < t0 or ts[-1] > t1:
            raise ValueError(f"Experiment {name!r}: times must lie within [t0, t1] = [{t0:g}, {t1:g}].")
        self.scene, self.integrator, self.times = scene, integrator, tuple(float(t) for t in ts)
        self.data, self.observe, self.sigma = jnp.asarray(d), observe, sigma
        self.t0, self.t1 = float(t0), t1
        self.dt0 = None if dt0 is None else float(dt0)
        # the default spelled out, so that the same test built with or without it (a fit
        # file names it) is one compiled program
        self.stepsize_controller = ConstantStepSize() if stepsize_controller is None else stepsize_controller
        self.root_finder = NewtonKrylov(rtol=1e-11) if root_finder is None else root_finder
        self.name = str(name)

    @classmethod
    def from_csv(cls, scene, integrator, path, observe: dict, sigma: Optional[dict] = None, **run) -> "Experiment":
        """An experiment whose data are a CSV file (`read_csv`: time first, then named
        columns).

        **Arguments:**

        - `scene`, `integrator`: as `Experiment`.
        - `path`: the CSV file.
        - `observe`: column name -> observable (one column each, in the order given).
        - `sigma`: column name -> noise level (default: none known).
        - `**run`: `t0`, `t1`, `dt0`, `stepsize_controller`, `root_finder`, `name` (default:
          the file's name), as `Experiment`.

        **Raises:**

        `ValueError` for a column the file lacks, and as `read_csv` and `Experiment`.
        """
        names, values = read_csv(path)
        missing = [k for k in observe if k not in names[1:]]
        if missing:
            raise ValueError(f"{path}: no column {missing[0]!r}; the file has {names[1:]}.")
        cols = [names.index(k) for k in observe]
        s = None if sigma is None else [float(sigma[k]) for k in observe]
        run.setdefault("name", os.path.splitext(os.path.basename(path))[0])
        return cls(scene, integrator, values[:, 0], values[:, cols], list(observe.values()), s, **run)

    @property
    def labels(self) -> Sequence[str]:
        """The names of the data's columns, from the observables."""
        return [lab for o in self.observe for lab in o.labels]

    def run(self, scene: Optional[Scene] = None):
        """The test's run (of `scene`, default its own) as a `Solution`, with frames at the
        sample times (the supports' forces, the energies and momenta only where an
        observable reads them); a run that fails returns with `status == "failed"`."""
        reactions = any(o.needs_reactions for o in self.observe)
        diagnostics = any(o.needs_diagnostics for o in self.observe)
        return simulate(self.scene if scene is None else scene, self.integrator, self.t0, self.t1, self.dt0,
                        saveat=SaveAt(np.asarray(self.times), reactions=reactions, diagnostics=diagnostics),
                        stepsize_controller=self.stepsize_controller, root_finder=self.root_finder, throw=False)

    def model(self, solution) -> jnp.ndarray:
        """What the observables read off a run, `(m, c)`; infinite for a failed run."""
        out = jnp.concatenate([o(solution) for o in self.observe], axis=1)
        return jnp.where(solution.status_code == FAILED, jnp.inf, out)

    def sensitivities(self, parameters: dict):
        """What the observables read off the test's run with `parameters` (name -> value,
        as `identify` takes them; the others as the scene has them) and their
        derivatives in each parameter: which columns, at which times, see a parameter,
        before a test is run or a fit is tried; or synthetic data.

        **Returns:**

        `(model, derivatives)`: the model `(m, c)` as `model(run())` gives it with these
        values, and parameter name -> `(m, c)` array of its derivatives (forward mode
        through the run). Computed by the program that a fit of the same parameters
        (`identify(self, parameters)`) evaluates at each iteration, so that the fit
        compiles nothing new for this test.

        **Raises:**

        `ValueError` as `identify` does for unknown parameters.
        """
        from ._identify import sensitivities

        return sensitivities(self, parameters)

    def scale(self) -> jnp.ndarray:
        """What each column's residuals are divided by, `(c,)`: `sigma`, or the data's
        root mean square."""
        if self.sigma is not None:
            return self.sigma
        rms = jnp.sqrt(jnp.mean(self.data**2, axis=0))
        return jnp.where(rms > 0, rms, 1.0)
