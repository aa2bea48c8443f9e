"""Nonlinear elimination of the nodes in contact: after each Newton correction, the skin nodes that
a contact term pushes on are brought to their own equilibrium by a small Newton of their own, the
rest of the unknown held (Lanzkron, Rose and Wilkes 1996, "An analysis of approximate nonlinear
elimination"; Cai and Keyes 2002).

Why: pressed lips sit micrometres apart on a barrier whose stiffness changes by orders of
magnitude with the gap, and their nodes slide along each other's facets. A Newton correction of
the whole face, fresh or from an old factor, predicts that badly: on a warm tracking frame at
404K tets Newton refactorised at nearly every iteration while the residual hovered on the lips
(docs/performance.md, "Contact in tracking"). The contact nonlinearity lives on a few thousand
dofs; the rest of the face is nearly linear between nearby equilibria. So the global correction
(often from an old factor) moves the face, and the contact nodes then relax in a local problem
whose tangent (the flesh over the cells around the contact surfaces plus the contact terms'
Hessians, each projected onto the positive semidefinite ones as Newton's is) is a small sparse
matrix, factorised in milliseconds. Newton's correction becomes the way from the iterate to the
relaxed point; its line search, the inversion guard and the collision-free bounds then act on it
as on any correction.

The local Newton takes a step bounded by the same collision-free step and inversion guard (over
the patch cells, the only ones it moves) and keeps it if the contact nodes' residual fell, halving
it otherwise; it stops once that residual is below ``reduction`` times the rest's (the global
Newton takes it from there) or below Newton's own absolute tolerance (nothing left to relax in a
converged solve), or after ``max_iterations``. (Stopping it also once a local correction moved no
dof further than Newton's step tolerance left more factorisations in the 404K warm frames:
docs/performance.md.) Each local step has a fresh local tangent: the barrier's stiffness changes
by orders of magnitude as a gap closes, and a local tangent kept over the steps took 8 steps to
cut the residual of a lip moved 0.01 mm off its pressed equilibrium 2.6-fold. The
contact nodes' rows of the residual come from the patch too (the residual form restricted like
the tangent, exact on those rows: every cell of a contact node is in the patch), at a fraction of
the whole face's assembly. Each relaxation assembles both over the cells around the nodes it moves
only, which give those nodes' rows and columns whole: on the 404K face a few thousand of the
patch's 17 689 cells, the forms made again from the compiled kernels' cache in milliseconds.

Under MPI the local problem is distributed as the unknown is (a parallel submatrix, MUMPS on the
same ranks); every decision is taken on global norms, so all ranks take the same steps.
"""
from typing import Callable

from petsc4py import PETSc
import numpy as np
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
import dolfinx.fem.petsc as fem_petsc

# Local Newton iterations per relaxation, and the contact nodes' residual (against the rest's)
# below which it stops: with 8 and 0.1, 4-14 factorisations per warm 404K tracking frame with lip
# and teeth contact instead of 10-25 (docs/performance.md, "Contact in tracking").
RELAXATION_ITERATIONS = 8
RELAXATION_REDUCTION = 0.1
# A local step whose contact residual did not fall is halved this many times before the relaxation
# stops where it is.
RELAXATION_HALVINGS = 4


class ContactRelaxation:
    """The local Newton of the contact nodes (module docstring) for a ``QuasistaticSolver``.

    ``residual`` and ``jacobian``: the solver's residual and tangent forms (UFL), restricted here
    to the cells around the contact surfaces; ``terms``: the solver's energy terms (each with
    ``surface``, a ``physics.contact.ContactSurface``, ``nodal_forces(displacement)``, its force
    on each of the surface's nodes, and ``step_fraction``); ``template``: a vector like the
    unknown's; ``assemble(x, b, residual_form, jacobian_form)``: b = the residual of these forms
    and the terms at x (Dirichlet rows zero), ``full_residual(x, b)``: the solver's whole one;
    ``guard``: the solver's ``InversionGuard`` (or None); ``compile_form(form)`` and
    ``create_matrix(form)``: the solver's (a matrix whose sparsity also holds the terms'
    couplings).
    """

    def __init__(self, residual: ufl.Form, jacobian: ufl.Form, space: fem.FunctionSpace, terms: tuple,
                 template: PETSc.Vec, assemble: Callable, full_residual: Callable[[PETSc.Vec, PETSc.Vec], None],
                 guard, compile_form: Callable, create_matrix: Callable,
                 max_iterations: int = RELAXATION_ITERATIONS, reduction: float = RELAXATION_REDUCTION):
        self.space, self.terms = space, tuple(terms)
        self.assemble, self.full_residual = assemble, full_residual
        self.max_iterations, self.reduction = max_iterations, reduction
        self.comm = space.mesh.comm
        self.local_iterations = 0  # local Newton steps taken in all
        self._residual_ufl, self._jacobian_ufl, self._compile_form = residual, jacobian, compile_form
        self._flags = fem.Function(space)  # work function of ``_cells_around``
        cells = space.mesh.topology.index_map(3).size_local
        self._cell_blocks = space.dofmap.list.array.reshape(-1, space.dofmap.dof_layout.num_dofs)[:cells]
        patch = self._cells_around(np.concatenate([term.surface.owned_blocks for term in self.terms]))
        self._patch_forms = self._forms_over(patch)
        self.guard = guard.restricted(patch) if guard is not None else None
        # The patch's sparsity holds every relaxation's tangent, over fewer cells: assembled once
        # so that the first assembly does not drop the entries its cells leave out.
        self._matrix = create_matrix(self._patch_forms[1])
        fem_petsc.assemble_matrix(self._matrix, self._patch_forms[1])
        self._matrix.assemble()
        self._ksp = PETSc.KSP().create(self.comm)
        self._ksp.setType("preonly")
        pc = self._ksp.getPC()
        pc.setType("cholesky")
        pc.setFactorSolverType("mumps")
        self._r = template.duplicate()
        self._trial_r = self._r.duplicate()
        self._step = self._r.duplicate()
        self._trial = self._r.duplicate()
        self._first = space.dofmap.index_map.local_range[0] * space.dofmap.index_map_bs

    def _cells_around(self, blocks: np.ndarray) -> np.ndarray:
        """This rank's cells that have a node among the owned local dof ``blocks`` of any rank
        (collective)."""
        flags = self._flags.x
        flags.array[:] = 0.0
        flags.array.reshape(-1, 3)[blocks] = 1.0
        flags.scatter_forward()
        flagged = flags.array.reshape(-1, 3)[:, 0] > 0.5
        return np.flatnonzero(flagged[self._cell_blocks].any(axis=1)).astype(np.int32)

    def _forms_over(self, cells: np.ndarray) -> tuple:
        """The residual and tangent forms over this rank's ``cells``."""
        tags = dmesh.meshtags(self.space.mesh, 3, cells, np.ones(len(cells), dtype=np.int32))
        return (self._compile_form(_restricted(self._residual_ufl, tags)),
                self._compile_form(_restricted(self._jacobian_ufl, tags)))

    def patch_residual(self, x: PETSc.Vec, b: PETSc.Vec) -> None:
        """b = the residual at x on the rows of the contact surfaces' nodes (the others hold the
        patch's part of theirs)."""
        self.assemble(x, b, *self._patch_forms)

    def _bound(self, y: PETSc.Vec, step: PETSc.Vec) -> float:
        """The largest t in (0, 1] such that y - s t step, s in [0, 1], inverts no patch cell and
        stays collision-free."""
        fraction = 1.0
        if self.guard is not None:
            for vector in (y, step):
                vector.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
            with y.localForm() as y_local, step.localForm() as step_local:
                fraction = self.guard.step_fraction(y_local.array_r, step_local.array_r)
        return min([fraction] + [term.step_fraction(y, step, 1.0) for term in self.terms])

    def _local_tangent(self, y: PETSc.Vec, rows: PETSc.IS, constrained: np.ndarray,
                       jacobian: fem.FormMetaClass) -> PETSc.Mat:
        """The tangent's (rows, rows) block at ``y`` (``jacobian``: the tangent form over the cells
        of the rows' nodes), the terms' Hessians projected as Newton's."""
        A = self._matrix
        A.zeroEntries()
        fem_petsc.assemble_matrix(A, jacobian)
        A.assemble()
        for term in self.terms:
            term.add_hessian(y, A, constrained)
            # A term whose Newton model adds more than the projection (the lips' wider reach)
            # gives the projection alone: the local Newton iterates to the contact nodes' equilibrium.
            projection = getattr(term, "add_projection", getattr(term, "add_newton_correction", None))
            if projection is not None:
                projection(y, A, constrained)
        K = A.createSubMatrix(rows, rows)
        K.setOption(PETSc.Mat.Option.SPD, True)
        return K

    def relax(self, y: PETSc.Vec, constrained: np.ndarray, tolerance: float = 0.0) -> None:
        """Move the contact nodes of ``y`` (owned values; ``constrained``: the owned local Dirichlet
        dofs, which stay) towards their equilibrium with the rest of ``y`` held, until their
        residual is below a ``reduction`` of the rest's or ``tolerance``. Collective."""
        blocks = np.unique(np.concatenate([term.surface.pushed_blocks(term.nodal_forces(y.array_r))
                                           for term in self.terms]))
        dofs = np.setdiff1d((3 * blocks[:, None] + np.arange(3)).reshape(-1), constrained)
        if self.comm.allreduce(len(dofs)) == 0:
            return
        forms = self._forms_over(self._cells_around(blocks))
        rows = PETSc.IS().createGeneral((self._first + dofs).astype(PETSc.IntType), comm=self.comm)
        self.full_residual(y, self._r)
        local = self._r.getSubVector(rows)
        norm = local.norm()
        target = max(self.reduction * np.sqrt(max(self._r.norm() ** 2 - norm ** 2, 0.0)), tolerance)
        correction = local.duplicate()
        self._r.restoreSubVector(rows, local)
        for _ in range(self.max_iterations):
            if norm <= target:
                break
            K = self._local_tangent(y, rows, constrained, forms[1])
            self._ksp.reset()
            self._ksp.setOperators(K)
            local = self._r.getSubVector(rows)
            self._ksp.solve(local, correction)
            K.destroy()
            descends = local.dot(correction) > 0.0
            self._r.restoreSubVector(rows, local)
            if self._ksp.getConvergedReason() < 0 or not descends:
                break
            self._step.set(0.0)
            embedded = self._step.getSubVector(rows)
            correction.copy(embedded)
            self._step.restoreSubVector(rows, embedded)
            fraction = self._bound(y, self._step)
            for _ in range(RELAXATION_HALVINGS + 1):
                y.copy(self._trial)
                self._trial.axpy(-fraction, self._step)
                self.assemble(self._trial, self._trial_r, *forms)  # exact on the relaxed rows
                trial_local = self._trial_r.getSubVector(rows)
                trial_norm = trial_local.norm()
                self._trial_r.restoreSubVector(rows, trial_local)
                if trial_norm < norm:
                    break
                fraction *= 0.5
            else:
                break
            self._trial.copy(y)
            self._trial_r.copy(self._r)
            norm = trial_norm
            self.local_iterations += 1
        correction.destroy()
        rows.destroy()


def _restricted(form: ufl.Form, tags) -> ufl.Form:
    """``form`` with its cell integrals over the cells tagged 1 by ``tags`` only; its facet
    integrals (the intraoral pressure on the lining) stay whole."""
    return ufl.Form([integral.reconstruct(subdomain_id=1, subdomain_data=tags)
                     if integral.integral_type() == "cell" else integral for integral in form.integrals()])
