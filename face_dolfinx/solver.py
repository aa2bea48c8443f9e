"""Quasistatic equilibrium by PETSc SNES, with an automatic continuation fallback.

Newton with a critical-point line search (PETSc ``cp``: the residual is the gradient of the
energy, so it finds where R(u + s du) . du = 0) solves R(u) = 0 for the given controls. New Dirichlet values enter through the first Newton step (lifting), which spreads a bone
motion smoothly into the flesh instead of shearing the layer of elements next to the bone. When
Newton fails (a step inverts an element and the residual is NaN, the tangent is indefinite far
from equilibrium, the line search stalls), ``solve_continuation`` restarts from the last
equilibrium and walks the controls towards the target in steps that halve on failure and grow
again on success; the log says so. Every option is a PETSc option under the solver's prefix
(default ``face_``), so a user can override any of them from the command line or a config.
"""
from dataclasses import dataclass
import logging
import time
from typing import Callable

from mpi4py import MPI
from petsc4py import PETSc
import numpy as np
import ufl
from dolfinx import fem
import dolfinx.fem.petsc as fem_petsc

log = logging.getLogger(__name__)

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

# Form compiler flags: -O2 keeps JIT time short for these long nonlinear kernels.
JIT_OPTIONS = {"cffi_extra_compile_args": ["-O3", "-march=native"], "cache_dir": None}


# Option names (by prefix) that QuasistaticSolver itself put in the PETSc options database, as
# opposed to options the user gave on the command line.
_OPTIONS_SET_BY_SOLVERS: dict[str, set[str]] = {}


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


class QuasistaticSolver:
    """Newton (SNES) for R(u) = 0 with Dirichlet conditions ``bcs`` whose values the owner sets.

    ``energy`` (optional) is the total potential, for reports and checks. The line search does not
    backtrack on it: near equilibrium its changes drown in round-off and stall the search.
    """

    def __init__(self, residual: ufl.Form, unknown: fem.Function, bcs: list, *,
                 jacobian: ufl.Form | None = None, energy: ufl.Form | None = None,
                 petsc_options: dict | None = None, options_prefix: str = "face_"):
        self.unknown = unknown
        self.bcs = bcs
        self.comm = unknown.function_space.mesh.comm
        self.residual_form = compile_form(residual)
        self.jacobian_form = compile_form(
            jacobian if jacobian is not None else ufl.derivative(residual, unknown))
        self.energy_form = compile_form(energy) if energy is not None else None

        self._residual_vector = fem_petsc.create_vector(self.residual_form)
        self.tangent = fem_petsc.create_matrix(self.jacobian_form)
        self.tangent.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        self._solution = unknown.vector.duplicate()
        self._prescribed = None  # work vector of bc_error

        self.snes = PETSc.SNES().create(self.comm)
        self.snes.setOptionsPrefix(options_prefix)
        opts = PETSc.Options()
        wanted = {options_prefix + key: value
                  for key, value in {**DEFAULT_PETSC_OPTIONS, **(petsc_options or {})}.items()}
        # The options database is global to the process: drop what an earlier solver with this
        # prefix put there and this one does not want, and overwrite the rest, so that each
        # solver gets its own petsc_options. A user's command-line PETSc option still wins.
        ours = _OPTIONS_SET_BY_SOLVERS.setdefault(options_prefix, set())
        for name in ours - wanted.keys():
            opts.delValue(name)
            ours.discard(name)
        for name, value in wanted.items():
            if name in ours or not opts.hasName(name):
                opts[name] = value
                ours.add(name)
        self.snes.setFunction(self._assemble_residual, self._residual_vector)
        self.snes.setJacobian(self._assemble_tangent, self.tangent)
        self.snes.setFromOptions()
        self.snes.getKSP().setFromOptions()

    # -- callbacks ---------------------------------------------------------------------------
    def _set_unknown(self, x: PETSc.Vec) -> None:
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        x.copy(self.unknown.vector)
        self.unknown.vector.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)

    def _assemble_residual(self, snes, x, b):
        self._set_unknown(x)
        with b.localForm() as b_local:
            b_local.set(0.0)
        fem_petsc.assemble_vector(b, self.residual_form)
        # Lifting costs twice the residual (it runs the tangent kernel on bone-adjacent cells) and
        # vanishes once the iterate holds the Dirichlet values: after the first full step.
        if self.bc_error(x) > 0.0:
            fem_petsc.apply_lifting(b, [self.jacobian_form], bcs=[self.bcs], x0=[x], scale=-1.0)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        fem_petsc.set_bc(b, self.bcs, x, -1.0)

    def _assemble_tangent(self, snes, x, A, P):
        A.zeroEntries()
        fem_petsc.assemble_matrix(A, self.jacobian_form, bcs=self.bcs)
        A.assemble()

    # -- public ------------------------------------------------------------------------------
    def energy(self) -> float:
        """Total energy at the current unknown (NaN if an element is inverted)."""
        return global_sum(self.comm, fem.assemble_scalar(self.energy_form))

    def residual_norm(self) -> float:
        """Norm of the free-dof residual at the current unknown (Dirichlet rows excluded)."""
        self.unknown.vector.copy(self._solution)
        self._assemble_residual(self.snes, self._solution, self._residual_vector)
        return self._residual_vector.norm()

    def newton(self) -> tuple[bool, int, str]:
        """One SNES solve from the current unknown; Dirichlet values are reached by the Newton steps."""
        self.unknown.vector.copy(self._solution)
        self.snes.solve(None, self._solution)
        self._set_unknown(self._solution)
        reason = self.snes.getConvergedReason()
        if reason > 0 and self.bc_error() > 1e-8:
            return False, self.snes.getIterationNumber(), "Dirichlet values not reached"
        return reason > 0, self.snes.getIterationNumber(), _reason_name(reason)

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
        motion of the head). Tries t = 1 at once; on failure halves the step, and doubles it after
        each success.
        """
        start = time.perf_counter()
        converged_state = self.unknown.vector.copy()
        t, step, newton_total, steps_taken, halvings = 0.0, 1.0, 0, 0, 0
        while t < 1.0:
            target = min(1.0, t + step)
            if predictor is not None:
                predictor(t, target)
            set_controls(target)
            ok, iterations, why = self.newton()
            newton_total += iterations
            if ok:
                t, steps_taken = target, steps_taken + 1
                self.unknown.vector.copy(converged_state)
                step = min(2.0 * step, 1.0 - t) if t < 1.0 else step
                continue
            halvings += 1
            if halvings > max_halvings:
                converged_state.copy(self.unknown.vector)
                self.unknown.vector.ghostUpdate(addv=PETSc.InsertMode.INSERT,
                                                mode=PETSc.ScatterMode.FORWARD)
                set_controls(t)
                raise EquilibriumError(
                    f"no equilibrium beyond {t:.4f} of the way to the target controls after "
                    f"{halvings - 1} step halvings (last failure: {why}); the state is left at the "
                    f"last equilibrium")
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
