"""What reading a scene file gives: `SceneFile` (`read_scene_file`)."""

import dataclasses
import warnings


@dataclasses.dataclass(frozen=True)
class SceneFile:
    """A scene file, read and checked: what `read_scene_file` returns.

    **Attributes:**

    - `scene`: the `Scene`.
    - `integrator`: the time element of ``[integrator]``.
    - `root_finder`: the `NewtonKrylov` of ``[solver]`` (with its ``[solver.gmres]``).
    - `t0`, `t1`: the run's start and end (``[time]``).
    - `dt0`: the constant step, the schedule ``((t_until, dt), ...)``, or with error
      control the first step tried (None: a hundredth of the run).
    - `steps`: the `StepTo` of the fixed steps from `t0` to `t1` (None with error control).
    - `max_halvings`: how often a failed step may be halved.
    - `rtol`, `atol`: the tolerances of error-controlled steps (None for fixed steps).
    - `saveat`: the `SaveAt` of ``[saveat]``.
    - `output`: dict with ``file`` (resolved against the scene file's folder), ``chunk``
      and ``commit_every`` (``[output]``).
    - `source`: the file's text; `path`; `base_dir`: where relative paths start.
    - `deprecated`: one note for each deprecated key the file uses (empty if none).
    - `nodes(name)`: the node indices of a group (see below).

    The attributes `t_end`, `dt` and `solver` are deprecated names of `t1`, `dt0` and
    `root_finder`.
    """

    scene: object
    integrator: object
    root_finder: object
    t0: float
    t1: float
    dt0: object
    steps: object
    max_halvings: int
    saveat: object
    output: dict
    source: str
    path: str
    base_dir: str
    rtol: object = None
    atol: object = None
    deprecated: tuple = ()
    node_groups: object = None  # name -> node indices: the [groups] tables and the mesh file's node groups

    def nodes(self, name: str):
        """The node indices of the group `name`: a ``[groups.NAME]`` table or a node group
        of the mesh file.

        **Raises:**

        `ValueError` naming the groups there are, for an unknown name.
        """
        return self.node_groups(name)

    @property
    def t_end(self):
        """Deprecated: `t1`."""
        return _deprecated_attribute(self, "t_end", "t1")

    @property
    def dt(self):
        """Deprecated: `dt0`."""
        return _deprecated_attribute(self, "dt", "dt0")

    @property
    def solver(self):
        """Deprecated: `root_finder`."""
        return _deprecated_attribute(self, "solver", "root_finder")


def _deprecated_attribute(sf, old, new):
    warnings.warn(f"SceneFile.{old} is deprecated, use SceneFile.{new}.", DeprecationWarning, stacklevel=3)
    return getattr(sf, new)
