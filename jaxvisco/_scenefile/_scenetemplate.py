"""The commented scene-file template printed by ``jaxvisco scene-template``.

It documents every key of the format (`_scenefile`) and runs as it stands: a clamped
strip under a tip load that is switched off at t = 1.
"""

TEMPLATE = '''\
# jaxvisco scene file (TOML). Run it with:   jaxvisco run SCENE.toml
# Every key is listed here; the ones commented out show alternatives. Paths are relative
# to this file. Vectors have one entry per space dimension (2 or 3). Arrays of tables
# ([[dirichlet]], [[load]], [[traction]]) are numbered from 1 in error messages.

[mesh]
# Either a mesh file (any format meshio reads: Gmsh .msh, Abaqus .inp, .vtu, ...), whose
# named groups (Gmsh physical groups, Abaqus *NSET / *ELSET / *SURFACE) may be used by name
# below ...
# file = "beam.msh"
# ... or a built-in generator: "rectangle" (nx, ny, lx, ly, origin), "box" (nx, ny, nz,
# lx, ly, lz, origin) or "lshape" (dim, refinement: the paper's L-shaped block).
generator = "rectangle"
nx = 8                       # cells along x
ny = 2                       # cells along y
lx = 4.0                     # side lengths (default 1)
ly = 1.0
# origin = [0.0, 0.0]        # lower corner (default the origin)
cell_type = "quad4"          # optional: the element (generators: quad4, quad8, quad9, tri3, tri6,
                             # hex8, hex20, hex27, tet4, tet10); with a file, keep only these cells
# quadrature_order = 3       # optional: spatial quadrature order (default: the element's full rule)

# Extra node groups selected by coordinate ranges, for meshes without groups (a group's
# name may not repeat one of the mesh file's). A node belongs to the group when every
# coordinate given lies in its inclusive range [lo, hi] (a number v means [v, v]), with
# a tolerance of 1e-9 times the mesh's bounding-box diagonal. Keys: x, y, z.
[groups.clamp]
x = [0.0, 0.0]

[groups.tip]
x = 4.0

[groups.top]
y = 1.0

[material]
# Neo-Hooke energy (Lame constants lam, mu); with eta_dev or eta_vol the same Neo-Hooke
# data also form the viscous (non-equilibrium) branch of the Reese-Govindjee model.
# Without both (or both = inf) the body is elastic: one branch, no internal variable.
lam = 30000.0
mu = 7500.0
eta_dev = 5000.0             # deviatoric viscosity (> 0; inf: no deviatoric flow)
eta_vol = inf                # volumetric viscosity (> 0; inf: no volumetric flow)
# Different branches instead of lam/mu above:
# [material.equilibrium]     lam = ...  mu = ...
# [material.nonequilibrium]  lam = ...  mu = ...   (omit for an elastic body)
density = 8.93               # reference mass density (> 0), required
mass = "consistent"          # or "lumped" (HRZ diagonal mass)
# Parts of other materials: the cells of a cell group (Gmsh physical surface/volume,
# Abaqus *ELSET, or the cells whose nodes all lie in a [groups] group) take the keys
# given here (lam, mu, eta_dev, eta_vol or the branch tables, density) and [material]'s
# others.
# The materials of one body must all be viscous or all elastic. Without lam/mu in
# [material] the parts must cover every cell.
# [[material.part]]
# cells = "tip"
# mu = 15000.0

[initial]                    # optional: the body starts at rest in the mesh's positions
# velocity = [0.0, 0.0]      # rigid translation v_T
# angular_velocity = 0.0     # rigid rotation omega: a number in 2D, a vector in 3D;
# center = [0.0, 0.0]        # v0 = v_T + omega x (X - center)  (center default the origin)
# [[initial.velocity_field]] # then the velocity of a node group (these win where they
# nodes = "tip"              # overlap the rigid motion; later entries win over earlier)
# value = [0.0, 1.0]

[[dirichlet]]                # position components held at their initial values
nodes = "clamp"              # a node group, or a list of them (mesh file or [groups])
components = "all"           # "all", or a list of "x", "y", "z" (or 0, 1, 2)
# displacement = [0.1, 0.0]  # optional: prescribed motion x0 + g(t) * displacement of
# time = { type = "ramp", t0 = 0.0, t1 = 1.0 }   # the held components (needs `time`,
                             # g(0) = 0; entries of components not held must be 0)

[[load]]                     # a dead nodal force, applied to EACH node of the group
nodes = "tip"
force = [0.0, -2.0]
# The time function g(t) that scales it (default 1; a number c: the constant c). Types and
# their keys (the same for [[traction]] and a prescribed [[dirichlet]]):
#   { type = "constant", value = 1.0 }
#   { type = "step", at = 1.0, before = 0.0, after = 1.0 }   (after from t = at on)
#   { type = "ramp", t0 = 0.0, t1 = 1.0, v0 = 0.0, v1 = 1.0 } (constant outside [t0, t1])
#   { type = "table", times = [0.0, 1.0, 2.0], values = [0.0, 1.0, 0.0] } (linear between)
#   { type = "sine", period = 1.0, amplitude = 1.0, phase = 0.0, offset = 0.0 }
time = { type = "step", at = 1.0, before = 1.0, after = 0.0 }

[[traction]]                 # a dead surface load on boundary facets
facets = "top"               # a facet group of the mesh file (Gmsh boundary lines/faces,
                             # Abaqus *SURFACE), or a node group: its boundary facets
traction = [0.0, -0.5]       # force per reference area (length in 2D) ...
# pressure = 1.0             # ... or a pressure (> 0 pushes into the body)
time = { type = "step", at = 1.0, before = 1.0, after = 0.0 }

[integrator]
name = "eG"                  # cG, eG (energy-consistent), Newmark or Midpoint
order = 1                    # polynomial degree k of cG(k) / eG(k)
# quadrature = 2             # Gauss points in time of cG/eG (default k; jaxvisco.eG(k, quadrature=))

# [solver]                   # optional: the Newton root finder (jaxvisco.NewtonKrylov's keywords)
# rtol = 1e-10               # also: max_iterations, linear_solver ("gmres" or "direct"),
#                            # line_search, stall_limit, reuse_limit, reuse_band, chord,
#                            # chord_contraction, retain
# [solver.gmres]             # optional: its linear solver (jaxvisco.GMRES's keywords)
# max_steps = 60             # also: refresh_after, backend ("jaxvisco"/"lineax"),
#                            # preconditioner ("auto"/"lu"/"amg": the block solve of
#                            # GMRES; "amg" is multigrid, for large 3D meshes),
#                            # restart (GMRES's basis length), multigrid_precision
#                            # ("single"/"double": the multigrid's arithmetic)

[time]                       # the names of jaxvisco.simulate
# t0 = 0.0                   # start time (default 0)
t1 = 3.0                     # end time (default: the schedule's last time)
dt0 = 0.05                   # a constant step ...
# schedule = [[1.0, 0.05], [3.0, 0.1]]   # ... or steps [t_until, dt] (piecewise constant)
# rtol = 1e-4                # ... or error-controlled steps (jaxvisco.PIDController; atol
# atol = 1e-4                # defaults to rtol); dt0 is then the first step tried
max_halvings = 6             # a failed step is halved at most this often

[saveat]                     # what to keep (jaxvisco.SaveAt)
every = 1                    # keep every n-th step
gamma = false                # also store the internal variable

[output]                     # optional; command-line options override these
file = "scene.h5"            # results file (default: this file's name with .h5)
# chunk = 50                 # at most this many steps per compiled call
# commit_every = 5.0         # commit at least about every so many seconds (0: every chunk)

# Names of jaxvisco 0.1, still read (with a deprecation note): [time] t_end = t1, dt = dt0;
# [output] save_every = [saveat] every, save_gamma = [saveat] gamma; [solver] krylov,
# krylov_max_steps, refresh_after, preconditioner, restart, multigrid_precision =
# [solver.gmres] backend ("gmres" = "jaxvisco"), max_steps, refresh_after, ...
'''
