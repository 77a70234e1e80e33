"""What an experiment measures, as functions of a run: load cells, markers, extensometers.

Each observable maps a `Solution` (whose frames are the data's sample times) to an
array (frames, columns); `Experiment` stacks the columns of its observables in order.
They are equinox Modules of data (node indices, a `Probe`, a component), so a fit that
holds them compiles once and a fit file (`jaxvisco identify`) can name them.
"""

import abc
from typing import Callable

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._fem._probe import Probe

_AXES = {"x": 0, "y": 1, "z": 2}


def _component(component, where):
    c = _AXES.get(component, component) if isinstance(component, str) else component
    if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or not 0 <= int(c) <= 2:
        raise ValueError(f"{where}: component must be 0, 1, 2 or 'x', 'y', 'z', got {component!r}.")
    return int(c)


class AbstractObservable(eqx.Module):
    """A measured quantity as a function of a run: the base of `ReactionForce`,
    `Displacement`, `Extensometer`, `Quantity` and `Custom`.

    An observable is called with a `Solution` whose frames are the data's sample times
    and returns an array `(frames, columns)`; `columns` says how many columns of data
    it explains and `labels` names them. A subclass sets `needs_reactions = True` when
    it reads `Solution.reaction`, and `needs_diagnostics = False` when it reads none of
    the frames' energies and momenta (the run then skips them: `SaveAt(diagnostics=False)`).
    """

    needs_reactions = False  # whether the run must save the supports' forces
    needs_diagnostics = True  # whether it reads the frames' energies or momenta

    @abc.abstractmethod
    def __call__(self, solution) -> jnp.ndarray:
        """The observed values (frames, columns)."""

    @property
    @abc.abstractmethod
    def columns(self) -> int:
        """How many columns of data it explains."""

    @property
    def labels(self) -> list:
        """The names of its columns (for reports and plots)."""
        return [f"{type(self).__name__}[{i}]" for i in range(self.columns)]


class AbstractOneColumn(AbstractObservable):
    """An observable of one column, labelled by its `name`."""

    @property
    def columns(self):
        return 1

    @property
    def labels(self):
        return [self.name]


class ReactionForce(AbstractOneColumn):
    """A load cell: the resultant force the supports exert on a group of held nodes in one
    direction, one column: the time element's reaction at each sample time
    (`Solution.reaction`), a polynomial of degree k-1 within a step. With eG(1) that is
    the mean over the step, first order in the step size; use k >= 2 where forces are
    fitted. Its run saves the reactions (`SaveAt(reactions=True)`).

    **Arguments:**

    - `nodes`: the node indices (or a boolean mask of the nodes), e.g. a grip's face.
    - `component`: the direction, `0`, `1`, `2` or `"x"`, `"y"`, `"z"`.
    - `name`: the column's name (default `"force"`).

    **Raises:**

    `ValueError` for an empty or non-integer node list, or an unknown component.

    **Example:**

    ```python
    import jaxvisco as jv

    test = jv.scenes.specimen("relaxation")
    load_cell = jv.ReactionForce(test.grip, "x")
    ```
    """

    nodes: tuple = eqx.field(static=True)
    component: int = eqx.field(static=True)
    name: str = eqx.field(static=True, default="force")
    needs_reactions = True
    needs_diagnostics = False

    def __init__(self, nodes, component, name="force"):
        idx = np.asarray(nodes)
        idx = np.flatnonzero(idx) if idx.dtype == bool else idx
        if idx.ndim != 1 or idx.size == 0 or not np.issubdtype(idx.dtype, np.integer):
            raise ValueError(f"ReactionForce: nodes must be a non-empty list of node indices, got {nodes!r}.")
        self.nodes = tuple(int(i) for i in idx)
        self.component = _component(component, "ReactionForce")
        self.name = str(name)

    def __call__(self, solution):
        return solution.reaction_force(np.asarray(self.nodes), self.component)[:, None]


class Displacement(AbstractObservable):
    """Markers or a DIC grid: the displacements of material points anywhere in the body
    (not only at nodes), read through the shape functions of the element holding each.

    **Arguments:**

    - `mesh`: the body's `Mesh`.
    - `points`: the points' reference coordinates, `(k, dim)`.
    - `component`: one direction (`0`, `1`, `2` or `"x"`, `"y"`, `"z"`): `k` columns;
      None (default): every component, `k * dim` columns, point by point.
    - `name`: the columns' name stem (default `"u"`).

    **Raises:**

    `ValueError` for points outside the body or an unknown component (as `Probe`).

    **Example:**

    ```python
    import jaxvisco as jv

    mesh = jv.box(4, 1, 1, 40.0, 10.0, 10.0)
    markers = jv.Displacement(mesh, [[10.0, 5.0, 5.0], [30.0, 5.0, 5.0]], "x")
    print(markers.columns)                         # 2
    ```
    """

    probe: Probe
    component: object = eqx.field(static=True)
    name: str = eqx.field(static=True, default="u")
    needs_diagnostics = False

    def __init__(self, mesh, points, component=None, name="u"):
        self.probe = Probe(mesh, points)
        self.component = None if component is None else _component(component, "Displacement")
        self.name = str(name)

    def __call__(self, solution):
        u = self.probe.displacements(solution.x)  # (frames, k, dim)
        if self.component is not None:
            return u[..., self.component]
        return u.reshape(u.shape[0], -1)

    @property
    def columns(self):
        k, d = self.probe.n_points, self.probe.dim
        return k if self.component is not None else k * d

    @property
    def labels(self):
        axes = "xyz"
        if self.component is not None:
            return [f"{self.name}{i}_{axes[self.component]}" for i in range(self.probe.n_points)]
        return [f"{self.name}{i}_{axes[c]}" for i in range(self.probe.n_points) for c in range(self.probe.dim)]


class Extensometer(AbstractOneColumn):
    """An extensometer: the change of the distance between two material points, one
    column.

    **Arguments:**

    - `mesh`: the body's `Mesh`.
    - `a`, `b`: the reference coordinates of the gauge's two points.
    - `name`: the column's name (default `"elongation"`).

    **Raises:**

    `ValueError` for a point outside the body.
    """

    probe: Probe
    name: str = eqx.field(static=True, default="elongation")
    needs_diagnostics = False

    def __init__(self, mesh, a, b, name="elongation"):
        self.probe = Probe(mesh, np.stack([np.asarray(a, float), np.asarray(b, float)]))
        self.name = str(name)

    def __call__(self, solution):
        x = self.probe.positions(solution.x)  # (frames, 2, dim)
        X = self.probe.points
        return (jnp.linalg.norm(x[:, 1] - x[:, 0], axis=-1) - jnp.linalg.norm(X[1] - X[0]))[:, None]


class Quantity(AbstractOneColumn):
    """A diagnostic of the run's frames by name, one column: not what a lab measures, but
    what a study of the scheme may fit.

    **Arguments:**

    - `field`: `"energy"`, `"kinetic"`, `"free_energy"`, `"dissipated"`,
      `"dissipation_rate"` or `"external_work"`.

    **Raises:**

    `ValueError` for another name.
    """

    field: str = eqx.field(static=True)
    _FIELDS = ("energy", "kinetic", "free_energy", "dissipated", "dissipation_rate", "external_work")

    def __init__(self, field):
        if field not in self._FIELDS:
            raise ValueError(f"Quantity: field must be one of {self._FIELDS}, got {field!r}.")
        self.field = field

    @property
    def needs_diagnostics(self):
        """Whether its field is one of the frames' diagnostics (not the cumulative ones)."""
        return self.field not in ("dissipated", "external_work")

    def __call__(self, solution):
        return getattr(solution, self.field)[:, None]

    @property
    def name(self):
        """Its column's label: the field."""
        return self.field


class Custom(AbstractObservable):
    """Any function of the run.

    **Arguments:**

    - `fn`: `fn(solution) -> (frames, n)` array (or `(frames,)` for one column),
      traceable by JAX.
    - `n`: how many columns it returns (default 1).

    **Raises:**

    `TypeError` when `fn` is not callable.

    **Example:**

    ```python
    import jaxvisco as jv

    tip_height = jv.Custom(lambda sol: sol.x[:, 0, 1])
    ```
    """

    fn: Callable = eqx.field(static=True)
    n: int = eqx.field(static=True)

    def __init__(self, fn, n=1):
        if not callable(fn):
            raise TypeError(f"Custom: fn must be callable, got {fn!r}.")
        self.fn, self.n = fn, int(n)

    def __call__(self, solution):
        out = jnp.asarray(self.fn(solution))
        return out[:, None] if out.ndim == 1 else out

    @property
    def columns(self):
        return self.n
