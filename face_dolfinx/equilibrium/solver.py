"""Quasistatic equilibrium by PETSc SNES, with an inversion guard and a continuation fallback.

Newton with a critical-point line search (PETSc ``cp``: the residual is the gradient of the
energy, so it finds where R(u + s du) . du = 0) solves R(u) = 0 for the given controls. New
Dirichlet values enter through the first Newton step (lifting), which spreads a bone motion
smoothly into the flesh instead of shearing the layer of elements next to the bone.

Far from equilibrium a full Newton step of this stiff, nearly incompressible material inverts
elements (NaN residual). An ``InversionGuard`` pre-check halves each step until no cell would be
flattened below a tenth of its rest volume, and a Newton that keeps being cut that way gives up
early. When Newton fails anyway (the tangent is indefinite far from equilibrium, the line search
stalls), ``solve_continuation`` restarts from the last equilibrium and walks the controls towards
the target in steps that halve on failure and grow again on success; the log says so. Measured on
the 50K face, rest -> smile / jaw opening / pucker: 11 / 17 / 20 Newton iterations before the
guard, 7 / 20 / 9 with it (only the jaw opening still needs the fallback).

Newton stops when the residual norm is below ``snes_atol`` (mN) or when its last correction moved
no dof by more than ``step_tolerance`` (mm): a solve started at an equilibrium whose residual sits on
its round-off floor just above ``snes_atol`` then stops after one tiny step instead of stalling.
With energy terms (contact) and an ``energy_tolerance`` (mN mm), Newton also stops once its last
correction du would release less energy than that, by the quadratic model of the tangent it came
from (R . du / 2, half the squared Newton decrement; the interior-point methods' test): pressed lips
slide along each other in nearly free modes where a correction moves a node by a millimetre for a
micro-joule, so that a bound on the correction's largest move keeps Newton iterating on a state
whose energy, and fit, no longer change. Neither test stops Newton before the Dirichlet dofs hold
their values: a step that the inversion guard or a collision-free bound shortened moved the bones
only that part of the way.

A ``FactorReusePolicy`` decides when Newton assembles and factorises the tangent and when it keeps
the factor it has: by default a fresh factor at every iteration until Newton is converging (the
last correction moved no dof by more than ``CONVERGING_CORRECTION`` and cut the residual 4-fold),
after which the factor of its last tangent finishes the solve. Optionally (``across_solves``, the
problem's ``reuse_factorization``) Newton keeps the last MUMPS factor as its matrix (modified
Newton) for as long as every iteration cuts the residual norm by ``refresh_contraction`` (default
``REFRESH_CONTRACTION``) or more, and a fresh factor for one more iteration whatever its cut, across
solves too: between nearby equilibria (frames of a take)
an iteration then costs a residual and a solve instead of an assembly and a factorisation. With
energy terms a cut too slow is judged again by the residual's energy norm, R . K0^-1 R (one solve
with the old factor K0), which the pressed lips' stiff barrier rows weigh little.
``factor_distance()`` says how far the unknown has moved from the state whose tangent the factor
holds, for callers that can use a nearby tangent (approximate Jacobians); ``factorize(newton_model=True)``
gives such a caller Newton's tangent at the unknown, which the next Newton solves keep as theirs.

Energy terms evaluated outside UFL (``energy_terms``, e.g. the contact barrier of
``face_dolfinx.physics.contact``) add to the total energy: each gives its energy, adds its gradient to
the residual and its Hessian to the assembled tangent (so the tangent stays that of one energy), and
bounds each Newton step next to the inversion guard (``step_fraction``: no line-search point may
leave the term's domain, e.g. penetrate an object). With no terms none of this runs: the Newton
iterates are those of the UFL energy alone, to the bit.

The tangent's structure is a setting (``tangent``): "spd" for the face, whose symmetric tangent
MUMPS factorises without pivoting (with a pivoting retry after a zero pivot), "symmetric" for a
symmetric indefinite one, "general" for a non-symmetric one (a follower load). Every option is a
PETSc option under the solver's prefix (default ``face_``, see ``PetscOptionsPrefix``), so a user
can override any of them from the command line.
"""
from dataclasses import dataclass
import logging
import math
import time
from typing import Callable

from mpi4py import MPI
from petsc4py import PETSc
import numpy as np
import ufl
from dolfinx import fem
import dolfinx.fem.petsc as fem_petsc
from dolfinx.fem.assemble import pack_coefficients

from face_dolfinx.equilibrium.relaxation import ContactRelaxation

log = logging.getLogger(__name__)
# Every Newton iteration, for diagnosing slow solves: not part of -v (a 404K tracked frame makes tens of
# lines); switched on by setting this logger to DEBUG (benchmarks/contact_tracking.py --trace-newton).
trace = logging.getLogger(__name__ + ".iterations")
trace.setLevel(logging.INFO)

# MUMPS Cholesky (LDL^T for indefinite tangents): at 212K dofs one factorisation served dozens of
# right-hand sides far faster than CG + BoomerAMG did. METIS ordering (icntl 7 = 5) was fastest.
DEFAULT_PETSC_OPTIONS = {
    "snes_type": "newtonls",
    # cp + continuation took 27 s for the demo's five expressions at 50K tets where backtracking
    # on the residual norm (bt, which also cuts steps into inversion) took 42 s.
    "snes_linesearch_type": "cp",
    "snes_rtol": 1e-10,
    "snes_atol": 1e-9,
    "snes_stol": 0.0,
    "snes_max_it": 25,
    "ksp_type": "preonly",
    "pc_type": "cholesky",
    "pc_factor_mat_solver_type": "mumps",
    "mat_mumps_icntl_7": 5,
    "mat_mumps_icntl_14": 80,
}

# Factorisation reuse (``reuse_factorization=True``): a Newton iteration with the old factor is
# kept while the residual norm falls at least this much per iteration; a slower one refreshes the
# factor at the current iterate. A factorisation costs about as much as ten residual evaluations and
# solves at 200K dofs, so a contraction of 0.25 or better pays for itself.
REFRESH_CONTRACTION = 0.25
# ... and a correction from the old factor that an energy term's collision-free bound cut below this
# fraction of its length refreshes it unless the residual norm fell as a step of that length should,
# whatever its energy norm did: the factor does not hold the barrier of the pairs that cut it (pairs
# that came close since it was made), and kept, its corrections crept, each cut shorter than the
# last (51 in a row at 0.002-0.16 of their length in a 404K frame from rest, the residual falling
# 1-3 % per iteration; docs/performance.md, "Cut corrections refresh the factor").
JUDGED_STEP_BOUND = 0.2

# ``krylov_on_old_factor`` (with factorisation reuse): each Newton correction is solved by GMRES on
# the exact tangent, applied matrix-free (a residual evaluation per product), preconditioned by the
# old factor, Eisenstat-Walker setting how exactly; the factor is refreshed only when a linear solve
# needs more than KRYLOV_REFRESH_ITERATIONS (a GMRES solve that stops at ksp_max_it still yields its
# best step). Measured at 404K tets tracking (docs/performance.md): 1 factorisation per frame
# instead of 3-5, but 64-95 residual evaluations and 46-63 solves (0.28 s each), so no faster
# than refactorising; it pays where a factorisation costs far more than a solve.
KRYLOV_REFRESH_ITERATIONS = 8
# ... or when the residual fell by less than this per Newton iteration over the last two: GMRES on the old
# factor converging in few iterations does not mean Newton progresses. On a 20K tracking frame
# with lip and teeth contact, Newton kept the factor for 100 iterations (~9 residuals each) at a
# time and never converged (docs/performance.md, "Contact in tracking").
KRYLOV_STALL_CONTRACTION = 0.9
KRYLOV_OPTIONS = {
    "snes_mf_operator": None,
    "snes_ksp_ew": None,
    # Eisenstat-Walker's default cap (0.9) let GMRES stop after one iteration while Newton crawled
    # (18 iterations on a tracking frame at 50K tets).
    "snes_ksp_ew_rtolmax": 0.1,
    "ksp_type": "gmres",
    "ksp_rtol": 1e-3,
    "ksp_max_it": 15,
    "snes_max_linear_solve_fail": 1000,
}

# mm: once a Newton correction moved no dof further than this (and cut the residual by
# REFRESH_CONTRACTION), the iterate is close enough for the factor of this solve's last tangent to
# finish the job: the last two factorisations of a solve become cheap modified-Newton iterations.
# Measured on the 50K face, rest -> smile / pucker / jaw opening: 7 / 9 / 19 factorisations ->
# 5 / 7 / 17 (10 / 12 / 27 iterations); at 50K a factorisation costs about what the extra
# iterations do, at 400K several times more (docs/performance.md).
CONVERGING_CORRECTION = 0.1
# Iterations a converging phase may run past the iteration limit: enough to take a correction of
# CONVERGING_CORRECTION below the converging phase's step tolerance (1e-10 mm) at a contraction of 4.
CONVERGING_PHASE_ITERATIONS = 15
# mN/mm: a converging phase stops on its step only once the residual is also below this times the
# step tolerance (1e-6 mN at the default 1e-8 mm; ``_converged``): the flesh's stiffness, about
# 10-100 mN/mm, turns a correction into a residual. A sphere pressed 5 mm into the small face's
# cheek, 2-3e4 mN/mm stiff at the end, stopped at a correction of 2e-11 mm with 6.8e-7 mN left on
# one rank and 2.0e-6 on two.
RESIDUAL_PER_STEP = 100.0

# Inversion guard (see InversionGuard, _precheck): measured on the 50K face (rest -> smile,
# jaw opening, pucker), cp capped at lambda <= 1 stalled on the pucker and uncapped ran into
# inverted elements; a cap of 2 with stall detection converged all three without continuation
# except the jaw opening.
GUARDED_MAX_LAMBDA = 2.0
STALLED_GUARD_FRACTION = 0.25
STALLED_GUARD_ITERATIONS = 3

# A Newton step whose directional derivative of the energy, relative to |R| |step|, lies above
# -DESCENT_ROUND_OFF still counts as descending (round-off near convergence).
DESCENT_ROUND_OFF = 1e-12

# Continuation gives up when CREEP_LOAD_STEPS load steps in a row, taken or failed, were no
# longer than CREEP_STEP of the way (``solve_continuation``).
CREEP_STEP = 1.0 / 128.0
CREEP_LOAD_STEPS = 16

# ``contact_relaxation=None``: the relaxation of the contact nodes starts, for the rest of a Newton
# solve, once this many corrections in a row were cut by the collision-free bound of an energy term
# that says ``relax_on_crawl`` (the lips') with at least CRAWL_CONTACT_SHARE of the residual's square
# on the contact surfaces' nodes: the lips peeling apart on the 404K face, where one edge-edge pair
# at the front set every bound and the rest of the face was in equilibrium (89 Newton iterations,
# 48 factorisations; 17 and 10 relaxed, from the start; docs/performance.md, "The lips' opening").
# Well-behaved 404K warm solves had at most 3 such corrections in a row; the 5K lips closing from
# rest had 15 and more, with about 15 % of the residual's square on the lips. (Cuts by the teeth's
# bound do not count: on the 5K face they started it in a solve from rest, which then reached
# another equilibrium of the pressed lining, from which a prediction's Newton failed,
# tests/test_teeth.py.)
CRAWL_CUTS = 6
CRAWL_CONTACT_SHARE = 0.9
# ``contact_relaxation=None`` with the factor kept across solves: where the residual's slow fall
# would refresh the factor and the nodes of the contact surfaces of terms that say
# ``relax_on_slow_fall`` (the teeth's, an object's, the lips') hold at least this share of the
# residual's square, the relaxation starts instead and the factor is kept (``_relaxes_instead``).
# The small face's lips pressed on the teeth, the orbicularis oris raised by half: 3
# factorisations instead of 9 (from 0.5 to 0.9 of the residual's square on the teeth's nodes);
# 404K tracking with the lips open: 0.85-0.997 where the factor was refreshed
# (docs/performance.md, "Settling on the teeth").
SLOW_FALL_CONTACT_SHARE = 0.5
# ``reuse_factorization``: an old factor whose corrections an energy term's bound cut in this many
# iterations in a row (``FactorReusePolicy.crawl_refresh_iterations``), each cutting the residual by
# less than 1 - CRAWL_REFRESH_CONTRACTION, is refreshed however well that matched the shortened
# steps' length: the lips' second closure on the 404K face crept for 35 such iterations on a factor
# made before the lips came close; refreshed after six, the next correction cut the residual 19-fold
# (docs/performance.md, "An old factor refreshed where bounded steps crawl").
CRAWL_REFRESH_ITERATIONS = 6
CRAWL_REFRESH_CONTRACTION = 0.9

# mm: a Dirichlet gap this small is closed by moving the bone nodes, not by more lifting.
SNAP_DISTANCE = 1e-3
# mm: a solve has reached its Dirichlet values once no Dirichlet dof is further from its value.
DIRICHLET_TOLERANCE = 1e-8

# C compiler flags of the generated kernels (compiled once per form, then taken from the cache).
JIT_OPTIONS = {"cffi_extra_compile_args": ["-O3", "-march=native"], "cache_dir": None}

# How the tangent is flagged for the factorisation (see QuasistaticSolver, ``tangent``).
TANGENT_STRUCTURES = ("spd", "symmetric", "general")


class EquilibriumError(RuntimeError):
    """No equilibrium found even with the continuation fallback."""


@dataclass
class SolveReport:
    """What one equilibrium solve did: Newton iterations over all load steps, steps taken."""

    converged: bool
    newton_iterations: int
    load_steps: int
    reason: str
    seconds: float


def compile_form(form: ufl.Form) -> fem.FormMetaClass:
    """Compile a UFL form once with the project's JIT options (the cache makes reruns free)."""
    return fem.form(form, jit_params={k: v for k, v in JIT_OPTIONS.items() if v is not None})


def global_sum(comm: MPI.Comm, local_value: float) -> float:
    return comm.allreduce(local_value, op=MPI.SUM)


class InversionGuard:
    """Shortens a Newton step that would flatten or invert a tetrahedron.

    Far from equilibrium (rest -> all muscles on, a wide jaw opening) the full Newton step of this
    stiff, nearly incompressible material inverts elements; the residual is then NaN and the whole
    solve used to be thrown away for continuation. Before the line search, the step is halved until
    every cell keeps at least ``min_volume_ratio`` of its rest volume (measured on the cell's
    vertices, exact for P1, the straight-sided part of a P2 cell). Cheap: a few numpy determinants
    per cell and Newton iteration. ``cells`` (local indices): guard these cells only, for a step
    that moves no vertex of the others (``restricted``).
    """

    def __init__(self, space: fem.FunctionSpace, min_volume_ratio: float = 0.1, max_halvings: int = 12,
                 cells: np.ndarray | None = None):
        num_cells = space.mesh.topology.index_map(3).size_local + space.mesh.topology.index_map(3).num_ghosts
        # Basix numbers the vertex dofs of a tetrahedron first, for P1 and P2 alike.
        self.vertex_blocks = space.dofmap.list.array.reshape(num_cells, -1)[:, :4]
        if cells is not None:
            self.vertex_blocks = self.vertex_blocks[cells]
        self.rest_points = space.tabulate_dof_coordinates()[:, :3][self.vertex_blocks]
        self.rest_volume = _signed_volumes(self.rest_points)
        self.space = space
        self.min_volume_ratio = min_volume_ratio
        self.max_halvings = max_halvings
        self.comm = space.mesh.comm

    def restricted(self, cells: np.ndarray) -> "InversionGuard":
        """The same guard over ``cells`` (local indices) only."""
        return InversionGuard(self.space, self.min_volume_ratio, self.max_halvings, cells)

    def min_ratio(self, displacement: np.ndarray) -> float:
        """Smallest current/rest volume ratio over the guarded cells of all ranks."""
        points = self.rest_points + displacement.reshape(-1, 3)[self.vertex_blocks]
        local = float((_signed_volumes(points) / self.rest_volume).min(initial=np.inf))
        return self.comm.allreduce(local, op=MPI.MIN)

    def step_fraction(self, displacement: np.ndarray, step: np.ndarray, largest: float = 1.0) -> float:
        """Largest ``largest`` * 2^-k such that displacement - that * step keeps every cell above
        the bound (or, if a cell is already below it, does not halve its volume again)."""
        bound = self._bound(displacement)
        fraction = largest
        for _ in range(self.max_halvings):
            if self.min_ratio(displacement - fraction * step) >= bound:
                return fraction
            fraction *= 0.5
        return fraction

    def flattens(self, start: np.ndarray, end: np.ndarray) -> bool:
        """Whether the straight move from the displacement ``start`` to ``end`` takes a cell below
        the bound of ``step_fraction`` (collective)."""
        return self.step_fraction(start, start - end) < 1.0

    def flattened_blocks(self, displacement: np.ndarray, step: np.ndarray) -> np.ndarray:
        """Local blocks (ghosts included) of the vertices of the guarded cells that displacement +
        step takes below the bound of ``step_fraction`` (on this rank's cells)."""
        bound = self._bound(displacement)
        points = self.rest_points + (displacement + step).reshape(-1, 3)[self.vertex_blocks]
        return np.unique(self.vertex_blocks[_signed_volumes(points) / self.rest_volume < bound])

    def _bound(self, displacement: np.ndarray) -> float:
        """The volume ratio a step from ``displacement`` keeps every cell above."""
        return min(self.min_volume_ratio, 0.5 * self.min_ratio(displacement))


def widened_tangent(A: PETSc.Mat, form: fem.FormMetaClass, pairs: np.ndarray) -> PETSc.Mat:
    """A matrix like ``A`` (the form's tangent, not yet assembled: same layout and local-to-global
    map) whose sparsity also holds the 3 x 3 blocks of ``pairs``, (k, 2) global node (block)
    indices; this rank keeps the pairs whose first node it owns. Entries outside it are still
    accepted (a new nonzero; the factorisation then analyses the changed pattern again)."""
    fem_petsc.assemble_matrix(A, form)
    A.assemble()
    indptr, indices, _ = A.getValuesCSR()
    first, last = A.getOwnershipRange()
    bs = A.getBlockSize()
    rows = np.repeat(np.arange(first, last), np.diff(indptr))
    mine = pairs[(pairs[:, 0] >= first // bs) & (pairs[:, 0] < last // bs)]
    component = np.arange(bs)
    extra_rows = (bs * mine[:, :1, None] + component[None, None, :]).repeat(bs, axis=1).reshape(-1)
    extra_columns = (bs * mine[:, 1:, None] + component[None, None, :]).repeat(bs, axis=2).reshape(-1)
    entries = np.unique(np.column_stack([np.concatenate([rows, extra_rows]),
                                         np.concatenate([indices, extra_columns])]), axis=0)
    counts = np.bincount(entries[:, 0] - first, minlength=last - first)
    widened = PETSc.Mat().create(comm=A.getComm())
    widened.setSizes(A.getSizes(), bsize=bs)
    widened.setType(A.getType())
    widened.setPreallocationCSR((np.concatenate([[0], np.cumsum(counts)]).astype(PETSc.IntType),
                                 entries[:, 1].astype(PETSc.IntType)))
    widened.setLGMap(*A.getLGMap())
    widened.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, False)
    A.destroy()
    return widened


def _signed_volumes(points: np.ndarray) -> np.ndarray:
    """Six times the signed volume of tetrahedra given as (cells, 4, 3) vertex positions (the
    triple product written out: at 200K cells 17 ms, np.cross with einsum 20-23 ms, a batched
    np.linalg.det 1.6x slower still)."""
    edges = points[:, 1:] - points[:, :1]
    a, b, c = edges[:, 0].T, edges[:, 1].T, edges[:, 2].T
    return (a[0] * (b[1] * c[2] - b[2] * c[1]) + a[1] * (b[2] * c[0] - b[0] * c[2])
            + a[2] * (b[0] * c[1] - b[1] * c[0]))


class PackedCoefficients:
    """A form's coefficient data, packed once and kept: before each assembly only the unknown's
    columns are refreshed from it; everything is repacked after ``stale`` was set (another
    coefficient changed). DOLFINx 0.5 packs every coefficient anew for every assembly: at 404K
    tets, 85-99 ms of a 138 ms residual assembly with the face's 16 coefficients.
    """

    def __init__(self, form: fem.FormMetaClass, unknown: fem.Function):
        self.form, self.unknown = form, unknown
        # Where the unknown's values go: pack with each value set to 1 + its local index.
        values = unknown.x.array
        kept = values.copy()
        values[:] = 0.0
        without = pack_coefficients(form)
        values[:] = 1.0 + np.arange(values.size)
        marked = pack_coefficients(form)
        values[:] = kept
        self._scatter = {}
        for key, array in marked.items():
            columns = np.flatnonzero(np.any(array != without[key], axis=0))
            index = (array[:, columns] - 1.0).astype(np.int64)
            if columns.size and np.array_equal(columns, np.arange(columns[0], columns[-1] + 1)):
                columns = slice(columns[0], columns[-1] + 1)  # a block: written 1.5x faster
            self._scatter[key] = (columns, index)
        self.stale = True
        self._packed = None

    def packed(self) -> dict:
        """Coefficient data for the unknown's current values (ghosts included)."""
        if self.stale:
            self._packed, self.stale = pack_coefficients(self.form), False
            return self._packed
        values = self.unknown.x.array
        for key, (columns, index) in self._scatter.items():
            self._packed[key][:, columns] = values[index]
        return self._packed


class FactorReusePolicy:
    """Decides, before each Newton iteration's tangent, whether the iteration keeps the factor it
    has (a modified Newton iteration: a residual and a solve) or assembles and factorises the
    tangent at its iterate.

    ``across_solves`` False: a fresh factor at every iteration until Newton is converging (its last
    correction moved no dof by more than ``converging_correction`` mm and cut the residual by
    ``refresh_contraction``); from there this solve's last factor finishes the job for as long as
    two iterations together contract as fast. ``across_solves`` True (``reuse_factorization``): the
    last factor, from whichever solve, is kept for as long as every iteration cuts the residual by
    ``refresh_contraction`` or more (a step that an energy term's collision-free bound shortened, of
    which the line search took a fraction t of the correction, ``record_taken``: by 1 - t (1 -
    ``refresh_contraction``), what a Newton step of that length achieves), and a fresh one for the
    next iteration at least: a fresh tangent whose correction cut the residual slowly tells of the
    problem's nonlinearity (a contact barrier settling), not of a stale factor, and another
    factorisation at once bought nothing (20K tracked frames with lip and teeth contact,
    docs/performance.md); or, with Krylov on the old factor, a linear solve takes no more than
    ``krylov_refresh_iterations`` and the residual falls by ``KRYLOV_STALL_CONTRACTION`` or more per
    iteration over the last two. Across solves with corrections by the factor alone, an old factor
    whose corrections an energy term's bound cut in ``crawl_refresh_iterations`` iterations in a
    row, each cutting the residual by less than 1 - CRAWL_REFRESH_CONTRACTION, is refreshed however
    well that matched the steps' length: the bound may be the factor's doing, the barrier stiffness
    of what came close since not in it. Either way a step that the inversion guard had to cut
    (shorter than the energy terms' bounds cut it) refreshes the factor (it says the factor is
    stale, not that Newton stalls), unless ``keeps_cut_fresh_factor`` (a lifting solve,
    ``QuasistaticSolver.newton``) and the factor is fresh: then it is kept for one more iteration.

    With energy terms the solver also gives ``keep_factor`` the old factor's correction at the
    current iterate as the energy it would release (``old_factor_release``): where the residual
    norm fell too slowly, the factor is still kept if that energy norm of the residual, squared
    (R . K0^-1 R), fell by the square of the ratio expected of the residual norm since the last
    correction of the same factor, or if that correction releases less than Newton's
    ``energy_tolerance`` (the solve stops after it); never if it climbs the energy, nor after a
    correction that the bound cut below ``judged_step_bound`` of its length. The pressed lips'
    barrier rows hold most of the residual's norm but, being stiff, little of its energy; a fresh
    tangent does not settle them faster (docs/performance.md, "Judged by energy").

    The solver reports each residual norm (``record_residual``), each Newton correction
    (``record_correction``) and each factorisation (``factorised``), and asks ``keep_factor``.
    """

    def __init__(self, across_solves: bool = False, refresh_contraction: float = REFRESH_CONTRACTION,
                 converging_correction: float = CONVERGING_CORRECTION,
                 krylov_refresh_iterations: int = KRYLOV_REFRESH_ITERATIONS,
                 judged_step_bound: float = JUDGED_STEP_BOUND,
                 crawl_refresh_iterations: int | None = CRAWL_REFRESH_ITERATIONS):
        self.across_solves = across_solves
        self.crawl_refresh_iterations = crawl_refresh_iterations  # None: never for a crawl
        self.judged_step_bound = judged_step_bound
        self.refresh_contraction = refresh_contraction
        self.converging_correction = converging_correction  # 0: a fresh factor every iteration
        self.krylov_refresh_iterations = krylov_refresh_iterations
        self.has_factor = False          # some tangent has been factorised (and not forgotten)
        self.refreshed_in_solve = False  # ... by the Newton solve under way
        self.fresh_factor = True         # the current iteration's correction comes from its own tangent
        self.step_was_cut = False        # the inversion guard shortened the last correction
        self.keeps_cut_fresh_factor = False  # a fresh factor the guard cut is kept once (a lifting solve)
        self.step_bound = 1.0            # fraction of the last correction the energy terms allowed
        self.step_taken = 1.0            # ... and the line search took of it
        self.correction_size = math.inf  # mm, largest dof change of the last correction
        self.contraction = 0.0           # residual norm ratio of the last iteration
        self.release = math.inf          # R . du of the last correction (mN mm)
        self.two_step_contraction = math.inf  # geometric mean of the last two ratios
        self.crawl = 0                   # old-factor iterations in a row with bounded steps and slow cuts
        self._last_norm = math.inf

    def start_solve(self) -> None:
        self.refreshed_in_solve = False

    def record_residual(self, iteration: int, norm: float) -> None:
        """The residual norm at the start of Newton iteration ``iteration`` (0: a new solve)."""
        if iteration == 0:
            self.step_was_cut, self.step_bound, self.step_taken = False, 1.0, 1.0
            self.correction_size, self.contraction = math.inf, 0.0
            self.two_step_contraction = math.inf
            self.crawl = 0
        else:
            self.two_step_contraction = math.sqrt(self.contraction * norm / max(self._last_norm, 1e-300))
            self.contraction = norm / max(self._last_norm, 1e-300)
        self._last_norm = norm

    def record_correction(self, size: float, cut: bool = False, bound: float = 1.0,
                          release: float = math.inf) -> None:
        """The last Newton correction moved a dof by at most ``size``; ``cut``: the inversion
        guard shortened it; ``bound``: the energy terms' collision-free bound let it go this
        fraction of the way; ``release``: R . du, the energy norm of the residual it came from."""
        self.correction_size, self.step_was_cut, self.step_bound, self.step_taken = size, cut, bound, bound
        self.release = release

    def record_taken(self, fraction: float) -> None:
        """The line search took ``fraction`` (2-norm) of the last correction, which an energy
        term's bound had shortened: its residual cut is judged by that length, not by the bound's
        (cp takes a bounded step once where the energy still falls beyond twice it)."""
        self.step_taken = min(1.0, fraction)

    def keep_factor(self, iteration: int, linear_iterations: int | None = None,
                    old_factor_release: Callable[[], float] | None = None, release_tolerance: float = 0.0,
                    relaxes_instead: Callable[[], bool] | None = None) -> bool:
        """Whether iteration ``iteration`` keeps the factor. ``linear_iterations``: the Krylov
        iterations of the last linear solve when corrections are solved by Krylov preconditioned
        by the factor (None: by the factor alone). ``old_factor_release``: R . K0^-1 R at the
        current iterate (a solve with the old factor), asked for only where the residual norm
        alone would refresh it; ``release_tolerance``: a correction releasing less (R . du / 2)
        ends the solve. ``relaxes_instead``: asked (``across_solves``) only where the residual's
        slow fall alone would refresh the factor, True where the solver relaxes the contact nodes
        from this iteration on instead; the factor is then kept."""
        crawled = (iteration > 0 and not self.fresh_factor and self.step_bound < 1.0
                   and self.contraction > CRAWL_REFRESH_CONTRACTION)
        self.crawl = self.crawl + 1 if crawled else 0
        # A bound that keeps cutting an old factor's corrections short may be the factor's doing:
        # the barrier stiffness of the pairs and nodes that came close since is not in it.
        crawling = (self.across_solves and self.crawl_refresh_iterations is not None
                    and self.crawl >= self.crawl_refresh_iterations)
        if linear_iterations is not None:
            contracting = (iteration > 0 and linear_iterations <= self.krylov_refresh_iterations
                           and self.two_step_contraction <= KRYLOV_STALL_CONTRACTION)
        else:
            # A step shortened to t of the correction cuts the residual of a quadratic model by t.
            expected = 1.0 - self.step_taken * (1.0 - self.refresh_contraction)
            contracting = iteration > 0 and self.contraction <= expected and not crawling
            if (not contracting and not crawling and old_factor_release is not None and self.across_solves
                    and iteration > 0
                    and self.has_factor and not self.fresh_factor and not self.step_was_cut
                    and self.step_bound >= self.judged_step_bound):
                release = old_factor_release()  # the energy norm, squared, both by the same factor
                contracting = 0.0 < release and (release <= expected**2 * self.release
                                                 or 0.5 * release < release_tolerance)
        if self.across_solves:
            keep = iteration == 0 or contracting or (linear_iterations is None and self.fresh_factor)
        else:
            # Modified-Newton residuals alternate between fast and slow cuts (0.017, 0.26, ... on
            # the 404K pucker), so once the factor is kept it is judged over two iterations: one
            # slow cut alone refactorised at a 1e-6 mm correction, 7 s of a 61 s solve.
            if not self.fresh_factor:
                contracting = iteration > 0 and self.two_step_contraction <= self.refresh_contraction
            keep = contracting and self.correction_size < self.converging_correction
        usable = self.has_factor and (not self.step_was_cut or (self.keeps_cut_fresh_factor and self.fresh_factor))
        keep = keep and usable
        if not keep and usable and relaxes_instead is not None and self.across_solves and iteration > 0:
            keep = relaxes_instead()
        self.fresh_factor = not keep
        return keep

    def factorised(self, in_newton: bool) -> None:
        """A tangent was factorised, by Newton (``in_newton``) or for other solves."""
        self.has_factor = True
        self.refreshed_in_solve = self.refreshed_in_solve or in_newton
        self.fresh_factor = self.fresh_factor or in_newton

    def forget_factor(self) -> None:
        """The factor must not be kept (a failed or reset factorisation): the next tangent is fresh."""
        self.has_factor = False

    @property
    def converging_phase(self) -> bool:
        """The current correction comes from an older factor of this solve (``across_solves``
        False): it contracts the residual only linearly."""
        return not (self.across_solves or self.fresh_factor)

    @property
    def used_only_an_old_factor(self) -> bool:
        """The solve under way has not factorised: every correction came from an older solve's
        factor (``across_solves``)."""
        return self.across_solves and not self.refreshed_in_solve


class PetscOptionsPrefix:
    """A solver's entries under ``prefix`` in PETSc's options database, which is global to the
    process.

    ``replace(options)`` writes each option unless the user gave it (command line, PETSC_OPTIONS,
    ``PETSc.Options()`` between solvers: a value other than the one a solver wrote): the user's
    value wins. It removes what an earlier solver with the same prefix wrote and this one does not
    want, so that every solver gets its own options.
    """

    # By prefix: each option a solver wrote, with its value as the database holds it.
    _written: dict[str, dict[str, str]] = {}

    def __init__(self, prefix: str):
        self.prefix = prefix

    def replace(self, options: dict) -> None:
        database = PETSc.Options()
        wanted = {self.prefix + key: value for key, value in options.items()}
        written = self._written.setdefault(self.prefix, {})
        for name in written.keys() - wanted.keys():
            if database.getString(name, None) == written.pop(name):
                database.delValue(name)
        for name, value in wanted.items():
            ours = name in written and database.getString(name, None) == written[name]
            if ours or not database.hasName(name):
                database[name] = value
                written[name] = database.getString(name)
            else:
                written.pop(name, None)  # the user's option


class QuasistaticSolver:
    """Newton (SNES) for R(u) = 0 with Dirichlet conditions ``bcs`` whose values the owner sets.

    ``tangent`` says how the tangent is factorised: "spd" (symmetric, MUMPS without numerical
    pivoting; a zero pivot makes that Newton solve start over with pivoting), "symmetric"
    (symmetric indefinite, with pivoting) or "general" (no symmetry, for LU). ``energy``
    (optional) is the total potential, for reports and checks. The line search does not
    backtrack on it: near equilibrium its changes drown in round-off and stall the search.
    ``reuse_policy`` decides when Newton refactorises (default: ``FactorReusePolicy()``).
    ``energy_terms``: energies outside UFL, each with ``energy(x)``, ``add_gradient(x, b)``,
    ``add_hessian(x, A, constrained)`` (A assembled; ``constrained``: the owned local Dirichlet dofs,
    whose rows and columns it leaves alone) and ``step_fraction(x, step, largest)`` (the largest t in
    (0, 1] such that x - s t largest step stays admissible for s in [0, 1]); x is the unknown's PETSc
    vector, all collective; ``label`` names it in the Newton trace, which also gives the residual's
    norm on the nodes of each term that has a ``surface`` (its ``ContactSurface``; the relaxation of
    the contact nodes needs it). A term whose Hessian couples nodes that share no element also has
    ``coupled_blocks()``, (k, 2) global node pairs: the tangent is built with room for them
    (``widened_tangent``). A term may change Newton's tangent (not the sensitivities'):
    ``add_newton_correction(x, A, constrained)``, True if it did, taken at every factorisation, or
    with ``exact_near_solution`` only until Newton is near the solution (``_newton_corrections``).
    A correction from a tangent that holds a term's exact Hessian (near the solution, or the
    sensitivities' factor kept across solves) that is no descent direction of the energy is solved
    again with every term's correction (``_refuse_exact_terms``; counted by
    ``refused_exact_tangents``): on such corrections Newton cycled, or converged to a maximum.
    ``flesh_correction`` (``definite.DefiniteFleshTangent``) changes Newton's tangent of the UFL
    energy itself the same way (with ``exact_near_solution``); its ``constrained`` are all local
    Dirichlet dofs, ghosts included, since it adds the stiffness of cells that share them.
    ``contact_relaxation``: True relaxes the contact nodes after every Newton correction
    (``relaxation.ContactRelaxation``), None from the correction at which a solve crawls on them,
    its corrections cut by the bound of a term that says ``relax_on_crawl`` (``CRAWL_CUTS``), or,
    with the factor kept across solves, at which the residual's slow fall on the nodes of a term
    that says ``relax_on_slow_fall`` would refresh the factor (``SLOW_FALL_CONTACT_SHARE``; the
    factor is kept there), False never.
    """

    def __init__(self, residual: ufl.Form, unknown: fem.Function, bcs: list, *, tangent: str,
                 jacobian: ufl.Form | None = None, energy: ufl.Form | None = None,
                 petsc_options: dict | None = None, options_prefix: str = "face_",
                 inversion_guard: InversionGuard | None = None,
                 reuse_policy: FactorReusePolicy | None = None, krylov_on_old_factor: bool = False,
                 step_tolerance: float = 1e-8, energy_tolerance: float | None = None,
                 keep_packed_coefficients: bool = False, energy_terms: tuple = (),
                 contact_relaxation: bool | None = None, flesh_correction=None):
        if tangent not in TANGENT_STRUCTURES:
            raise ValueError(f"tangent = {tangent!r}: give one of {', '.join(TANGENT_STRUCTURES)}")
        self.unknown = unknown
        self.inversion_guard = inversion_guard
        self.energy_terms = tuple(energy_terms)
        # The terms with a contact surface, and their nodes on this rank, all surfaces' last.
        self._surface_terms = [term for term in self.energy_terms if hasattr(term, "surface")]
        self._surface_blocks = [term.surface.owned_blocks for term in self._surface_terms]
        if self._surface_blocks:
            self._surface_blocks.append(np.unique(np.concatenate(self._surface_blocks)))
        # Newton's change to the flesh's own tangent (``definite.DefiniteFleshTangent``) or None.
        self.flesh_correction = flesh_correction
        self.reuse_policy = reuse_policy if reuse_policy is not None else FactorReusePolicy()
        # mm: Newton has converged once a correction moves no dof further than this. 1e-8 mm lies
        # far below anything measurable and above the round-off of the corrections.
        self.step_tolerance = step_tolerance
        # mN mm: with energy terms, Newton has converged once a correction would release less energy.
        if energy_tolerance is not None and not energy_tolerance > 0.0:
            raise ValueError(f"energy_tolerance = {energy_tolerance}: give a positive energy (mN mm) or None")
        self.energy_tolerance = energy_tolerance if self.energy_terms else None
        self._released = math.inf  # energy the last correction would release (R . du / 2, mN mm)
        self._bounded_norm = None  # 2-norm of the last correction, if an energy term's bound shortened it
        self._bounding_term = None  # the energy term whose bound cut the last correction most
        self._tracing = False  # the Newton trace is on (rank 0's logger, the same on every rank)
        # True: relax the contact nodes after every correction; None: once Newton crawls on them
        # (CRAWL_CUTS) or the residual falls slowly on them (SLOW_FALL_CONTACT_SHARE); False: never.
        self.contact_relaxation = contact_relaxation
        self._relaxing = False  # ... after the corrections of this Newton solve
        self._crawl_cuts = 0  # corrections in a row that a bound cut, the residual on the contact nodes
        self.energy_stops = 0  # Newton solves stopped by energy_tolerance
        self.factorizations = 0     # numerical factorisations so far (a cost counter)
        self.residual_evaluations = 0  # residual assemblies so far (matrix-free products included)
        self.linear_iterations = 0     # Krylov iterations (each one solve with the factor) so far
        self._factor_controls_current = False  # the factor holds a tangent of the controls now set
        self.factor_is_exact = True  # ... the exact one (no term's Newton correction in it)
        self.bcs = bcs
        self._factor_conditions = ()  # the Dirichlet conditions of the factor's tangent
        self._factor_has_exact_terms = False  # a term's exact Hessian (exact_near_solution) is in it
        self.refused_exact_tangents = 0  # tangents with exact terms whose correction climbed the energy
        # Whether such corrections are refused (``_refuse_exact_terms``); False only to measure it.
        self.refuse_ascent = True
        # Whether the reuse policy may keep a factor by the energy norm of the residual (with energy
        # terms, ``FactorReusePolicy.keep_factor``); False only to measure it.
        self.judge_factor_by_energy = True
        self.comm = unknown.function_space.mesh.comm
        self.residual_form = compile_form(residual)
        jacobian = jacobian if jacobian is not None else ufl.derivative(residual, unknown)
        self.jacobian_form = compile_form(jacobian)
        self.energy_form = compile_form(energy) if energy is not None else None
        # Only for an owner that calls controls_changed() whenever it changes a coefficient of
        # these forms other than the unknown.
        self._packs = ([PackedCoefficients(form, unknown) for form in (self.residual_form, self.jacobian_form)]
                       if keep_packed_coefficients else None)

        self._residual_vector = fem_petsc.create_vector(self.residual_form)
        self._residual_work = self._residual_vector.duplicate()
        self.tangent_structure = tangent
        self.tangent = self._create_tangent(self.jacobian_form)
        if tangent != "general":
            self.tangent.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        # "spd" makes MUMPS factorise without numerical pivoting (SYM = 1): 4.4-5.0 s instead of
        # 5.5 s at 404K tets, same solve residual (1e-12). Off equilibrium the face's tangent may
        # have a few negative pivots (2 of 237K seen mid-Newton on the pucker), which this LDL^T
        # factorises as well. A zero pivot fails the factorisation (seen in jaw openings from rest
        # at 404K): newton() then drops the flag for that solve (_factorise_with_pivoting).
        self.tangent.setOption(PETSc.Mat.Option.SPD, tangent == "spd")
        self._pivoting = False
        self._solution = unknown.vector.duplicate()
        self._start = unknown.vector.duplicate()  # where the current Newton solve began
        self._factor_state = unknown.vector.duplicate()  # the unknown whose tangent was factorised
        self._distance_work = unknown.vector.duplicate()
        self._trial_correction = unknown.vector.duplicate()  # the old factor's, judged by its energy
        self._prescribed = None  # work vector of bc_error

        self.snes = PETSc.SNES().create(self.comm)
        self.snes.setOptionsPrefix(options_prefix)
        options = dict(DEFAULT_PETSC_OPTIONS)
        if krylov_on_old_factor:
            if not self.reuse_policy.across_solves:
                raise ValueError("krylov_on_old_factor needs reuse_factorization: without it every "
                                 "Newton iteration has a fresh factor and nothing to precondition")
            options.update(KRYLOV_OPTIONS)
        if inversion_guard is not None or self.energy_terms:
            options["snes_linesearch_maxstep"] = GUARDED_MAX_LAMBDA
        PetscOptionsPrefix(options_prefix).replace({**options, **(petsc_options or {})})
        self.snes.setFunction(self._assemble_residual, self._residual_vector)
        self.snes.setJacobian(self._assemble_tangent, self.tangent)
        self.snes.setConvergenceTest(self._converged)
        self._guard_x, self._guard_step = unknown.vector.duplicate(), unknown.vector.duplicate()
        # Nonlinear elimination of the contact nodes after each correction (relaxation.py).
        self.relaxation = None
        if contact_relaxation is not False and self.energy_terms and len(self._surface_terms) == len(self.energy_terms):
            self.relaxation = ContactRelaxation(
                residual, jacobian, unknown.function_space, self.energy_terms, unknown.vector,
                assemble=self._residual_of, full_residual=lambda x, b: self._assemble_residual(self.snes, x, b),
                guard=inversion_guard, compile_form=compile_form, create_matrix=self._create_tangent)
            self._relaxed = unknown.vector.duplicate()
        self.snes.setLineSearchPreCheck(self._precheck)
        self.snes.setFromOptions()
        self.snes.getKSP().setFromOptions()
        # PETSc ends Newton at its own limit whatever the convergence test says: it gets room for a
        # converging phase past the limit ``_converged`` applies (snes_max_it, iteration_limit).
        self.iteration_limit = self.snes.getTolerances()[3]
        self.snes.setTolerances(max_it=self.iteration_limit + CONVERGING_PHASE_ITERATIONS)

    def _create_tangent(self, form: fem.FormMetaClass) -> PETSc.Mat:
        """A matrix for ``form``'s tangent whose sparsity also holds the energy terms' couplings."""
        A = fem_petsc.create_matrix(form)
        coupled = [term.coupled_blocks() for term in self.energy_terms if hasattr(term, "coupled_blocks")]
        return widened_tangent(A, form, np.concatenate(coupled)) if coupled else A

    # -- callbacks ---------------------------------------------------------------------------
    def _set_unknown(self, x: PETSc.Vec) -> None:
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        x.copy(self.unknown.vector)
        self.unknown.vector.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)

    def _assemble_residual(self, snes, x, b):
        self.residual_evaluations += 1
        self._residual_of(x, b, self.residual_form, self.jacobian_form, packed=True)

    def _residual_of(self, x: PETSc.Vec, b: PETSc.Vec, residual_form: fem.FormMetaClass,
                     jacobian_form: fem.FormMetaClass, packed: bool = False) -> None:
        """b = the residual at x of ``residual_form`` (``jacobian_form``, its tangent, for the
        lifting) and the energy terms, Dirichlet rows zero; ``packed``: the forms are the solver's
        own, whose kept coefficient data serve."""
        self._set_unknown(x)
        packs = packed and self._packs is not None
        # Matrix-free products (-snes_mf_operator) evaluate the residual into vectors without
        # ghosts: assemble into our own and copy the owned values.
        with b.localForm() as b_local:
            target = b if b_local.handle else self._residual_work
        with target.localForm() as target_local:
            target_local.set(0.0)
        fem_petsc.assemble_vector(target, residual_form, coeffs=self._coefficients(0) if packs else None)
        # Lifting costs twice the residual (it runs the tangent kernel on bone-adjacent cells) and
        # vanishes once the iterate holds the Dirichlet values: after the first full step.
        if self.bc_error(x) > 0.0:
            fem_petsc.apply_lifting(target, [jacobian_form], bcs=[self.bcs], x0=[self.unknown.vector],
                                    scale=-1.0, coeffs=[self._coefficients(1)] if packs else None)
        target.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        for term in self.energy_terms:
            term.add_gradient(x, target)
        fem_petsc.set_bc(target, self.bcs, x, -1.0)
        if target is not b:
            target.copy(b)

    def _precheck(self, x, step):
        """Line-search pre-check: records the size of the Newton correction (for the step
        tolerance) and, with a guard, shortens it against inversion. The next iterate is
        x - lambda step with lambda at most GUARDED_MAX_LAMBDA (cp extrapolates when the energy
        still falls at lambda = 1, unbounded it ran into inverted elements); the step is shortened
        so that no such lambda inverts an element. A Newton direction that keeps pointing into
        inversion is cut again and again: after STALLED_GUARD_ITERATIONS such cuts in a row,
        Newton gives up (the continuation fallback takes over) instead of crawling to the
        iteration limit."""
        if self.refuse_ascent and self._factor_has_exact_terms and not self._descends(step):
            self._refuse_exact_terms(x, step)
        if self.energy_terms:
            self._released = 0.5 * self.snes.getFunction()[0].dot(step)
        relaxed = self._relaxing
        if relaxed:
            self._relax_contact_nodes(x, step)
        correction_size = step.norm(PETSc.NormType.NORM_INFINITY)
        snapped = self._snap_dirichlet_values(x, step)
        if self.inversion_guard is None and not self.energy_terms:
            self.reuse_policy.record_correction(correction_size)
            return snapped or relaxed
        fraction, bound = self._step_bounds(x, step, GUARDED_MAX_LAMBDA)
        # Only the guard's own cut counts towards its stall: where a term's bound cuts the step
        # shorter still, that term, not inversion, limits Newton.
        if self.reuse_policy.fresh_factor:
            self._guard_cuts = self._guard_cuts + 1 if fraction < min(STALLED_GUARD_FRACTION, bound) else 0
        # A step from an old factor that the guard had to cut says the factor is stale, not that
        # Newton stalls: the next iteration refactorises instead. Where a term's bound cuts the
        # step shorter still, the guard cut nothing.
        # (The bound is of the line search's longest step, GUARDED_MAX_LAMBDA corrections.)
        self.reuse_policy.record_correction(correction_size, cut=fraction < min(1.0, bound),
                                            bound=min(1.0, GUARDED_MAX_LAMBDA * bound), release=2.0 * self._released)
        # The line search takes the bounded step once (cp stops where its next lambda would pass
        # GUARDED_MAX_LAMBDA) or further: what it took is judged (``_converged``).
        self._bounded_norm = step.norm() if bound < 1.0 else None
        fraction = min(fraction, bound)
        if fraction < 1.0:
            step.scale(fraction)
            return True
        return snapped or relaxed

    def _step_bounds(self, x: PETSc.Vec, step: PETSc.Vec, largest: float) -> tuple[float, float]:
        """The fractions t of ``step`` such that x - s t largest step, s in [0, 1], inverts no
        element (the guard's; 1 without a guard) and stays admissible for every energy term
        (their collision-free bound). The terms' bounds cut routinely while contact settles, with
        old and fresh factors alike: they count neither as the guard's stall nor as a stale factor
        (the residual's contraction, against what a step of that length achieves, judges the
        factor)."""
        fraction = 1.0
        if self.inversion_guard is not None:
            for source, work in ((x, self._guard_x), (step, self._guard_step)):
                source.copy(work)
                work.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
            with self._guard_x.localForm() as x_local, self._guard_step.localForm() as step_local:
                fraction = self.inversion_guard.step_fraction(
                    x_local.array_r, step_local.array_r, largest) / largest
        bound, self._bounding_term = 1.0, None
        for term in self.energy_terms:
            term_bound = term.step_fraction(x, step, largest)
            if term_bound < bound:
                bound, self._bounding_term = term_bound, term
        return fraction, bound

    def _relax_contact_nodes(self, x: PETSc.Vec, step: PETSc.Vec) -> None:
        """Newton's correction ``step`` becomes the way from ``x`` to the point where its
        admissible part leads, with the contact nodes relaxed there (``ContactRelaxation``)."""
        y = self._relaxed
        x.copy(y)
        y.axpy(-min(self._step_bounds(x, step, 1.0)), step)
        self.relaxation.relax(y, self._constrained_dofs(), tolerance=self.snes.getTolerances()[1])
        x.copy(step)
        step.axpy(-1.0, y)
        self._set_unknown(x)

    def _descends(self, step: PETSc.Vec) -> bool:
        """Whether the energy falls along the Newton step x - lambda ``step`` (R(x) . step > 0)."""
        residual = self.snes.getFunction()[0]
        return residual.dot(step) > -DESCENT_ROUND_OFF * residual.norm() * step.norm()

    def _refuse_exact_terms(self, x: PETSc.Vec, step: PETSc.Vec) -> None:
        """The tangent with a term's exact Hessian (``exact_near_solution``, or the sensitivities'
        tangent kept across solves) was indefinite where the residual points: its correction
        climbs the energy, and Newton cycled on such steps (the pressed lips of a bilabial frame,
        docs/contact.md). ``step`` is solved again at ``x`` with the tangent in which every term
        takes its Newton correction; later factorisations may take the exact Hessian again
        (refusing it for the rest of the solve made the lips' closing converge linearly: 94
        Newton iterations instead of 73)."""
        self.refused_exact_tangents += 1
        self._set_unknown(x)
        self._assemble_newton_tangent(x, self.tangent, exact_terms=False)
        ksp = self.snes.getKSP()
        ksp.solve(self.snes.getFunction()[0], step)
        self.linear_iterations += max(ksp.getIterationNumber(), 1)
        if ksp.getConvergedReason() < 0:
            step.set(np.nan)  # a failed factorisation fails the line search, and the continuation takes over

    def _snap_dirichlet_values(self, x, step) -> bool:
        """Put Dirichlet dofs within SNAP_DISTANCE of their values exactly there (and take them out
        of the step). The line search's lambda is rarely exactly 1, so the first step leaves the
        bone nodes a fraction of their motion short, and every residual would pay for the lifting
        until round-off closed the gap. The step's free part already holds the flesh's response
        to that last bit of bone motion (the lifting of the residual it came from)."""
        gap = self.bc_error(x)
        if not 0.0 < gap <= SNAP_DISTANCE:
            return False
        fem_petsc.set_bc(x, self.bcs)
        fem_petsc.set_bc(step, self.bcs, x, 0.0)
        return True

    def _converged(self, snes, iteration, norms):
        """PETSc's default test (atol, rtol, stol, max_it, NaN), the step tolerance and the
        guard's stall test. Also gives the residual norm to the reuse policy."""
        xnorm, step_norm, fnorm = norms
        rtol, atol, stol, _ = snes.getTolerances()
        max_it = self.iteration_limit
        reasons = PETSc.SNES.ConvergedReason
        policy = self.reuse_policy
        policy.record_residual(iteration, fnorm)
        if iteration > 0 and self._bounded_norm:
            policy.record_taken(step_norm / self._bounded_norm)
        self._bounded_norm = None
        if iteration == 0:
            self._guard_cuts, self._initial_fnorm, self._released = 0, fnorm, math.inf
            # (Whether rank 0 traces: the residual's split below is a reduction over the ranks.)
            self._tracing = self.comm.bcast(self.comm.rank == 0 and trace.isEnabledFor(logging.DEBUG), root=0)
            self._relaxing, self._crawl_cuts = self.relaxation is not None and self.contact_relaxation is True, 0
        # Only a correction that such a term's bound cut needs the residual's split (a reduction).
        may_start = iteration > 0 and self._may_start_relaxing()
        watched = may_start and policy.step_bound < 1.0 and getattr(self._bounding_term, "relax_on_crawl", False)
        norms = self._contact_residual_norms(snes.getFunction()[0]) if self._tracing or watched else None
        if may_start:
            crawling = watched and norms[-1] ** 2 >= CRAWL_CONTACT_SHARE * fnorm ** 2
            self._crawl_cuts = self._crawl_cuts + 1 if crawling else 0
            if self._crawl_cuts >= CRAWL_CUTS:
                self._relaxing = True
                if self.comm.rank == 0:
                    log.debug("Newton: %d corrections in a row cut by the %s' bound, the residual on the contact "
                              "nodes: relaxing them from here on", self._crawl_cuts, self._bounding_term.label)
        if self._tracing:
            split = " (" + ", ".join(f"{term.label} {norm:.4g}" for term, norm in zip(
                self._surface_terms, norms)) + ")" if self._surface_terms else ""
            if self.comm.rank == 0 and iteration == 0:
                trace.debug("Newton 0: residual %.4g mN%s", fnorm, split)
            elif self.comm.rank == 0:  # what the correction of the iteration before did
                trace.debug("Newton %d: residual %.4g mN%s (x %.3g) after a correction from %s factor (%d made so "
                            "far): %.3g mm, %.3g taken (2-norm), bound %.3g%s%s, releasing %.3g mN mm", iteration,
                            fnorm, split, policy.contraction, "a fresh" if policy.fresh_factor else "an old",
                            self.factorizations, policy.correction_size, step_norm, policy.step_bound,
                            f" ({self._bounding_term.label})" if policy.step_bound < 1.0 else "",
                            ", guard cut" if policy.step_was_cut else "", self._released)
        if not np.isfinite(fnorm):
            return reasons.DIVERGED_FNORM_NAN
        if fnorm < atol:
            return reasons.CONVERGED_FNORM_ABS
        # Steps of the converging phase (from an older factor) contract linearly, so the relative
        # test, which a quadratically convergent step overshoots by orders of magnitude, would
        # stop them early (the widest jaw opening at 5K tets: 8e-5 mN instead of below 1e-9);
        # they stop on their size, with a hundredfold margin for their slower contraction (one
        # more cheap iteration).
        converging_phase = policy.converging_phase
        if iteration > 0 and not converging_phase and fnorm < rtol * self._initial_fnorm:
            return reasons.CONVERGED_FNORM_RELATIVE
        step_tolerance = 0.01 * self.step_tolerance if converging_phase else self.step_tolerance
        small_step = iteration > 0 and (step_norm < stol * xnorm or policy.correction_size < step_tolerance)
        # Against a stiff barrier a correction that small still leaves a large residual: cheap as
        # they are, the converging phase's iterations go on until the residual is small too
        # (RESIDUAL_PER_STEP), or the correction two decades smaller still.
        if (small_step and converging_phase and fnorm >= RESIDUAL_PER_STEP * self.step_tolerance
                and policy.correction_size >= 0.01 * step_tolerance):
            small_step = False
        small_release = (iteration > 0 and self.energy_tolerance is not None
                         and abs(self._released) < self.energy_tolerance)
        # A step that a bound shortened leaves the bones short of their values by that much: the
        # small-step and energy tests stop Newton only once they are there (stopped short, the
        # solve would count as failed and start again from the last equilibrium: docs/contact.md).
        if (small_step or small_release) and self.bc_error(snes.getSolution()) <= DIRICHLET_TOLERANCE:
            self.energy_stops += int(not small_step)
            return reasons.CONVERGED_SNORM_RELATIVE
        # The iteration limit stops a Newton that is not converging: a converging phase (a kept
        # factor cutting the residual at least 1 / REFRESH_CONTRACTION per iteration) finishes,
        # within the room PETSc's own limit gives it (CONVERGING_PHASE_ITERATIONS).
        if iteration >= max_it and not converging_phase:
            return reasons.DIVERGED_MAX_IT
        if self._guard_cuts >= STALLED_GUARD_ITERATIONS:
            if self.comm.rank == 0:
                log.debug("Newton: the inversion guard cut %d fresh corrections in a row below %g of their length",
                          self._guard_cuts, STALLED_GUARD_FRACTION)
            return reasons.DIVERGED_LINE_SEARCH
        return reasons.CONVERGED_ITERATING

    def _contact_residual_norms(self, residual: PETSc.Vec) -> list[float]:
        """The residual's norm on the nodes of each energy term that has a contact surface, then on
        all of them together (collective): where a crawling Newton's residual sits."""
        squares = np.square(residual.array_r).reshape(-1, 3).sum(axis=1)
        local = np.array([squares[blocks].sum() for blocks in self._surface_blocks])
        return np.sqrt(self.comm.allreduce(local, op=MPI.SUM)).tolist()

    def assemble_tangent(self, A: PETSc.Mat) -> None:
        """Assemble the tangent at the unknown into ``A`` (Dirichlet rows and columns identity)."""
        A.zeroEntries()
        fem_petsc.assemble_matrix(A, self.jacobian_form, bcs=self.bcs, coeffs=self._coefficients(1))
        A.assemble()
        for term in self.energy_terms:
            term.add_hessian(self.unknown.vector, A, self._constrained_dofs())

    def _assemble_tangent(self, snes, x, A, P):
        linear_iterations = None
        if A.handle != P.handle:
            # -snes_mf_operator: Krylov on the exact tangent (J v by differencing the residual at
            # x), preconditioned by the factor of P; the factor is refreshed when Krylov slows.
            A.assemble()
            linear_iterations = snes.getKSP().getIterationNumber()
        if not self._factor_has_these_conditions():
            # Its rows of a node held since (the lining a contact object's move carries) are the
            # flesh's, not the identity: its corrections would move the held node; and of a node
            # released since they would hold it still.
            self.reuse_policy.forget_factor()
        if self.reuse_policy.keep_factor(snes.getIterationNumber(), linear_iterations,
                                         (self._old_factor_release if self.energy_terms and self.judge_factor_by_energy
                                          else None),
                                         self.energy_tolerance or 0.0,
                                         self._relaxes_instead if self._may_start_relaxing() else None):
            return  # P is untouched, so the PC keeps its factor: a modified Newton iteration
        self._assemble_newton_tangent(x, P)

    def _may_start_relaxing(self) -> bool:
        """Whether the relaxation of the contact nodes may still start in this Newton solve
        (``contact_relaxation`` None, not started yet)."""
        return self.relaxation is not None and self.contact_relaxation is None and not self._relaxing

    def _relaxes_instead(self) -> bool:
        """Where the residual's slow fall would refresh the factor: if the surface nodes of the
        terms that say ``relax_on_slow_fall`` (the teeth, objects, the lips) hold
        SLOW_FALL_CONTACT_SHARE of the residual's square, the relaxation of the contact nodes
        starts (for the rest of the solve) and the factor is kept (collective). The lining resting
        on the teeth settles on a barrier whose stiffness changes by orders of magnitude with the
        gap: there a fresh factor's correction cut the residual no faster than an old one's (404K
        tracking with the lips open, docs/performance.md, "Settling on the teeth"); so do the lips
        letting go of each other (docs/performance.md, "The lips' opening, again")."""
        watched = [term.surface.owned_blocks for term in self._surface_terms if getattr(term, "relax_on_slow_fall", False)]
        blocks = np.unique(np.concatenate(watched)) if watched else np.zeros(0, dtype=np.int32)
        squares = np.square(self.snes.getFunction()[0].array_r).reshape(-1, 3)[blocks].sum()
        share = self.comm.allreduce(squares, op=MPI.SUM) / self.snes.getFunctionNorm() ** 2
        if not share >= SLOW_FALL_CONTACT_SHARE:
            return False
        self._relaxing = True
        if self.comm.rank == 0:
            log.debug("Newton: the residual falls slowly, %.3g of its square on the contact surfaces' nodes: "
                      "relaxing the contact nodes from here on, the factor kept", share)
        return True

    def _old_factor_release(self) -> float:
        """R . K0^-1 R at the current iterate, K0 the factor Newton has (one solve; the kept
        factor's correction is solved again by SNES)."""
        ksp = self.snes.getKSP()
        residual = self.snes.getFunction()[0]
        ksp.solve(residual, self._trial_correction)
        self.linear_iterations += 1
        release = residual.dot(self._trial_correction)
        return release if ksp.getConvergedReason() >= 0 and np.isfinite(release) else math.inf

    def _assemble_newton_tangent(self, x: PETSc.Vec, P: PETSc.Mat, exact_terms: bool = True) -> None:
        """Assemble Newton's tangent at the unknown (which is ``x``) into ``P``; the PC sees a
        changed matrix and factorises it when the KSP is next set up or solves. ``exact_terms``
        False: every term takes its Newton correction, near the solution too."""
        self.assemble_tangent(P)
        self._factor_conditions = tuple(self.bcs)
        exact = not self._add_newton_corrections(P, exact_terms)
        self.factorizations += 1
        self.reuse_policy.factorised(in_newton=True)
        self._factor_controls_current, self.factor_is_exact = True, exact
        x.copy(self._factor_state)

    def _add_newton_corrections(self, A: PETSc.Mat, exact_terms: bool = True) -> bool:
        """A += the energy terms' changes of their Hessians for Newton's corrections, and the
        flesh's (``add_newton_correction``; with ``exact_terms`` as ``_newton_corrections`` decides,
        else every one); the factor of that matrix is no exact tangent for the sensitivities
        (``factor_distance``). Returns whether A changed."""
        changed, self._factor_has_exact_terms = False, False
        terms = [(term, self._constrained_dofs()) for term in self.energy_terms if hasattr(term, "add_newton_correction")]
        if self.flesh_correction is not None:  # it adds cells' stiffness, so the ghost dofs' too
            terms.append((self.flesh_correction, self._constrained_dofs(ghosts=True)))
        for term, constrained in terms:
            if not exact_terms or self._newton_corrections(term):
                changed = term.add_newton_correction(self.unknown.vector, A, constrained) or changed
            else:
                self._factor_has_exact_terms = True
        return changed

    def _newton_corrections(self, term) -> bool:
        """Whether Newton's tangent takes ``term``'s correction: always, or for a term that says
        ``exact_near_solution``, only until Newton is near the solution (its last correction was
        taken whole and moved no dof further than CONVERGING_CORRECTION)."""
        if not getattr(term, "exact_near_solution", False):
            return True
        policy = self.reuse_policy
        near = (self.snes.getIterationNumber() > 0 and policy.correction_size < CONVERGING_CORRECTION
                and policy.step_bound >= 1.0 and not policy.step_was_cut)
        return not near

    def _constrained_dofs(self, ghosts: bool = False) -> np.ndarray:
        """The owned (with ``ghosts``, all) local dofs of the Dirichlet conditions."""
        dofs = [bc.dof_indices()[0] for bc in self.bcs]
        dofs = np.concatenate(dofs) if dofs else np.zeros(0, dtype=np.int32)
        return dofs if ghosts else dofs[dofs < self.unknown.vector.getLocalSize()]

    def _factor_has_these_conditions(self) -> bool:
        """Whether the factor was made under the Dirichlet conditions now set (the same objects)."""
        return len(self._factor_conditions) == len(self.bcs) and all(
            a is b for a, b in zip(self._factor_conditions, self.bcs))

    def _factor(self, A: PETSc.Mat) -> None:
        """Factorise ``A`` for solves outside Newton. An "spd" tangent that meets a zero pivot
        without pivoting (the exact tangent with the lips' curvature, at a state Newton left well
        short of equilibrium: 404K tracking, docs/performance.md) is factorised again with
        pivoting, as Newton's own solves are (a solve on a failed factor is MUMPS's error -3)."""
        self._factor_conditions = tuple(self.bcs)
        ksp = self.snes.getKSP()

        def factorised() -> bool:  # PETSc reports a failed factorisation as the KSP's reason only
            ksp.setOperators(A, A)
            ksp.setUp()
            ksp.getPC().setUp()
            self.factorizations += 1
            return ksp.getConvergedReason() >= 0

        if not factorised() and self.tangent_structure == "spd" and not self._pivoting:
            self._factorise_with_pivoting("the factorisation")
            factorised()
        if ksp.getConvergedReason() < 0:
            self.reuse_policy.forget_factor()
            raise EquilibriumError(f"the tangent's factorisation failed (KSP reason {ksp.getConvergedReason()})")
        self.reuse_policy.factorised(in_newton=False)
        self._factor_controls_current, self.factor_is_exact = True, True
        # The sensitivities' tangent is exact: Newton may keep it (reuse across solves).
        self._factor_has_exact_terms = (self.flesh_correction is not None
                                        or any(hasattr(term, "add_newton_correction") for term in self.energy_terms))

    def _coefficients(self, form: int) -> dict | None:
        """Packed coefficients of the residual (0) or tangent (1) form; None: DOLFINx packs them."""
        return None if self._packs is None else self._packs[form].packed()

    def controls_changed(self) -> None:
        """The owner changed the controls (Dirichlet values, coefficients of the forms): the
        factor, whatever its state, no longer holds a tangent of them, and kept coefficient data
        are packed anew."""
        self._factor_controls_current = False
        for pack in self._packs or ():
            pack.stale = True

    def factor_distance(self, exact: bool = True) -> float:
        """Largest distance of a dof of the unknown from the state whose tangent the factor
        holds (0 right after ``factorize``), over all ranks; inf if no factor holds a tangent of
        the controls now set, or (``exact``) if it holds Newton's tangent with an energy term's
        correction (``factor_is_exact`` False: the contact Hessians projected). Collective."""
        if not (self.reuse_policy.has_factor and self._factor_controls_current and self._factor_has_these_conditions()):
            return math.inf
        if exact and not self.factor_is_exact:
            return math.inf
        self.unknown.vector.copy(self._distance_work)
        self._distance_work.axpy(-1.0, self._factor_state)
        return self._distance_work.norm(PETSc.NormType.NORM_INFINITY)

    def factorize(self, newton_model: bool = False) -> None:
        """Assemble and factorise the tangent at the unknown (for sensitivities; in reuse mode
        the factor then also serves the next Newton solves). ``newton_model``: Newton's tangent,
        every energy term's correction in it (``factor_is_exact`` False if one changed it)."""
        self.assemble_tangent(self.tangent)
        changed = newton_model and self._add_newton_corrections(self.tangent, exact_terms=False)
        self._factor(self.tangent)
        if newton_model:
            self.factor_is_exact, self._factor_has_exact_terms = not changed, False
        self.unknown.vector.copy(self._factor_state)

    def solve_tangent(self, rhs: PETSc.Vec, out: PETSc.Vec) -> None:
        """out = K^-1 rhs with the current factor (exact while ``factor_distance()`` is 0)."""
        ksp = self.snes.getKSP()
        ksp.solve(rhs, out)
        if ksp.getConvergedReason() < 0:
            raise EquilibriumError(f"tangent solve failed ({ksp.getConvergedReason()})")

    # -- public ------------------------------------------------------------------------------
    def energy(self) -> float:
        """Total energy at the current unknown (NaN if an element is inverted)."""
        return (global_sum(self.comm, fem.assemble_scalar(self.energy_form))
                + sum(term.energy(self.unknown.vector) for term in self.energy_terms))

    def residual_norm(self) -> float:
        """Norm of the free-dof residual at the current unknown (Dirichlet rows excluded)."""
        self.unknown.vector.copy(self._solution)
        self._assemble_residual(self.snes, self._solution, self._residual_vector)
        return self._residual_vector.norm()

    def newton(self, lifting: bool = False) -> tuple[bool, int, str]:
        """One SNES solve from the current unknown; Dirichlet values are reached by the Newton steps.
        ``lifting``: a solve that lifts held surface nodes far to their Dirichlet values (a contact
        object's push-out or carry, ``face_dolfinx.physics.contact``), whose corrections the
        inversion guard cuts while the flesh follows: a fresh factor whose correction it cut is
        kept for one more iteration (``FactorReusePolicy``). Refactorised at every cut, the teeth's
        lifted push-out of the lips' second closure took 9 factorisations in 11 iterations
        (docs/performance.md)."""
        self.reuse_policy.start_solve()
        self.reuse_policy.keeps_cut_fresh_factor = lifting
        if self._pivoting:
            self._set_pivoting(False)
        began, factorizations, residuals = time.perf_counter(), self.factorizations, self.residual_evaluations
        self.unknown.vector.copy(self._start)
        reason = self._solve_from_start()
        if reason == PETSc.SNES.ConvergedReason.DIVERGED_LINEAR_SOLVE and self.tangent_structure == "spd":
            self._factorise_with_pivoting()
            reason = self._solve_from_start()
        elif reason < 0 and self.reuse_policy.used_only_an_old_factor:
            # Only the old factor was used and Newton failed: retry once with fresh tangents.
            self.reuse_policy.forget_factor()
            reason = self._solve_from_start()
        self._set_unknown(self._solution)
        if self.comm.rank == 0:
            log.debug("Newton: %s after %d its, %d factorisations, %d residuals, %.2f s",
                      _reason_name(reason), self.snes.getIterationNumber(), self.factorizations - factorizations,
                      self.residual_evaluations - residuals, time.perf_counter() - began)
        if reason > 0 and self.bc_error() > DIRICHLET_TOLERANCE:
            return False, self.snes.getIterationNumber(), "Dirichlet values not reached"
        return reason > 0, self.snes.getIterationNumber(), _reason_name(reason)

    def _solve_from_start(self) -> int:
        self._start.copy(self._solution)
        self.snes.solve(None, self._solution)
        self.linear_iterations += self.snes.getLinearSolveIterations()
        return self.snes.getConvergedReason()

    def _factorise_with_pivoting(self, retried: str = "the Newton solve") -> None:
        """After a failed factorisation (a zero pivot of a tangent factorised without pivoting,
        seen mid-Newton in jaw openings from rest at 404K tets): MUMPS keeps its error, and
        PETSc then skips every later numerical factorisation of the same analysis, so the
        preconditioner is reset (a new analysis) and the tangent is factorised as symmetric
        indefinite, with pivoting, for the rest of this solve (``retried``, named in the log).
        The next solve goes back to the cheaper factorisation (4.4-5.0 s against 5.5 s at 404K)."""
        if self.comm.rank == 0:
            log.warning("the tangent's factorisation failed (zero pivot without pivoting): retrying %s "
                        "with pivoting", retried)
        self._set_pivoting(True)

    def _set_pivoting(self, pivoting: bool) -> None:
        self._pivoting = pivoting
        self.tangent.setOption(PETSc.Mat.Option.SPD, not pivoting)
        self.snes.getKSP().getPC().reset()
        self.reuse_policy.forget_factor()

    @property
    def pivoting(self) -> bool:
        """An "spd" tangent is factorised with pivoting, for the rest of the Newton solve after a
        failed factorisation."""
        return self._pivoting

    def bc_error(self, x: PETSc.Vec | None = None) -> float:
        """Largest distance of a Dirichlet dof of ``x`` (default: the unknown) from its
        prescribed value, over all ranks."""
        x = self.unknown.vector if x is None else x
        # set_bc writes the prescribed values in the unknown's numbering, also for a condition on a
        # sub-space (whose g lives in the collapsed space) or with a Constant value.
        if self._prescribed is None:
            self._prescribed = x.duplicate()
        x.copy(self._prescribed)
        fem_petsc.set_bc(self._prescribed, self.bcs)
        local = 0.0
        for bc in self.bcs:
            dofs, _ = bc.dof_indices()
            owned = dofs[dofs < x.getLocalSize()]
            if owned.size:
                local = max(local, np.abs(x.array_r[owned] - self._prescribed.array_r[owned]).max())
        return self.comm.allreduce(local, op=MPI.MAX)

    def solve_continuation(self, set_controls: Callable[[float], None], *, max_halvings: int = 10,
                           predictor: Callable[[float, float], None] | None = None) -> SolveReport:
        """Reach the controls ``set_controls(1.0)`` from the equilibrium at ``set_controls(0.0)``.

        ``set_controls(t)`` puts the controls (activations, Dirichlet values) at fraction t of the
        way; the unknown must hold the equilibrium for t = 0 on entry. ``predictor(t0, t1)``, if
        given, moves the unknown from the equilibrium at t0 towards a guess for t1 (e.g. the rigid
        motion of the head); if it returns False it found no admissible start, and that load step
        fails. Tries t = 1 at once; on failure halves the step, and doubles it after
        each success. Gives up when a step of 2^-max_halvings of the way fails: a walk that keeps
        progressing with occasional failures goes on (counting every failure stopped the 5x jaw
        opening of the stability study after six failures spread over its first third); and when
        CREEP_LOAD_STEPS load steps in a row, taken or failed, were no longer than CREEP_STEP of the
        way: at that pace the walk would need hundreds of Newton solves (the 5K bilabial take's hard
        closure crept on in steps of 1/256 for as long as a test suite runs).
        """
        start = time.perf_counter()
        converged_state = self.unknown.vector.copy()
        t, step, newton_total, steps_taken, failures = 0.0, 1.0, 0, 0, 0
        smallest_step = 0.5 ** max_halvings
        creeping = 0  # load steps in a row no longer than CREEP_STEP
        while t < 1.0:
            creeping = creeping + 1 if step <= CREEP_STEP else 0
            target = min(1.0, t + step)
            if predictor is not None and predictor(t, target) is False:
                # No admissible start for this load step: it fails as a failed solve would.
                ok, iterations, why = False, 0, "the predictor found no admissible start"
            else:
                set_controls(target)
                ok, iterations, why = self.newton()
            newton_total += iterations
            if ok:
                t, steps_taken = target, steps_taken + 1
                self.unknown.vector.copy(converged_state)
                step = min(2.0 * step, 1.0 - t) if t < 1.0 else step
                continue
            failures += 1
            if step <= smallest_step or creeping >= CREEP_LOAD_STEPS:
                converged_state.copy(self.unknown.vector)
                self.unknown.vector.ghostUpdate(addv=PETSc.InsertMode.INSERT,
                                                mode=PETSc.ScatterMode.FORWARD)
                set_controls(t)
                raise EquilibriumError(
                    f"no equilibrium beyond {t:.4f} of the way to the target controls: a step of "
                    f"{step:.4g} of the way failed after {failures} failures in all and {creeping} "
                    f"load steps in a row no longer than {CREEP_STEP:g} (last: {why}); "
                    f"the state is left at the last equilibrium")
            if self.comm.rank == 0:
                log.info("Newton failed at load %.4f (%s, %d iterations); continuation fallback "
                         "retries from %.4f with step %.4f", target, why, iterations, t, step / 2)
            step /= 2.0
            converged_state.copy(self.unknown.vector)
            self.unknown.vector.ghostUpdate(addv=PETSc.InsertMode.INSERT,
                                            mode=PETSc.ScatterMode.FORWARD)
        if steps_taken > 1 and self.comm.rank == 0:
            log.info("continuation fallback reached the target in %d load steps", steps_taken)
        converged_state.destroy()
        return SolveReport(True, newton_total, steps_taken, "converged",
                           time.perf_counter() - start)


_REASONS = {v: k for k, v in vars(PETSc.SNES.ConvergedReason).items() if not k.startswith("_")}


def _reason_name(reason: int) -> str:
    return f"{_REASONS.get(reason, 'UNKNOWN')} ({reason})"
