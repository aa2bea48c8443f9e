"""Dynamic re-simulation: the face driven over time with mass and damping (sifakis2005 section 9).

The quasistatic face (``FaceProblem``) answers "where is the flesh at rest for these controls";
played back over time, the flesh would also swing: the cheeks and the nose lag behind a fast head
shake and overshoot. ``FaceProblem.dynamics(settings)`` adds inertia and damping to its residual
and returns a ``DynamicFace``, which steps the state (displacement, velocity, acceleration) in time:

    M a(t) + C v(t) + R(u(t); controls(t)) = 0,    u = bone motion on the bone-attached nodes,

with M the consistent mass matrix of density rho (``forms.Inertia``; units: mm, kPa, mN, kg and
seconds, 1000 kg/m^3 = 1e-6 kg/mm^3), C the damping (``forms.ViscousDamping``: a drag alpha M and
a Kelvin-Voigt viscosity eta) and R the quasistatic residual (flesh, muscles, pressure). Schemes,
both implicit and unconditionally stable for linear problems:

- ``newmark``: Newmark's average acceleration (beta = 1/4, gamma = 1/2, the trapezoidal rule):
  second order, no numerical damping; an undamped free vibration keeps its energy to O(dt^2);
- ``backward_euler``: first order, strongly dissipative (it damps every mode whose period is not
  long against the step), for a robust, smooth playback.

Each step solves for u(t + dt) by the project's Newton (``QuasistaticSolver``: MUMPS, the inversion
guard, the critical-point line search; the step's residual is the gradient of an incremental
potential, so that line search applies), with a = c0 (u - u_n) - c1 v_n - c2 a_n and
v = d0 (u - u_n) + d1 v_n + d2 a_n: the tangent is K + c0 M + d0 C. The bone motion of the new time
enters as Dirichlet values, whose velocities and accelerations follow by the same formulas.
A step whose Newton fails is halved (and grows back after successes), down to
``time_step / 2^max_halvings``; beyond that ``DynamicsError`` names the time and the state is left at
the last converged step (frames already handed to ``on_frame`` are kept).

Contact (a problem's rigid objects, its teeth, the lips on each other; docs/contact.md) is part of
the incremental potential: the barrier energy adds to it, its gradient to the step's residual and
its Hessian to the tangent, and its collision-free step bound shortens every Newton step next to
the inversion guard's, so no iterate of any time step penetrates. The barrier is conservative:
with Newmark the energy (strain, barrier and kinetic) is kept to the step's accuracy while the
flesh bounces on an object, backward Euler never gains. The objects and the teeth stand at their
poses of the step's end time. An object that moves into the flesh within a step (or teeth that
close on the lining) would leave the start inside it, where the barrier is infinite: the step then
starts from the quasistatic solve's held move (``ContactPotential.move_to``: the surface pushed out
of the new pose, the dent held while the flesh follows it, by this integrator's Newton, inertia
included), after which Newton on the incremental potential releases the held nodes. The held move
only makes an admissible start: the step's result is the minimiser of the incremental potential
(strongly convex at these steps, c0 M dominating) whatever the start. Where the poses' change
leaves every node most of its gap (``needs_held_move``), the barrier alone pushes the flesh.
"""
from dataclasses import dataclass
import logging
import math
import time
from typing import Callable

from mpi4py import MPI
from petsc4py import PETSc
import numpy as np
from dolfinx import fem
import dolfinx.fem.petsc as fem_petsc


log = logging.getLogger(__name__)

SCHEMES = ("newmark", "backward_euler")
# Newmark's average acceleration.
NEWMARK_BETA, NEWMARK_GAMMA = 0.25, 0.5
# The bones' velocity and acceleration: differences over this fraction of the time step.
BONE_RATE_STEP = 1e-3
# Soft tissue, 1000 kg/m^3, in kg/mm^3 (forms.inertia: the time unit is then the second).
TISSUE_DENSITY = 1e-6


class DynamicsError(ValueError):
    """Bad dynamic settings or times, or a time step that does not converge even when subdivided."""


@dataclass(frozen=True)
class DynamicSettings:
    """``density`` (kg/mm^3), ``mass_damping`` alpha (1/s: C = alpha M), ``viscosity`` eta (kPa s,
    Kelvin-Voigt), ``scheme`` (``SCHEMES``), ``time_step``: the largest substep (s), halved at
    most ``max_halvings`` times when Newton fails."""

    density: float = TISSUE_DENSITY
    mass_damping: float = 0.0
    viscosity: float = 0.0
    scheme: str = "newmark"
    time_step: float = 1.0 / 240.0
    max_halvings: int = 6

    def __post_init__(self):
        def positive(name, allow_zero=False):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or (
                    value < 0 if allow_zero else value <= 0):
                raise DynamicsError(f"dynamic {name} = {value!r}: give a {'non-negative' if allow_zero else 'positive'} "
                                    "number")
        positive("density")
        positive("time_step")
        positive("mass_damping", allow_zero=True)
        positive("viscosity", allow_zero=True)
        if self.scheme not in SCHEMES:
            raise DynamicsError(f"dynamic scheme {self.scheme!r}: give one of {', '.join(SCHEMES)}")
        if not (isinstance(self.max_halvings, int) and self.max_halvings >= 0):
            raise DynamicsError(f"dynamic max_halvings = {self.max_halvings!r}: give an integer >= 0")

    @property
    def damped(self) -> bool:
        return self.mass_damping > 0 or self.viscosity > 0


def needs_held_move(contact, displacement: np.ndarray, old_poses, new_poses) -> bool:
    """Whether moving ``contact``'s objects from ``old_poses`` to ``new_poses`` would start a step
    inside an object or against it (``ContactPotential.closes_in``: for a sphere's triangle barrier
    the skin's triangles count too): then the step starts from the held move (module docstring).
    The same on every rank."""
    return contact.closes_in(displacement, old_poses, new_poses)


class TimeLevels:
    """The last converged state (displacement, velocity, acceleration: functions of the
    displacement's space) and the scheme's coefficients (constants: a new step size recompiles
    nothing), from which the forms take the new acceleration and velocity as functions of u."""

    def __init__(self, space: fem.FunctionSpace):
        mesh = space.mesh
        self.displacement = fem.Function(space, name="displacement_previous")
        self.velocity = fem.Function(space, name="velocity")
        self.acceleration = fem.Function(space, name="acceleration")
        self.coefficients = [fem.Constant(mesh, PETSc.ScalarType(0.0)) for _ in range(6)]
        self.values = np.zeros(6)

    def new_acceleration(self, u):
        c0, c1, c2 = self.coefficients[:3]
        return c0 * (u - self.displacement) - c1 * self.velocity - c2 * self.acceleration

    def new_velocity(self, u):
        d0, d1, d2 = self.coefficients[3:]
        return d0 * (u - self.displacement) + d1 * self.velocity + d2 * self.acceleration

    def set_step(self, scheme: str, dt: float) -> None:
        if scheme == "newmark":
            beta, gamma = NEWMARK_BETA, NEWMARK_GAMMA
            values = (1.0 / (beta * dt * dt), 1.0 / (beta * dt), 0.5 / beta - 1.0,
                      gamma / (beta * dt), 1.0 - gamma / beta, dt * (1.0 - 0.5 * gamma / beta))
        else:
            values = (1.0 / (dt * dt), 1.0 / dt, 0.0, 1.0 / dt, 0.0, 0.0)
        self.values = np.array(values)
        for constant, value in zip(self.coefficients, values):
            constant.value = value

    def accept(self, u: np.ndarray) -> None:
        """The converged displacement ``u`` (local array with ghosts) becomes the last state."""
        c0, c1, c2, d0, d1, d2 = self.values
        increment = u - self.displacement.x.array
        acceleration = c0 * increment - c1 * self.velocity.x.array - c2 * self.acceleration.x.array
        self.velocity.x.array[:] = d0 * increment + d1 * self.velocity.x.array + d2 * self.acceleration.x.array
        self.acceleration.x.array[:] = acceleration
        self.displacement.x.array[:] = u


@dataclass
class AdvanceReport:
    """What reaching one time took: substeps, Newton iterations, the smallest substep (s)."""

    substeps: int
    newton_iterations: int
    smallest_substep: float
    seconds: float


class DynamicFace:
    """The time integrator of a ``FaceProblem`` (module docstring); made by
    ``FaceProblem.dynamics(settings)``, which owns its forms. The problem's displacement is the
    state's displacement; its controls are those of the current time."""

    def __init__(self, problem, settings: DynamicSettings, solver, levels: TimeLevels,
                 mass_form, kinetic_energy_form):
        self.problem, self.settings, self.solver, self.levels = problem, settings, solver, levels
        self.comm = problem.comm
        self.time = 0.0
        self._substep = settings.time_step
        self._mass_form, self._kinetic_form = mass_form, kinetic_energy_form
        self._begun = False
        self.held_moves = 0  # steps started from the held move so far, per object or teeth (a cost counter)
        self.start()

    # -- state -------------------------------------------------------------------------------
    def start(self, time: float = 0.0, velocity: np.ndarray | None = None) -> None:
        """Start at ``time`` from the problem's current displacement and controls, with
        ``velocity`` (local dof array; default at rest). The first step takes the bones' velocity
        and acceleration from its controls and the flesh's acceleration from the balance of forces
        (``_begin``): an equilibrium at rest starts unaccelerated, a released shape with the
        acceleration that its unbalanced forces give."""
        if not math.isfinite(time):
            raise DynamicsError(f"start time {time!r}: give a finite number of seconds")
        u = self.problem.u.x.array
        self.levels.displacement.x.array[:] = u
        self.levels.velocity.x.array[:] = 0.0 if velocity is None else velocity
        self.levels.acceleration.x.array[:] = 0.0
        self.time = float(time)
        self._substep = self.settings.time_step
        self._begun = False

    def _set_bone_rates(self, controls_at, t: float, direction: float) -> None:
        """Velocity and acceleration of the bone-attached dofs at ``t`` from their prescribed
        motion, by one-sided differences over ``BONE_RATE_STEP`` of the time step, forwards
        (``direction`` 1, at the start) or backwards (-1): the scheme's own formulas applied to
        prescribed displacements carry any error (e.g. a start at rest of bones already moving)
        from step to step, alternating in sign, without decay."""
        h = direction * BONE_RATE_STEP * self.settings.time_step
        positions = []
        for k in range(3):
            controls = controls_at(t + k * h)
            positions.append(self.problem.bone_positions(controls.cranium, controls.jaw))
        p0, p1, p2 = positions
        blocks = self.problem.bone_blocks
        self.levels.velocity.x.array.reshape(-1, 3)[blocks] = (-3.0 * p0 + 4.0 * p1 - p2) / (2.0 * h)
        self.levels.acceleration.x.array.reshape(-1, 3)[blocks] = (p0 - 2.0 * p1 + p2) / (h * h)

    def _begin(self, controls_at) -> None:
        self._set_bone_rates(controls_at, self.time, 1.0)
        self._balance_acceleration()
        self._begun = True

    def _assembled_residual(self) -> PETSc.Vec:
        """The step's residual at the unknown, the contact terms' gradients included, zero on the
        Dirichlet dofs."""
        form = self.solver.residual_form
        vector = fem_petsc.create_vector(form)
        with vector.localForm() as local:
            local.set(0.0)
        fem_petsc.assemble_vector(vector, form)
        vector.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        for term in self.solver.energy_terms:
            term.add_gradient(self.problem.u.vector, vector)
        fem_petsc.set_bc(vector, self.problem.bcs, scale=0.0)
        return vector

    def _balance_acceleration(self) -> None:
        """The free dofs' acceleration from M a = -(R(u) + C v), the bones' acceleration (set) on
        the right-hand side (the residual of a step with every scheme coefficient zero but d1 = 1 is
        R(u) + C v; R includes the contact forces)."""
        saved = self.levels.values.copy()
        for constant, value in zip(self.levels.coefficients, (0.0, 0.0, 0.0, 0.0, 1.0, 0.0)):
            constant.value = value
        force = self._assembled_residual()
        for constant, value in zip(self.levels.coefficients, saved):
            constant.value = value
        force.scale(-1.0)
        acceleration = self.levels.acceleration.vector
        bones = acceleration.duplicate()  # the bones' acceleration alone
        acceleration.copy(bones)
        fem_petsc.set_bc(bones, self.problem.bcs, scale=0.0)
        bones.axpy(-1.0, acceleration)
        bones.scale(-1.0)
        full_mass = fem_petsc.assemble_matrix(self._mass_form)
        full_mass.assemble()
        coupling = force.duplicate()
        full_mass.mult(bones, coupling)
        force.axpy(-1.0, coupling)
        fem_petsc.set_bc(force, self.problem.bcs, scale=0.0)
        mass = fem_petsc.assemble_matrix(self._mass_form, bcs=self.problem.bcs)
        mass.assemble()
        ksp = PETSc.KSP().create(self.comm)
        ksp.setOperators(mass)
        ksp.setType("cg")
        ksp.getPC().setType("jacobi")
        ksp.setTolerances(rtol=1e-12, atol=1e-30, max_it=2000)
        free = force.duplicate()
        ksp.solve(force, free)
        if ksp.getConvergedReason() < 0:
            raise DynamicsError(f"the initial acceleration (mass matrix solve) did not converge "
                                f"({ksp.getConvergedReason()})")
        free.axpy(1.0, bones)  # the solve gave 0 on the bone rows
        free.copy(acceleration)
        acceleration.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        for item in (ksp, mass, full_mass, force, coupling, bones, free):
            item.destroy()

    def kinetic_energy(self) -> float:
        """1/2 v.M v (mN mm = uJ) of the last converged state."""
        return self.comm.allreduce(fem.assemble_scalar(self._kinetic_form), op=MPI.SUM)

    def total_energy(self) -> float:
        """Strain and contact barrier energy (``FaceProblem.energy``, at the current controls) plus
        kinetic energy."""
        return self.problem.energy() + self.kinetic_energy()

    @property
    def velocity(self) -> np.ndarray:
        return self.levels.velocity.x.array

    @property
    def acceleration(self) -> np.ndarray:
        return self.levels.acceleration.x.array

    # -- stepping ----------------------------------------------------------------------------
    def step(self, controls, dt: float) -> tuple[bool, int, str]:
        """One implicit step of ``dt`` seconds to ``controls``; on failure the state stays."""
        problem, levels = self.problem, self.levels
        old_controls = problem.controls.copy()
        levels.set_step(self.settings.scheme, dt)
        start = levels.displacement.x.array
        # The last shape carried along the cranium's motion, as the quasistatic solve starts (a
        # Taylor extrapolation with the last acceleration, which keeps the stiff modes' ringing
        # under average acceleration, started the 5K face's head shake at residuals of 1e6 mN
        # and needed halved steps; this start took 6 Newton iterations a step).
        change = controls.cranium.compose(old_controls.cranium.inverse())
        X = problem.dof_coordinates
        guess = (change.apply(X + start.reshape(-1, 3)) - X).reshape(-1)
        guard = problem.solver.inversion_guard
        fraction = guard.step_fraction(start, start - guess) if guard is not None else 1.0
        if problem.lips is not None:  # nor may the start take the lips through each other
            fraction *= problem.lips.admissible_fraction(start, start + fraction * (guess - start))
        problem.u.x.array[:] = start + fraction * (guess - start)
        held = self._held_moves(old_controls, controls, change)
        problem.set_controls(controls)
        self.solver.controls_changed()  # the time levels changed (coefficients of its forms)
        iterations = 0
        for contact, poses in held:
            iterations += contact.move_to(poses, self.solver)
            self.held_moves += 1
        ok, newton, why = self.solver.newton()
        iterations += newton
        if ok:
            levels.accept(problem.u.x.array)
        else:
            problem.u.x.array[:] = start
            problem.set_controls(old_controls)
        return ok, iterations, why

    def _held_moves(self, before, controls, change) -> list:
        """(contact, new poses) of the problem's objects and teeth whose move from ``before`` to
        ``controls`` needs the held move at the start now in the unknown (``needs_held_move``);
        the teeth's old poses carried along the cranium's ``change``, as the start was."""
        problem, held = self.problem, []
        displacement = problem.u.x.array
        if problem.contact is not None and needs_held_move(problem.contact, displacement, before.objects,
                                                           controls.objects):
            held.append((problem.contact, controls.objects))
        if problem.teeth_contact is not None:
            old = tuple(change.compose(pose) for pose in problem.teeth_poses(before))
            new = problem.teeth_poses(controls)
            if needs_held_move(problem.teeth_contact, displacement, old, new):
                held.append((problem.teeth_contact, new))
        return held

    def advance(self, end: float, controls_at: Callable[[float], object]) -> AdvanceReport:
        """Integrate to time ``end`` (s) with the controls ``controls_at(t)`` (a ``Controls``) at
        each substep's end, in substeps of at most ``settings.time_step``, halved on failure."""
        began = time.perf_counter()
        largest = self.settings.time_step
        smallest_allowed = largest * 0.5 ** self.settings.max_halvings
        substeps, newton, smallest, halvings = 0, 0, math.inf, 0
        if not self._begun:
            self._begin(controls_at)
        while end - self.time > 1e-9 * largest:
            dt = min(self._substep, end - self.time)
            ok, iterations, why = self.step(controls_at(self.time + dt), dt)
            newton += iterations
            if ok:
                self.time = end if end - (self.time + dt) <= 1e-9 * largest else self.time + dt
                self._set_bone_rates(controls_at, self.time, -1.0)
                substeps += 1
                smallest = min(smallest, dt)
                self._substep = min(2.0 * self._substep, largest)
                continue
            halvings += 1
            if dt <= smallest_allowed * (1 + 1e-9):
                raise DynamicsError(
                    f"no converged time step at t = {self.time:.6g} s: a substep of {dt:.3g} s failed ({why}) "
                    f"after {halvings} halving(s) (settings.max_halvings = {self.settings.max_halvings}); "
                    f"the state is left at t = {self.time:.6g} s")
            if self.comm.rank == 0:
                log.info("time step %.3g s from t = %.6g s failed (%s): halved", dt, self.time, why)
            self._substep = dt / 2.0
        return AdvanceReport(substeps, newton, smallest, time.perf_counter() - began)

    def run(self, controls_at: Callable[[float], object], times, on_frame=None) -> list[AdvanceReport]:
        """Integrate through ``times`` (s, strictly increasing, the first not before the current
        time), calling ``on_frame(index, t, report)`` at each: what it writes is kept if a later
        step fails. A first time equal to the current one is the current state (report None)."""
        times = np.asarray(times, dtype=float).reshape(-1)
        if times.size == 0 or not np.all(np.isfinite(times)):
            raise DynamicsError(f"times {times.tolist()!r}: give one or more finite times (s)")
        if np.any(np.diff(times) <= 0):
            bad = int(np.flatnonzero(np.diff(times) <= 0)[0])
            raise DynamicsError(f"times must increase: {times[bad]:g} s is followed by {times[bad + 1]:g} s")
        if times[0] < self.time - 1e-12:
            raise DynamicsError(f"the first time {times[0]:g} s lies before the current time {self.time:g} s")
        reports = []
        for index, t in enumerate(times):
            report = self.advance(t, controls_at) if t > self.time + 1e-12 else None
            reports.append(report)
            if on_frame is not None:
                on_frame(index, float(t), report)
        return reports
