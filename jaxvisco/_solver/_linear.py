"""How each Newton iteration solves its linear system: `GMRES` or `Direct`.

Objects, as `NewtonKrylov(linear_solver=...)` takes them (after lineax and optimistix):
every setting of the linear solve lives on the solver it belongs to. The strings of
jaxvisco 0.1 stay accepted: ``"krylov"`` is `GMRES()` and ``"direct"`` is `Direct()`;
the keywords ``krylov``, ``krylov_max_steps`` and ``refresh_after`` of `NewtonKrylov` are
deprecated aliases of `GMRES`'s fields (`from_legacy`).
"""

import warnings

import equinox as eqx
import numpy as np

_BACKENDS = ("jaxvisco", "lineax")
PRECONDITIONERS = ("auto", "lu", "amg")
_PRECISIONS = {"single": np.float32, "double": np.float64}
# Where "auto" switches to the multigrid: 3D meshes with at least this many position
# unknowns. Measured (3D L-shape hex8, eG(1), h = 0.1, 5 steps, ms/step multigrid / LU):
# 672 unknowns 21 / 21, 3969 136 / 153, 12 000 560 / 578, 26 871 1183 / 1395-2067;
# the LU's fill grows faster beyond (benchmarks/results/scaling_amg_s18.json). With the
# float32 cycles, 12 000 unknowns, alternating pairs: 517 / 455 against 543 / 550 ms/step,
# but 15-17 s of compilation against 11-13 s and 920 against 1300 MB: the faster steps
# repay the compile only after ~75 steps, so the switch stays here. Again after the chord
# iterations (session 29, quiet, alternating pairs, 5 steps; ms for the first step, which
# forms the tangent, and for the later ones, which reuse it; LU / multigrid):
#   3 969 unknowns   first 414 396 / 286 279   later 44 39 / 82 76      compile 11 / 15 s
#   12 000           first 1819 1667 / 842 878  later 196 174 / 269 240   compile 11 / 14 s
#   26 871           first 5147 5143 / 2161 1808  later 477 617 / 449 512  compile 11 / 20 s
# Below the switch the LU's steps that reuse its factorization are faster; above it the
# multigrid wins both (benchmarks/results/switch_s29.json).
AUTO_AMG_UNKNOWNS = 20_000
# GMRES's basis on the multigrid path (`GMRES.restart` None): at most this many vectors
# before a restart. The basis holds every unknown (Γ included: 93 % of them on the 3D
# L-shape); with 61 rows it was 188 MB of the 782 MB of XLA buffers of the hex8 r4 run
# and the largest array at the peak (the preconditioner's cycles keep Krylov vectors per
# Newton iteration at 2-3 there, so the restart rarely triggers). With 20 (21 rows) the
# basis set the peak of XLA's buffers at hex8 r8 (196 875 unknowns, 3.07 million with Γ):
# temporary buffers of the compiled loop 1963 MB, with 10 1729 MB
# (`benchmarks/loop_memory.py`); the runs there take 2-5 Krylov vectors per Newton iteration.
AMG_RESTART = 10


class AbstractLinearSolver(eqx.Module):
    """The linear solve of a Newton iteration: `GMRES` or `Direct`."""

    def block_solver(self, scene):
        """How the condensed position block of `scene` is solved: ``"lu"`` or ``"amg"``
        (`GMRES.preconditioner`; ``"auto"`` resolved by the mesh, `Direct` always LU)."""
        choice = getattr(self, "preconditioner", "lu")
        if choice != "auto":
            return choice
        return "amg" if scene.dim == 3 and scene.disc.n_nodes * 3 >= AUTO_AMG_UNKNOWNS else "lu"

    def block_dtype(self):
        """Floating type of the multigrid's operators and cycles (`GMRES.multigrid_precision`)."""
        return _PRECISIONS[getattr(self, "multigrid_precision", "single")]

    def memory_first(self, scene):
        """Whether a Newton iteration of `scene` saves memory over work: on the
        multigrid path (large 3D meshes) its JVPs re-run the residual instead of keeping
        a linearization, and GMRES restarts (`restart_for`) and rebuilds its solution
        from the basis."""
        return self.block_solver(scene) == "amg"

    def restart_for(self, scene):
        """GMRES's basis length for `scene` (`GMRES.restart`; None: no restart)."""
        restart = getattr(self, "restart", None)
        if restart is None and self.memory_first(scene):
            return AMG_RESTART
        return restart


class GMRES(AbstractLinearSolver):
    """Newton–Krylov (the default linear solver of `NewtonKrylov`): GMRES on the
    Jacobian-vector product of the step residual, right-preconditioned by a solve with
    the condensed tangent, which is kept across iterations and steps.

    **Arguments:**

    - `max_steps`: Krylov vectors per Newton iteration (60).
    - `refresh_after`: re-form the tangent once GMRES needed more vectors than this (5);
      on the multigrid path at the start of the next step.
    - `backend`: `"jaxvisco"` (default: a GMRES that checks its residual after every
      Arnoldi step) or `"lineax"` (lineax's GMRES, restarted every 5 vectors; it checks
      convergence once per restart cycle, so it costs more vectors).
    - `preconditioner`: how the condensed position block is solved: `"lu"` (a sparse LU
      on the host, exact where the tangent was formed), `"amg"` (six W-cycles of
      smoothed-aggregation multigrid in JAX: no fill-in, no host call, cost about linear
      in the mesh, runs on GPUs) or `"auto"` (default: the multigrid for 3D meshes with
      at least 20 000 position unknowns, the LU otherwise).
    - `restart`: Krylov vectors kept before GMRES restarts (None, the default: no restart
      on the LU path, 10 on the multigrid path, where the basis over every unknown is the
      largest array of a step). `max_steps` bounds the vectors of all cycles together.
    - `multigrid_precision`: `"single"` (default) or `"double"`, the arithmetic of the
      multigrid's operators and cycles. Only the preconditioner runs in float32: the
      residuals, Krylov vectors and updates stay float64 and the step converges to the
      same tolerance. `"double"` can solve the block to any tolerance (float32 stops
      near 1e-6). Derivatives of a run use a float64 multigrid either way.

    **Raises:**

    `ValueError` for a setting out of its range or not among the accepted strings.

    **Example:**

    ```python
    import jaxvisco as jv

    root_finder = jv.NewtonKrylov(linear_solver=jv.GMRES(max_steps=30, preconditioner="lu"))
    ```
    """

    max_steps: int = eqx.field(static=True, default=60)
    refresh_after: int = eqx.field(static=True, default=5)
    backend: str = eqx.field(static=True, default="jaxvisco")
    preconditioner: str = eqx.field(static=True, default="auto")
    restart: int | None = eqx.field(static=True, default=None)
    multigrid_precision: str = eqx.field(static=True, default="single")

    def __check_init__(self):
        if isinstance(self.max_steps, bool) or not isinstance(self.max_steps, int) or self.max_steps < 1:
            raise ValueError(f"GMRES: max_steps must be an integer >= 1, got {self.max_steps!r}.")
        if isinstance(self.refresh_after, bool) or not isinstance(self.refresh_after, int) or self.refresh_after < 0:
            raise ValueError(f"GMRES: refresh_after must be an integer >= 0, got {self.refresh_after!r}.")
        if self.backend not in _BACKENDS:
            raise ValueError(f"GMRES: backend must be one of {_BACKENDS}, got {self.backend!r}.")
        if self.preconditioner not in PRECONDITIONERS:
            raise ValueError(f"GMRES: preconditioner must be one of {PRECONDITIONERS}, got {self.preconditioner!r}.")
        if self.restart is not None and (isinstance(self.restart, bool) or not isinstance(self.restart, int)
                                         or self.restart < 1):
            raise ValueError(f"GMRES: restart must be None or an integer >= 1, got {self.restart!r}.")
        if self.multigrid_precision not in _PRECISIONS:
            raise ValueError(f"GMRES: multigrid_precision must be one of {tuple(_PRECISIONS)}, "
                             f"got {self.multigrid_precision!r}.")


class Direct(AbstractLinearSolver):
    """Exact Newton steps (`NewtonKrylov(linear_solver=Direct())`): the condensed
    tangent is formed and factored at every iteration; no Krylov vectors, no chord
    iterations. The robust choice for stiff regimes, and the one with which a run split
    into parts repeats the uninterrupted run exactly."""


_STRINGS = {"krylov": GMRES, "direct": Direct}
_KRYLOV = {"gmres": "jaxvisco", "lineax": "lineax"}


def krylov_backend(krylov):
    """`GMRES`'s backend for the 0.1 name `krylov` (``"gmres"`` or ``"lineax"``)."""
    if krylov not in _KRYLOV:
        raise ValueError(f"krylov must be one of {tuple(_KRYLOV)}, got {krylov!r}.")
    return _KRYLOV[krylov]


def from_legacy(linear_solver, krylov=None, krylov_max_steps=None, refresh_after=None):
    """The linear solver for `NewtonKrylov(linear_solver=..., [krylov, krylov_max_steps,
    refresh_after])`: an `AbstractLinearSolver` as given, a string of 0.1 as its object;
    the three keywords (deprecated) fill a `GMRES`."""
    if isinstance(linear_solver, str):
        if linear_solver not in _STRINGS:
            raise ValueError(f"linear_solver must be GMRES(...), Direct() or one of {tuple(_STRINGS)}, "
                             f"got {linear_solver!r}.")
        linear_solver = _STRINGS[linear_solver]()
    elif not isinstance(linear_solver, AbstractLinearSolver):
        raise ValueError(f"linear_solver must be GMRES(...), Direct() or one of {tuple(_STRINGS)}, "
                         f"got {linear_solver!r}.")
    legacy = {k: v for k, v in dict(krylov=krylov, krylov_max_steps=krylov_max_steps,
                                    refresh_after=refresh_after).items() if v is not None}
    if not legacy:
        return linear_solver
    warnings.warn(f"NewtonKrylov({', '.join(legacy)}=...) is deprecated: write NewtonKrylov(linear_solver=GMRES("
                  "backend=..., max_steps=..., refresh_after=...)).", DeprecationWarning,
                  stacklevel=5)  # NewtonKrylov's caller (past equinox's __init__ machinery)
    if not isinstance(linear_solver, GMRES):
        raise TypeError(f"NewtonKrylov: {', '.join(legacy)} set(s) GMRES, but linear_solver is {linear_solver!r}.")
    return GMRES(max_steps=int(legacy.get("krylov_max_steps", linear_solver.max_steps)),
                 refresh_after=int(legacy.get("refresh_after", linear_solver.refresh_after)),
                 backend=krylov_backend(krylov) if "krylov" in legacy else linear_solver.backend,
                 preconditioner=linear_solver.preconditioner, restart=linear_solver.restart,
                 multigrid_precision=linear_solver.multigrid_precision)
