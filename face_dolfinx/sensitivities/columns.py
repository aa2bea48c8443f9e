"""Derivatives of the equilibrium shape with respect to the controls (sifakis2005 section 6).

At an equilibrium f(X(c), c) = 0, with K the tangent (identity rows on Dirichlet dofs):
  activations       K dX/da_i = f_i                                   (eq. 5)
  intraoral p       K dX/dp = df/dp, the load of a unit pressure (f is linear in p)
  bone-driven b_i   K dX/db_i = -K_UC dX^C/db_i - d(grad E_c)/db_i, and dX^C/db_i on C
                    (eq. 6, by lifting; the last term when the teeth's barrier E_c moves with the bones)
  cranium frame     dX/db_i = (dM_c/db_i) y + dt_c/db_i,  y = M_c^-1 (x - t_c)   (analytic)
One factorisation of K serves every right-hand side; it is the equilibrium solver's own (same
matrix, same KSP), so with factorisation reuse the next Newton solves start from it too. A caller
that can live with an approximate K (Gauss-Newton directions) may keep a factor the Newton solve
made at a state close to the equilibrium instead of factorising again.
"""
from dataclasses import replace
import math

from petsc4py import PETSc
import numpy as np
from dolfinx import fem
import dolfinx.fem.petsc as fem_petsc


class EquilibriumSensitivity:
    """Columns of dX/dc at the problem's current equilibrium, as local dof arrays."""

    def __init__(self, problem):
        self.problem = problem
        self.solver = problem.solver
        self._rhs = problem.u.vector.duplicate()
        self._solution = problem.u.vector.duplicate()
        self._lift = fem.Function(problem.V)
        self._lift_bc = fem.dirichletbc(self._lift, problem.bone_blocks)
        self._accepted_distance = 0.0

    def factor(self, reuse_within: float = 0.0, newton_tangent: bool = False) -> float:
        """Set up the tangent at the current shape for the solves that follow: the solver's newest
        factor if it holds a tangent of these controls (with ``reuse_within`` > 0 also Newton's,
        whose contact Hessians are projected) at a state no further than ``reuse_within`` (mm, per
        dof) from this one, else a fresh assembly and factorisation: of the exact tangent, or with
        ``newton_tangent`` and ``reuse_within`` > 0 of Newton's at this state. Returns the distance
        of the factor's state from this one: 0 with ``solver.factor_is_exact``, the exact tangent."""
        self._accepted_distance = reuse_within
        distance = self.solver.factor_distance(exact=reuse_within == 0.0)
        if math.isfinite(distance) and distance <= reuse_within:
            return distance
        self.solver.factorize(newton_model=newton_tangent and reuse_within > 0.0)
        return 0.0

    def _solve_all(self, fill_rhs, count: int) -> np.ndarray:
        """K^-1 b_j for j < count, ``fill_rhs(j)`` putting b_j into ``self._rhs``: (count, local dofs
        incl. ghosts). With a direct factor, all right-hand sides go to MUMPS as one dense block
        (20K face, 32 muscles: 0.13 s against 1.0 s one by one); otherwise one Krylov solve each."""
        distance = self.solver.factor_distance(exact=self._accepted_distance == 0.0)
        if not (math.isfinite(distance) and distance <= self._accepted_distance):
            # An older factor (factorisation reuse, a later solve) gives the sensitivities of
            # another state.
            raise RuntimeError(f"the factor holds the tangent of a state {distance:.3g} mm from the current "
                               f"one ({self._accepted_distance:g} accepted): call factor() first")
        owned = self._rhs.getLocalSize()
        pc = self.solver.snes.getKSP().getPC()
        block = pc.getType() in ("cholesky", "lu") and count > 1
        if block:
            rhs = PETSc.Mat().createDense([(owned, self._rhs.getSize()), (None, count)],
                                          comm=self.problem.comm)
            rhs.setUp()
            values = rhs.getDenseArray()
        columns = []
        for j in range(count):
            fill_rhs(j)
            if block:
                values[:, j] = self._rhs.array_r
            else:
                self.solver.solve_tangent(self._rhs, self._solution)
                columns.append(self._with_ghosts(self._solution.array_r))
        if not block:
            return np.array(columns).reshape(count, -1)
        rhs.assemble()
        solution = rhs.duplicate()
        pc.getFactorMatrix().matSolve(rhs, solution)
        solved = solution.getDenseArray()
        columns = [self._with_ghosts(solved[:, j]) for j in range(count)]
        rhs.destroy()
        solution.destroy()
        return np.array(columns).reshape(count, -1)

    def _with_ghosts(self, owned_values: np.ndarray) -> np.ndarray:
        self._solution.array[:] = owned_values
        self._solution.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        with self._solution.localForm() as local:
            return local.array.copy()

    def activation_columns(self, muscles=None) -> np.ndarray:
        """dX/da_i for the given muscles (default all): (k, local dofs incl. ghosts)."""
        muscles = list(range(self.problem.num_muscles) if muscles is None else muscles)
        return self._solve_all(lambda j: self.problem.active_force(muscles[j], out=self._rhs), len(muscles))

    def pressure_columns(self) -> np.ndarray:
        """dX/dp for the intraoral pressure: (1, local dofs incl. ghosts)."""
        return self._solve_all(lambda j: self.problem.pressure_force(out=self._rhs), 1)

    def boundary_columns(self, bone_derivatives: np.ndarray, teeth_derivatives=None) -> np.ndarray:
        """dX/db for parameters that move the bone-attached nodes non-rigidly (the jaw).

        ``bone_derivatives`` (k, num bone blocks, 3): dX^C/db_i at ``problem.bone_blocks``.
        ``teeth_derivatives`` (``teeth_pose_derivatives``): how the same parameters move the
        teeth, for a problem with teeth contact; the lining resting on teeth that move with the
        bone then follows them (the mixed term -d(grad E_c)/db_i on the right-hand side). A problem
        with teeth contact needs it unless the parameters leave the teeth where they are.
        """
        problem = self.problem
        jacobian_form = problem.solver.jacobian_form
        teeth = problem.teeth_contact if teeth_derivatives is not None else None
        if teeth is not None and len(teeth_derivatives) != len(bone_derivatives):
            raise ValueError(f"{len(teeth_derivatives)} teeth pose derivatives for {len(bone_derivatives)} parameters")

        def lifted(j):
            values = self._lift.x.array.reshape(-1, 3)
            values[:] = 0.0
            values[problem.bone_blocks] = bone_derivatives[j]
            with self._rhs.localForm() as local:
                local.set(0.0)
            fem_petsc.apply_lifting(self._rhs, [jacobian_form], bcs=[[self._lift_bc]])
            self._rhs.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
            if teeth is not None:  # the teeth leave out the bone-held nodes: nothing on the rows set below
                teeth.add_pose_rate(problem.u.x.array, teeth_derivatives[j], self._rhs, scale=-1.0)
            fem_petsc.set_bc(self._rhs, [self._lift_bc])
        return self._solve_all(lifted, len(bone_derivatives))

    def cranium_columns(self) -> np.ndarray:
        """dX/d(M_c, t_c) for the 12 affine numbers (row-major M, then t), analytic.

        Exact when M_c is a rotation: the whole equilibrium then moves with the cranium frame.
        """
        problem = self.problem
        x = problem.dof_coordinates + problem.u.x.array.reshape(-1, 3)
        return frame_columns(x, problem.controls.cranium).reshape(12, -1)


def frame_columns(points: np.ndarray, frame) -> np.ndarray:
    """d(points)/d(M, t) (12, n, 3) for points that move with an affine frame x = M y + t."""
    y = (points - frame.translation) @ np.linalg.inv(frame.matrix).T
    columns = np.zeros((12,) + points.shape)
    for i in range(3):
        for j in range(3):
            columns[3 * i + j][:, i] = y[:, j]
        columns[9 + i][:, i] = 1.0
    return columns


def bone_position_derivatives(problem, pose_of, params: np.ndarray, step: float) -> np.ndarray:
    """dX^C/dp_i at the bone blocks for a bone pose ``pose_of(p) -> (cranium, jaw)``.

    Central differences; exact (up to round-off) for poses affine in p, such as the 12 numbers of
    an affine jaw frame, where any ``step`` will do; for the TMJ angles use a small step.
    """
    params = np.asarray(params, dtype=float)
    derivatives = []
    for i in range(len(params)):
        bump = np.zeros_like(params)
        bump[i] = step
        forward = problem.bone_positions(*pose_of(params + bump))
        backward = problem.bone_positions(*pose_of(params - bump))
        derivatives.append((forward - backward) / (2 * step))
    return np.array(derivatives)


def teeth_pose_derivatives(problem, pose_of, params: np.ndarray, step: float) -> list:
    """d(pose)/dp_i of each of the problem's teeth (``FaceProblem.teeth_poses``) for a bone pose
    ``pose_of(p) -> (cranium, jaw)``: per parameter, one (dM, dt) per teeth surface, by central
    differences (the parameters and ``step`` of ``bone_position_derivatives``). Empty tuples for
    a problem without teeth contact."""
    params = np.asarray(params, dtype=float)
    derivatives = []
    for i in range(len(params)):
        bump = np.zeros_like(params)
        bump[i] = step
        poses = []
        for sign in (1.0, -1.0):
            cranium, jaw = pose_of(params + sign * bump)
            poses.append(problem.teeth_poses(replace(problem.controls, cranium=cranium, jaw=jaw)))
        derivatives.append(tuple(((forward.matrix - backward.matrix) / (2 * step),
                                  (forward.translation - backward.translation) / (2 * step))
                                 for forward, backward in zip(*poses)))
    return derivatives
