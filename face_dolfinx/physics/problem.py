"""The quasistatic face: spaces, forms, boundary conditions and the equilibrium solver.

``FaceProblem`` alone owns the function spaces, the compiled forms and the SNES solver; the
constitutive model is ``face_dolfinx.physics.material.FaceMaterial``. Controls
(muscle activations, cranium frame, mandible frame relative to the cranium, and optionally the
intraoral pressure) live in DG0 functions, a ``fem.Constant`` and the Dirichlet values, so changing
them never recompiles a form.

Rigid kinematic objects (``contact``, ``face_dolfinx.physics.contact``: a sphere, a half-space)
press on a tagged surface (the skin) through a barrier energy the solver adds to the flesh's (a
sphere on the surface's triangles, ``face_dolfinx.physics.face_contact``, the others on its nodes); their
poses are controls (``Controls.objects``), each solve pushes the surface out of an object's new pose
before Newton (the barrier needs a start that overlaps nothing), and the continuation fallback walks
the poses like the other controls. With ``ContactSettings(teeth=True)`` the model's teeth (closed
triangle surfaces, ``FaceModel.teeth``) hold the lining of the lips and cheeks by the same barrier;
their poses are not controls of their own but the bone frames they are fixed to (the upper teeth
the cranium's, the lower ones the mandible's), so opening the jaw moves the lower teeth.

The intraoral pressure (``intraoral_pressure=True``, a model with an ``oral`` surface) is the air
pressure in the mouth above the ambient one, a follower load on the lining of the lips and cheeks:
positive pushes them out (puffed cheeks, pushed lips), negative draws them in (suction). A follower
load on a surface with a free border has a non-symmetric tangent, which MUMPS then factorises by
LU instead of Cholesky.

Muscles are embedded per tetrahedron (Sifakis et al. 2005 section 3). Rather than one UFL term per
muscle (32 terms of piecewise curves make FFCx slow and the kernels long), each cell carries K
"slots" (K = the largest number of muscles overlapping in one cell): slot k holds the fiber, the
weight sigma_max * fraction and the activation of the k-th muscle present there. The forms see K
fiber terms whatever the number of muscles; activations are scattered into the slots.
"""
from dataclasses import dataclass, replace
import logging
import time

from mpi4py import MPI
from petsc4py import PETSc
import numpy as np
from scipy.spatial import cKDTree
import ufl
from dolfinx import fem
from dolfinx import mesh as dolfinx_mesh
import dolfinx.fem.petsc as fem_petsc

import forms
from face_dolfinx.model.bones import AffineMap
from face_dolfinx.model.folder import cell_midpoints
from face_dolfinx.model.regions import material_fields
from face_dolfinx.equilibrium.definite import DefiniteFleshTangent
from face_dolfinx.equilibrium.solver import (REFRESH_CONTRACTION, FactorReusePolicy, InversionGuard,
                                             QuasistaticSolver, SolveReport, compile_form)
from face_dolfinx.physics.contact import CARRY_REACH, UNMOVED, ContactPotential, ContactSettings
from face_dolfinx.physics.face_contact import FACE_NEWTON_ITERATIONS, FaceContactPotential
from face_dolfinx.physics.object_features import contact_potential
from face_dolfinx.physics.self_contact import LIP_NEWTON_ITERATIONS, LipContact, LipContactSettings, lip_facets
from face_dolfinx.physics.material import FaceMaterial, FiberSlot
from face_dolfinx.physics.rigid_mesh import TriangleMesh

log = logging.getLogger(__name__)

# mm: the farthest a Gauss-Newton prediction's lining node is moved out of the teeth
# (``FaceProblem._lining_projected``) rather than the prediction cut short.
PROJECTION_LIMIT = 0.5
# mm: the widths, smallest first, over which a prediction cut short around a few nodes returns to
# its whole way (``FaceProblem._bounded_locally``); the first that flattens no cell is taken.
BLEND_WIDTHS = (2.0, 4.0, 8.0, 16.0)
LOCAL_CUT_NODES = 64  # the most vertices of flattened cells for which it is cut short around them only


@dataclass
class Controls:
    """Everything that drives the face: activations, cranium frame, jaw frame (rel. cranium), the
    intraoral pressure (kPa; 0 on a problem without that control) and the poses of the contact
    objects (world frame; empty on a problem without them)."""

    activations: np.ndarray
    cranium: AffineMap
    jaw: AffineMap
    pressure: float = 0.0
    objects: tuple = ()

    def interpolate(self, other: "Controls", t: float) -> "Controls":
        return Controls((1 - t) * self.activations + t * other.activations,
                        self.cranium.interpolate(other.cranium, t), self.jaw.interpolate(other.jaw, t),
                        (1 - t) * self.pressure + t * other.pressure,
                        tuple(a.geodesic(b, t) for a, b in zip(self.objects, other.objects)))

    def copy(self) -> "Controls":
        return Controls(self.activations.copy(), self.cranium, self.jaw, self.pressure, tuple(self.objects))

    def same_as(self, other: "Controls") -> bool:
        """The same values exactly."""
        return (np.array_equal(self.activations, other.activations) and self.cranium.same_as(other.cranium)
                and self.jaw.same_as(other.jaw) and self.pressure == other.pressure
                and len(self.objects) == len(other.objects)
                and all(a.same_as(b) for a, b in zip(self.objects, other.objects)))


@dataclass
class MuscleSlots:
    """Muscle data scattered into K per-cell slots (see module docstring)."""

    muscle_of_slot: np.ndarray  # (K, num DG0 dofs) muscle index or -1, in DG0 dof order
    weight: list                # K DG0 functions: sigma_max * volume fraction
    fiber: list                 # K DG0 vector functions: unit rest fiber direction
    activation: list            # K DG0 functions: the activation of the slot's muscle
    direction: list             # K DG0 functions: an activation direction (for f_i = df/da_i)


def _dg0_cell_dofs(space: fem.FunctionSpace) -> np.ndarray:
    """DG0 dof of every local cell (owned and ghost)."""
    return space.dofmap.list.array.reshape(-1)


def _cell_tags(mesh, cells) -> dolfinx_mesh.MeshTagsMetaClass:
    """Cell tags marking ``cells`` (local indices) with 1."""
    cells = np.unique(np.asarray(cells, dtype=np.int32))
    return dolfinx_mesh.meshtags(mesh, mesh.topology.dim, cells, np.ones_like(cells))


def build_muscle_slots(model, mesh) -> MuscleSlots:
    entries_cell, entries_muscle, entries_weight, entries_fiber = [], [], [], []
    for index, muscle in enumerate(model.muscles):
        stress = model.peak_stress(index)
        entries_cell.append(np.asarray(muscle.cells, dtype=np.int64))
        entries_muscle.append(np.full(len(muscle.cells), index))
        entries_weight.append(stress * np.asarray(muscle.fraction, dtype=float))
        entries_fiber.append(np.asarray(muscle.fiber, dtype=float).reshape(-1, 3))
    cells = np.concatenate(entries_cell) if entries_cell else np.zeros(0, dtype=np.int64)
    order = np.argsort(cells, kind="stable")
    cells = cells[order]
    muscles = np.concatenate(entries_muscle)[order] if entries_cell else cells
    weights = np.concatenate(entries_weight)[order] if entries_cell else np.zeros(0)
    fibers = np.concatenate(entries_fiber)[order] if entries_cell else np.zeros((0, 3))
    # Slot of each entry = its rank among the entries of the same cell.
    first_of_cell = np.searchsorted(cells, cells, side="left")
    slot = np.arange(len(cells)) - first_of_cell
    local_slots = int(slot.max()) + 1 if len(slot) else 0
    num_slots = max(1, mesh.comm.allreduce(local_slots, op=MPI.MAX))  # same forms on every rank

    DG0 = fem.FunctionSpace(mesh, ("DG", 0))
    DG0v = fem.VectorFunctionSpace(mesh, ("DG", 0))
    dofs = _dg0_cell_dofs(DG0)
    muscle_of_slot = -np.ones((num_slots, len(dofs)), dtype=np.int64)
    weight, fiber, activation, direction = [], [], [], []
    for k in range(num_slots):
        in_slot = slot == k
        c = cells[in_slot]
        muscle_of_slot[k, dofs[c]] = muscles[in_slot]
        w = fem.Function(DG0, name=f"muscle_weight_{k}")
        w.x.array[dofs[c]] = weights[in_slot]
        f = fem.Function(DG0v, name=f"fiber_{k}")
        f_values = f.x.array.reshape(-1, 3)
        f_values[:, 0] = 1.0  # any unit vector where the slot is empty (weight 0 there)
        f_values[dofs[c]] = fibers[in_slot]
        weight.append(w)
        fiber.append(f)
        activation.append(fem.Function(DG0, name=f"activation_{k}"))
        direction.append(fem.Function(DG0, name=f"activation_direction_{k}"))
    # Slot data come from every rank's own (owned + ghost) cells: nothing to scatter.
    return MuscleSlots(muscle_of_slot, weight, fiber, activation, direction)


def build_material_fields(model, mesh) -> dict[str, fem.Function] | None:
    """The flesh parameters mu10, mu01, kappa (kPa) and the passive fibre scale as DG0 functions
    with the model's regional overrides (``face_dolfinx.model.regions``); None for a model without
    overrides, whose forms keep the parameters as numbers: FFCx folds those into the kernels'
    constants, and the same values in DG0 functions change a solve in the last bit (8e-16 mm on
    the slab), so a uniform model gives the results it always gave, to the bit."""
    if not model.material_overrides:
        return None
    DG0 = fem.FunctionSpace(mesh, ("DG", 0))
    dofs = _dg0_cell_dofs(DG0)
    fields = {}
    for name, values in material_fields(model, cell_midpoints(mesh)).items():
        function = fem.Function(DG0, name=f"material_{name}")
        function.x.array[dofs] = values  # every local cell's own value: nothing to scatter
        fields[name] = function
    return fields


class FaceProblem:
    """Quasistatic face for given activations and bone frames.

    Parameters
    ----------
    model : FaceModel (``face_dolfinx.model.folder``): mesh, facet tags, muscles, material.
    degree : polynomial degree of the displacement (1 or 2; 2 cures most volumetric locking).
    quadrature_degree : defaults to the degree that integrates the P1 forms exactly (1) and
        2 for P2; FFCx's own estimate for these forms is far too high.
    petsc_options : PETSc options for the SNES/KSP/PC (prefix ``face_``), e.g.
        {"pc_type": "hypre", "ksp_type": "cg"} to try AMG instead of MUMPS Cholesky.
    reuse_factorization : keep the last MUMPS factor as Newton's matrix across iterations and
        solves (modified Newton), refactorising only when an iteration contracts the residual
        too little (see solver.py).
    krylov_on_old_factor : with ``reuse_factorization``, solve each Newton correction by GMRES on
        the exact (matrix-free) tangent preconditioned by the old factor, refactorising only when
        GMRES slows (solver.KRYLOV_OPTIONS): exact Newton steps at a residual evaluation and a
        solve per GMRES iteration. Not faster at 404K P1 tets (docs/performance.md); for meshes
        where a factorisation costs far more than a solve.
    newton_tolerance : mm; Newton has converged once a correction moves no dof further than this
        (``QuasistaticSolver.step_tolerance``). 1e-4 mm changed no fitted marker or activation
        error in docs/performance.md.
    newton_energy_tolerance : mN mm; with contact, Newton has also converged once a correction would
        release less energy than this (``QuasistaticSolver.energy_tolerance``): pressed lips slide in
        nearly free modes whose corrections the step tolerance measures in millimetres
        (docs/performance.md, "Contact in tracking"). None: the step tolerance alone.
    refresh_contraction : with ``reuse_factorization``, refactorise when a Newton iteration cuts the
        residual by less than this factor (0.25; 0.5 saved factorisations at 404K tets, where one
        costs as much as a dozen iterations, docs/performance.md).
    line_search_iterations : secant iterations of the critical-point line search per Newton step
        (PETSc ``snes_linesearch_max_it``; 1). 3 cut the slowest tracking frames at 404K tets from 94
        to 21 s, where Newton converges only linearly (docs/performance.md).
    inversion_guard : shorten Newton steps that would flatten a cell (``solver.InversionGuard``);
        off only to measure what the guard buys (``benchmarks/stability.py``; solves without a
        ``guess``, which the guard pulls back).
    intraoral_pressure : add the intraoral pressure control (module docstring); the model needs
        facets tagged ``oral``.
    contact : ``ContactSettings``: rigid objects pressing on the model's facets tagged
        ``contact.surface`` (module docstring, docs/contact.md); their poses join the controls.
    lip_contact : ``LipContactSettings``: the upper and lower lip press on each other instead of
        passing through (``face_dolfinx.physics.self_contact``, docs/contact.md).
        With ``contact.teeth`` the model's teeth touch the facets tagged ``contact.teeth_surface``
        (``teeth_contact``), moving with their bones.
    contact_relaxation : with contact, after each Newton correction the nodes a contact term
        pushes on are brought to their own equilibrium by a local Newton, the rest held
        (``equilibrium.relaxation``): fewer factorisations where pressed lips slide
        (docs/performance.md, "Contact in tracking"). None (default): only once a Newton solve
        crawls on them (``equilibrium.solver.CRAWL_CUTS``, docs/performance.md, "The lips'
        opening") or, with ``reuse_factorization``, where the residual's slow fall on the contact
        surfaces' nodes would refresh the factor (``SLOW_FALL_CONTACT_SHARE``, "Settling on the teeth");
        True: after every correction; False: never.
    definite_tangent : Newton's tangent takes each cell's flesh stiffness with its clearly negative
        curvature clamped (``equilibrium.definite``), until Newton is near the solution; the
        equilibrium is the same. None (default): on with any contact, where the teeth squeeze the
        lining, or an object the skin, into cells whose exact stiffness makes the tangent nearly
        singular (docs/performance.md, "A definite flesh tangent"); P1 displacements only.
    """

    def __init__(self, model, *, degree: int = 1, quadrature_degree: int | None = None,
                 petsc_options: dict | None = None, reuse_factorization: bool = False,
                 krylov_on_old_factor: bool = False, newton_tolerance: float = 1e-8,
                 newton_energy_tolerance: float | None = None, refresh_contraction: float = REFRESH_CONTRACTION, inversion_guard: bool = True,
                 line_search_iterations: int = 1, intraoral_pressure: bool = False,
                 contact: ContactSettings | None = None, lip_contact: LipContactSettings | None = None,
                 contact_relaxation: bool | None = None, definite_tangent: bool | None = None):
        if line_search_iterations < 1:
            raise ValueError(f"line_search_iterations = {line_search_iterations}: give 1 or more")
        self.model = model
        mesh = self.mesh = model.mesh
        self.comm = mesh.comm
        self.num_muscles = len(model.muscles)
        self.V = fem.VectorFunctionSpace(mesh, ("CG", degree))
        self.u = fem.Function(self.V, name="displacement")
        q = quadrature_degree if quadrature_degree is not None else max(1, 2 * (degree - 1))
        dx = ufl.dx(domain=mesh, metadata={"quadrature_degree": q})
        self.slots = build_muscle_slots(model, mesh)
        self.material_fields = build_material_fields(model, mesh)

        fields = self.material_fields
        self.material = FaceMaterial.from_parameters(model.material if fields is None else fields, [
            FiberSlot(f0, w, a) for w, f0, a in zip(self.slots.weight, self.slots.fiber, self.slots.activation)],
            passive_scale=1.0 if fields is None else fields["passive"])
        F = forms.deformation_gradient(self.u)
        energy = self.material.strain_energy(F) * dx
        v = ufl.TestFunction(self.V)
        # The residual from the laws' stresses: the tangent is then one automatic derivative.
        residual = ufl.inner(self.material.first_piola(F), ufl.grad(v)) * dx
        self.degree = degree
        self.has_pressure = intraoral_pressure
        self.pressure = fem.Constant(mesh, PETSc.ScalarType(0.0))
        if intraoral_pressure:
            # The cofactor J F^-T has degree 2(p-1), the test function p: 3p-2 integrates it exactly.
            oral_tag = self._surface_tag("oral", f"model {model.path}: no facets tagged 'oral' (the lining of the lips "
                                         "and cheeks), so it has no intraoral pressure control; rebuild a built-in "
                                         "or adapted model, or tag that surface in its mesh (docs/model_format.md)")
            oral = ufl.ds(domain=mesh, subdomain_data=model.facet_tags, subdomain_id=oral_tag,
                          metadata={"quadrature_degree": 3 * degree - 2})
            normal = ufl.FacetNormal(mesh)
            residual = residual - forms.FollowerPressure(self.pressure).virtual_work(F, normal, v) * oral
            # df/dp: the load of a unit pressure at the current shape (the residual is linear in p).
            self._pressure_load = compile_form(forms.FollowerPressure(1.0).virtual_work(F, normal, v) * oral)
        # df/da_i: the active stress with a direction in place of a, integrated over muscle i's
        # cells only (one compiled kernel, one form object per muscle's cells): 32 assemblies over
        # the whole mesh per Jacobian cost more than the factorisation at 50K tets.
        active_along_direction = ufl.inner(self.material.active_first_piola(F, self.slots.direction), ufl.grad(v))
        self._active_residuals = [
            compile_form(active_along_direction * ufl.dx(
                domain=mesh, subdomain_data=_cell_tags(mesh, muscle.cells), subdomain_id=1,
                metadata={"quadrature_degree": q}))
            for muscle in model.muscles]

        self.cranium_blocks, self.mandible_blocks = self._bone_dof_blocks()
        self.dof_coordinates = self.V.tabulate_dof_coordinates()[:, :3]
        self.bone_displacement = fem.Function(self.V, name="bone_displacement")
        self.bone_blocks = np.concatenate([self.cranium_blocks, self.mandible_blocks])
        self.bcs = [fem.dirichletbc(self.bone_displacement, self.bone_blocks)]
        # The tangent is the Hessian of the energy: symmetric, and positive definite near
        # equilibrium.
        # With the follower pressure it is not symmetric (module docstring): LU.
        general = {"pc_type": "lu"} if intraoral_pressure else {}
        self.contact = None
        if contact is not None and (contact.objects or not contact.teeth):
            tag = self._surface_tag(contact.surface, f"{contact.where}: model {model.path} has no facets tagged "
                                                     f"{contact.surface!r} to touch the objects")
            self.contact = contact_potential(self.V, model.facet_tags.find(tag), contact)
        if self.contact is not None:
            self.contact.check_clear(self.u.x.array)
        self.teeth_bones = tuple(model.teeth) if contact is not None and contact.teeth else ()
        self.teeth_contact = self._teeth_contact(contact) if contact is not None and contact.teeth else None
        self.lips = None
        if lip_contact is not None:
            self.lips = LipContact(self.V, *lip_facets(model, lip_contact), lip_contact, self.bone_blocks)
        # Whether a prediction with lip or teeth contact starts from the equilibrium carried with
        # the head (``_carried_with_head``); False only to measure it.
        self.carry_head = True
        # Whether a prediction that would flatten a few cells is cut short around them
        # (``_bounded_locally``) before it is cut as a whole; False only to measure it.
        self.bound_prediction_locally = True
        energy_terms = tuple(term for term in (self.contact, self.teeth_contact, self.lips) if term is not None)
        if definite_tangent is None:
            definite_tangent = degree == 1 and bool(energy_terms)
        # Pressed lips settle in many collision-limited Newton steps (75 for the 5K face's lips
        # closed by the orbicularis oris at 1): Newton is given room before continuation.
        lip_newton = {"snes_max_it": LIP_NEWTON_ITERATIONS} if self.lips is not None else {}
        if self.lips is None and isinstance(self.contact, FaceContactPotential):
            lip_newton = {"snes_max_it": FACE_NEWTON_ITERATIONS}  # likewise the triangles on a sphere
        # The time integrator adds inertia and damping to the residual, with its test function.
        self._residual, self._test_function = residual, v
        self._tangent_structure = "general" if intraoral_pressure else "spd"
        self._petsc_options = {"snes_linesearch_max_it": line_search_iterations, **general, **lip_newton,
                               **(petsc_options or {})}
        self.solver = QuasistaticSolver(residual, self.u, self.bcs, tangent=self._tangent_structure,
                                        energy=energy,
                                        petsc_options=self._petsc_options,
                                        inversion_guard=InversionGuard(self.V) if inversion_guard else None,
                                        reuse_policy=FactorReusePolicy(across_solves=reuse_factorization,
                                                                       refresh_contraction=refresh_contraction),
                                        krylov_on_old_factor=krylov_on_old_factor,
                                        step_tolerance=newton_tolerance,
                                        energy_tolerance=newton_energy_tolerance, keep_packed_coefficients=True,
                                        energy_terms=energy_terms, contact_relaxation=contact_relaxation,
                                        flesh_correction=(DefiniteFleshTangent(self.material.first_piola, F, self.u)
                                                          if definite_tangent else None))
        self.controls = self.rest_controls()
        self.set_controls(self.controls)

    def dynamics(self, settings=None):
        """A time integrator of this face (``face_dolfinx.equilibrium.dynamics.DynamicFace``): the
        residual with inertia and damping (``forms.Inertia``, ``forms.ViscousDamping``) of
        ``settings`` (``DynamicSettings``; default: tissue density, no damping, Newmark's average
        acceleration), its own Newton solver with this problem's options, inversion guard and
        contact terms (objects, teeth, lips: their barrier joins the incremental potential),
        starting from the current displacement and controls."""
        from face_dolfinx.equilibrium.dynamics import DynamicFace, DynamicSettings, TimeLevels
        settings = settings if settings is not None else DynamicSettings()
        levels = TimeLevels(self.V)
        # rho u.v integrated exactly for degree p: 2p.
        dx = ufl.dx(domain=self.mesh, metadata={"quadrature_degree": 2 * self.degree})
        v = self._test_function
        inertia = forms.Inertia(settings.density)
        residual = self._residual + inertia.virtual_work(levels.new_acceleration(self.u), v) * dx
        if settings.damped:
            damping = forms.ViscousDamping(settings.density, settings.mass_damping, settings.viscosity)
            residual = residual + damping.virtual_work(levels.new_velocity(self.u), v) * dx
        solver = QuasistaticSolver(residual, self.u, self.bcs, tangent=self._tangent_structure,
                                   petsc_options=self._petsc_options,
                                   inversion_guard=self.solver.inversion_guard,
                                   step_tolerance=self.solver.step_tolerance,
                                   energy_tolerance=self.solver.energy_tolerance, keep_packed_coefficients=True,
                                   energy_terms=self.solver.energy_terms,
                                   contact_relaxation=self.solver.contact_relaxation)
        mass = compile_form(inertia.virtual_work(ufl.TrialFunction(self.V), v) * dx)
        kinetic_energy = compile_form(inertia.kinetic_energy(levels.velocity) * dx)
        return DynamicFace(self, settings, solver, levels, mass, kinetic_energy)

    # -- set-up ------------------------------------------------------------------------------
    def _surface_tag(self, name: str, missing: str) -> int:
        """The tag value of the model's surface ``name``; ValueError(``missing``) if no facet on any
        rank carries it."""
        tag = self.model.boundary_ids.get(name)
        count = 0 if tag is None else self.comm.allreduce(len(self.model.facet_tags.find(tag)), op=MPI.SUM)
        if count == 0:
            raise ValueError(missing)
        return tag

    def _teeth_contact(self, settings: ContactSettings) -> ContactPotential:
        """The barrier of the model's teeth against the facets tagged ``settings.teeth_surface``;
        refuses teeth that a node of that surface is inside or within dhat of at rest."""
        where = f"model {self.model.path} ([teeth] of its model.toml)"
        if not self.model.teeth:
            raise ValueError(f"model {self.model.path} has no teeth ([teeth] in its model.toml, "
                             "docs/model_format.md): contact with the teeth needs them")
        tag = self._surface_tag(settings.teeth_surface, f"{where}: no facets tagged {settings.teeth_surface!r} "
                                                        "to rest on the teeth")
        objects = tuple(TriangleMesh(*self.model.teeth[bone], name=f"teeth on the {bone}") for bone in self.teeth_bones)
        teeth = ContactPotential(self.V, self.model.facet_tags.find(tag),
                                 replace(settings, objects=objects, poses=(), dhat=settings.teeth_dhat,
                                         surface=settings.teeth_surface, where=where), label="teeth")
        # The bones' nodes move with their own teeth; the barrier must not cut their path short.
        teeth.ignore(self.bone_blocks)
        teeth.check_clear(self.u.x.array, margin=settings.teeth_dhat)
        return teeth

    def teeth_poses(self, controls: Controls) -> tuple:
        """World poses of the teeth: the upper ones in the cranium frame, the lower ones in the
        mandible's (the jaw frame composed with the cranium's)."""
        return tuple(controls.cranium if bone == "cranium" else controls.cranium.compose(controls.jaw)
                     for bone in self.teeth_bones)

    def rest_controls(self) -> Controls:
        """No activation, bones in their rest frames, objects at their rest poses."""
        objects = self.contact.settings.rest_poses() if self.contact is not None else ()
        return Controls(np.zeros(self.num_muscles), AffineMap(), AffineMap(), 0.0, objects)

    def _bone_dof_blocks(self):
        tags = self.model.facet_tags
        fdim = self.mesh.topology.dim - 1
        ids = self.model.boundary_ids

        def blocks(name):
            return fem.locate_dofs_topological(self.V, fdim, tags.find(ids[name]))

        cranium = blocks("cranium")
        # A node on both bones stays with the skull: the cranium is the fixed reference.
        mandible = np.setdiff1d(blocks("mandible"), cranium)
        if self.comm.allreduce(len(cranium), op=MPI.SUM) == 0:
            raise ValueError(f"model {self.model.path}: no cranium-attached facets (tag {ids['cranium']})")
        return cranium, mandible

    # -- controls ----------------------------------------------------------------------------
    def activation_vector(self, activations) -> np.ndarray:
        """Activations as a vector in model muscle order from a vector or a {name: value} dict."""
        if isinstance(activations, dict):
            vector = np.zeros(self.num_muscles)
            for name, value in activations.items():
                vector[self.model.muscle_index(name)] = value
        else:
            vector = np.asarray(activations, dtype=float).reshape(-1)
            if vector.shape != (self.num_muscles,):
                raise ValueError(f"expected {self.num_muscles} activations, got {vector.shape[0]}")
        bad = np.flatnonzero(~((vector >= 0.0) & (vector <= 1.0)))
        if bad.size:
            names = ", ".join(f"{self.model.muscles[i].name}={vector[i]:g}" for i in bad)
            raise ValueError(f"activations must lie in [0, 1]: {names}")
        return vector

    def _scatter(self, vector: np.ndarray, targets: list) -> None:
        """Put a per-muscle vector into the per-slot DG0 functions ``targets``."""
        padded = np.append(vector, 0.0)  # index -1 (empty slot) reads 0
        for k, target in enumerate(targets):
            target.x.array[:] = padded[self.slots.muscle_of_slot[k]]

    def bone_positions(self, cranium: AffineMap, jaw: AffineMap) -> np.ndarray:
        """World positions of the bone-attached dofs (``bone_blocks`` order) for bone frames."""
        X = self.dof_coordinates
        on_cranium = cranium.apply(X[self.cranium_blocks])
        on_mandible = cranium.compose(jaw).apply(X[self.mandible_blocks])
        return np.concatenate([on_cranium, on_mandible])

    def adopt(self, controls: Controls, displacement: np.ndarray) -> None:
        """Take ``displacement`` (local dofs incl. ghosts) as the equilibrium at ``controls``
        without solving: for a state solved before and kept, e.g. the best point of a line search
        or a checkpoint. Re-solving it would change it at round-off level, at the price of a
        factorisation."""
        self.u.x.array[:] = displacement
        self.set_controls(controls.copy())

    def reset_to_rest(self) -> None:
        """Zero controls and zero displacement, their exact equilibrium, without a solve
        (``solve`` would walk the controls back from wherever they are)."""
        self.adopt(self.rest_controls(), np.zeros_like(self.u.x.array))

    def set_controls(self, controls: Controls) -> None:
        """Put ``controls`` into the forms (activations) and the Dirichlet values (bone frames)
        without solving: the displacement stays as it is, no longer an equilibrium in general."""
        if controls.pressure and not self.has_pressure:
            raise ValueError(f"intraoral pressure {controls.pressure:g} kPa on a problem without that control "
                             "(FaceProblem(intraoral_pressure=True))")
        num_objects = len(self.contact.objects) if self.contact is not None else 0
        if len(controls.objects) != num_objects:
            raise ValueError(f"{len(controls.objects)} object poses for a problem with {num_objects} contact objects")
        if not controls.same_as(self.controls):
            self.solver.controls_changed()
        self._scatter(controls.activations, self.slots.activation)
        self.pressure.value = controls.pressure
        self._put_objects(controls)
        values = self.bone_displacement.x.array.reshape(-1, 3)
        values[self.bone_blocks] = (self.bone_positions(controls.cranium, controls.jaw)
                                    - self.dof_coordinates[self.bone_blocks])
        self.controls = controls

    def _move_rigidly(self, old: AffineMap, new: AffineMap) -> None:
        """Carry the current shape along a change of the cranium frame (exact for rigid motion).

        The jaw gets no such predictor: blending its rigid motion into the flesh (e.g. by a
        harmonic weight) was measured to slow Newton down (94 vs 19 iterations for a 15 degree
        opening at 50K tets); the lifting of the first Newton step spreads it better.
        """
        change = new.compose(old.inverse())
        X = self.dof_coordinates
        values = self.u.x.array.reshape(-1, 3)
        values[:] = change.apply(X + values) - X

    # -- solving -----------------------------------------------------------------------------
    def solve(self, activations=None, cranium: AffineMap | None = None,
              jaw: AffineMap | None = None, guess: np.ndarray | None = None,
              max_halvings: int = 10, pressure: float | None = None, objects=None) -> SolveReport:
        """Equilibrium for the given controls (unspecified ones keep their values).

        Newton starts from ``guess`` (a dof array, e.g. the Gauss-Newton prediction X + dX/dc dc)
        if given, cut short around a few nodes where it would flatten cells
        (``_bounded_locally``), then pulled back as a whole where it would still invert cells or
        break a contact (with lip or teeth contact, only its part beyond the current
        equilibrium carried rigidly with the cranium's change; the lining it takes into the teeth
        moved out of them instead where that is small), else from the current equilibrium carried
        along the change of the cranium frame; a start whose lips intersect after the lining was
        pushed out of the teeth's or an object's way counts as failed. If that fails,
        continuation from the current equilibrium takes over, halving its step at most
        ``max_halvings`` times before raising EquilibriumError. ``objects``: the poses of the
        contact objects (``AffineMap``s, world frame).
        """
        start = self.controls.copy()
        target = Controls(
            self.activation_vector(activations) if activations is not None else start.activations,
            cranium if cranium is not None else start.cranium,
            jaw if jaw is not None else start.jaw,
            float(pressure) if pressure is not None else start.pressure,
            tuple(objects) if objects is not None else start.objects)
        if guess is not None:
            began = time.perf_counter()
            equilibrium = self.u.x.array.copy()
            origin = self._carried_with_head(start, target)
            carried = equilibrium if origin is start else self.u.x.array.copy()
            # A long linear prediction can invert elements: cut it short around a few nodes, or
            # pull it back towards the equilibrium as a whole.
            if self.bound_prediction_locally:
                guess, fraction = self._bounded_locally(carried, guess)
            else:
                fraction = self.solver.inversion_guard.step_fraction(carried, carried - guess)
            cuts = [("inversion guard", fraction)]
            # ... or let the lips pass through each other, or the lining into the teeth
            for label, term in (("lips", self.lips), ("teeth", self.teeth_contact), ("objects", self.contact)):
                if term is None:
                    continue
                end = carried + fraction * (guess - carried)
                if term is self.teeth_contact:  # the teeth move with their bones along the prediction
                    poses = self.teeth_poses(origin.interpolate(target, fraction))
                    cut = term.relative_fraction(carried, end, poses)
                    projected = self._lining_projected(carried, end, poses) if cut < 1.0 else None
                    if projected is not None:
                        guess = carried + (projected - carried) / fraction
                        cuts.append(("teeth, lining projected instead", cut))
                        continue
                else:
                    cut = term.admissible_fraction(carried, end)
                fraction *= cut
                cuts.append((label, cut))
            if fraction < 1.0:
                log.debug("prediction pulled back to %.3g of the way (%s)%s", fraction,
                          ", ".join(f"{label} {cut:.3g}" for label, cut in cuts if cut < 1.0),
                          "" if origin is start else " after the head's rigid motion")
            self.u.x.array[:] = carried + fraction * (guess - carried)
            # The pulled-back prediction stands for the controls that far along: its bone nodes go
            # exactly to their frames there (the prediction is linear in the controls) and the
            # objects and the teeth move there from the equilibrium's poses in solves that hold the
            # bones still. Bones moving in such a solve (to the old frames, or the rest of the way
            # to linearised ones) pressed the lining against the teeth at their new pose until a
            # node was inside (Newton's barrier blocks had no finite value; the fit ended).
            held = 0
            if self.contact is not None or self.teeth_contact is not None:
                reached = origin.interpolate(target, fraction) if fraction < 1.0 else target
                self.set_controls(reached)
                self.u.x.array.reshape(-1, 3)[self.bone_blocks] = self.bone_displacement.x.array.reshape(-1, 3)[
                    self.bone_blocks]
                self.u.x.scatter_forward()
                self._put_objects(origin)
                held = self._clear_objects(reached)
                if fraction < 1.0:
                    # The solve takes the bones the rest of the way by lifting; the objects and the
                    # teeth go to the target's poses first, pushing the lining out of their way. Put
                    # there unchecked, the teeth overran a lining node: a NaN residual, and the solve
                    # restarted from the last equilibrium.
                    self._put_objects(reached)
                    held += self._clear_objects(target)
            self.set_controls(target)
            if self._lips_intersect():
                ok, iterations, why = False, 0, "the lips intersect after the lining was pushed out"
            else:
                ok, iterations, why = self.solver.newton()
            if ok:
                return SolveReport(True, held + iterations, 1, why, time.perf_counter() - began)
            log.info("Newton from the predicted shape failed (%s); continuing from the last "
                     "equilibrium", why)
            self.u.x.array[:] = equilibrium
            self.set_controls(start)

        def controls_at(t):
            self.set_controls(start.interpolate(target, t))

        held = []  # Newton iterations of the objects' moves

        def predictor(t0, t1):
            old = start.cranium.interpolate(target.cranium, t0)
            new = start.cranium.interpolate(target.cranium, t1)
            if not old.same_as(new):
                self._move_rigidly(old, new)
            # After a failed load step the unknown is back at t0's equilibrium, the objects still at
            # the failed step's poses: they move from t0's (a tip's path from there is what dents
            # the skin, ObjectFeatureContact.push_out).
            self._put_objects(start.interpolate(target, t0))
            held.append(self._clear_objects(start.interpolate(target, t1), start.interpolate(target, t0)))
            return not self._lips_intersect()

        report = self.solver.solve_continuation(controls_at, predictor=predictor,
                                                max_halvings=max_halvings)
        self.set_controls(target)
        return replace(report, newton_iterations=report.newton_iterations + sum(held)) if any(held) else report

    def _bounded_locally(self, carried: np.ndarray, guess: np.ndarray) -> tuple[np.ndarray, float]:
        """The prediction ``guess`` (from ``carried``) cut short around a few nodes where it
        flattens cells: the vertices of those cells go the inversion guard's fraction of the way,
        the nodes around them return to the whole way over a width of ``BLEND_WIDTHS`` (rest
        distance, a smoothstep), the bones' nodes all the way. The exact Jacobian's prediction can
        be huge on a few lining nodes by the incisors' edge, where the tangent is nearly singular:
        cut as a whole for them, it took the whole face 6-25 % of its way (404K face,
        docs/performance.md). ``guess`` itself where it flattens no cell, cells with more than
        ``LOCAL_CUT_NODES`` vertices (a prediction wrong over a region, not at a few nodes), or
        cells at every width. With it the inversion guard's fraction of the way for the whole of
        what is returned."""
        step = guess - carried
        guard = self.solver.inversion_guard
        whole = guard.step_fraction(carried, -step)
        if whole == 1.0:
            return guess, whole
        flattened = self.dof_coordinates[guard.flattened_blocks(carried, step)]
        flattened = np.unique(np.concatenate(self.comm.allgather(flattened)), axis=0)
        if len(flattened) > LOCAL_CUT_NODES:
            log.debug("prediction not cut short around a few nodes: it flattens cells with %d vertices", len(flattened))
            return guess, whole
        distance = cKDTree(flattened).query(self.dof_coordinates)[0]
        for width in BLEND_WIDTHS:
            ramp = np.minimum(distance / width, 1.0)
            scales = whole + (1.0 - whole) * ramp * ramp * (3.0 - 2.0 * ramp)
            scales[self.bone_blocks] = 1.0
            bounded = carried + (scales[:, None] * step.reshape(-1, 3)).reshape(-1)
            if not guard.flattens(carried, bounded):
                log.debug("prediction cut short around %d nodes over %g mm to %.3g of the way", len(flattened),
                          width, whole)
                return bounded, 1.0
        log.debug("prediction not cut short around a few nodes: a blend over %g mm still flattens a cell", width)
        return guess, whole

    def _lips_intersect(self) -> bool:
        """Whether the lips intersect at the unknown. The push-out of the lining before the teeth's
        or an object's move (``ContactPotential.move_to``) knows nothing of the lips: pressed
        micrometres apart, a pushed lip node went through the other lip (5K face, the bilabial
        take with the head moving), and Newton went on from there. Such a start is refused."""
        return self.lips is not None and self.lips.intersects(self.u.x.array)

    def _lining_projected(self, equilibrium: np.ndarray, end: np.ndarray, poses) -> np.ndarray | None:
        """The prediction ``end`` with the lining nodes that it takes too close to the teeth (at
        ``poses``) moved out along the teeth's normals (``ContactPotential.projected_end``), or
        None where that would move a node farther than PROJECTION_LIMIT, invert a cell, or let
        the lips pass each other. The linear prediction does not see the teeth beyond the
        barrier's reach and takes lining nodes that arrive at them inside; the teeth's bound cut
        the whole face's prediction short for those few nodes, and Newton took the cut prediction
        after solves that push the lining out of the teeth moved to their poses. The move is
        judged from ``end``, which the bounds before the teeth's admit from the equilibrium: judged
        from the equilibrium, the lips' bound of a prediction cut exactly at it decided by
        round-off (the lips' second closure, docs/performance.md)."""
        projected = self.teeth_contact.projected_end(equilibrium, end, poses, PROJECTION_LIMIT)
        if projected is None:
            return None
        projected = self._mended_move(end, projected)
        if projected is None or self.solver.inversion_guard.flattens(end, projected):
            log.debug("prediction's lining not moved out of the teeth: the move flattens a cell or lets the lips "
                      "pass each other")
            return None
        # (Collective on every rank: the ranks may log at different levels.)
        moves = np.linalg.norm((projected - end).reshape(-1, 3), axis=1)
        moved = self.comm.allreduce(int(np.count_nonzero(moves[:self.V.dofmap.index_map.size_local] > 0.0)))
        log.debug("prediction's lining moved out of the teeth instead: %d nodes, up to %.3g mm", moved,
                  self.comm.allreduce(float(moves.max(initial=0.0)), op=MPI.MAX))
        return projected

    def _mended_move(self, start: np.ndarray, end: np.ndarray) -> np.ndarray | None:
        """``end``, a push of lining nodes from the displacement ``start`` out of the teeth's or an
        object's way, if the straight move to it lets the lips pass each other nowhere, else with
        the other lip pushed along (``LipContact.pushed_along``) if that makes it so, else None
        (collective; whether the move flattens cells is the caller's to judge). The lips pressed on
        each other in front of the closing teeth: the lower lip's nodes pushed out of the teeth's
        way went into the upper lip, and each such start failed (the lips' second closure,
        docs/performance.md)."""
        if self.lips is None:
            return end
        pushed = self.lips.pushed_along(start, end)  # ``end`` itself where the lips let it be
        if pushed is None:
            log.debug("lining not pushed out: the other lip would pass it, pushed along or not")
        elif pushed is not end:
            along = np.linalg.norm(self.lips.positions(pushed) - self.lips.positions(end), axis=1) > UNMOVED
            log.debug("lining pushed out with %d nodes of the other lip pushed along", np.count_nonzero(along))
        return pushed

    def _carried_with_head(self, start: Controls, target: Controls) -> Controls:
        """Before a prediction with lip or teeth contact is bounded: carry the equilibrium (and the
        teeth) rigidly along the cranium's change from ``start`` to ``target``, and return the
        controls it is the equilibrium of (``start`` with the target's cranium frame; ``start``
        itself, the unknown untouched, when the cranium stays, moves non-rigidly, or a contact
        object stands in the way). A rigid motion keeps every distance, so the contact bounds
        then cut only the non-rigid rest of the prediction, and a cut prediction leaves only that
        rest to the lifting of Newton's first step, not most of the head's motion."""
        if (not self.carry_head or (self.lips is None and self.teeth_contact is None)
                or start.cranium.same_as(target.cranium)):
            return start
        change = target.cranium.compose(start.cranium.inverse())
        if np.abs(change.matrix.T @ change.matrix - np.eye(3)).max() > 1e-10:
            return start
        before = self.u.x.array.copy()
        self._move_rigidly(start.cranium, target.cranium)
        if self.contact is not None and self.contact.admissible_fraction(before, self.u.x.array) < 1.0:
            self.u.x.array[:] = before
            return start
        origin = Controls(start.activations, target.cranium, start.jaw, start.pressure, start.objects)
        self._put_objects(origin)
        return origin

    def _put_objects(self, controls: Controls) -> None:
        """Put the contact objects and the teeth at their poses in ``controls`` (nothing else)."""
        if self.contact is not None:
            self.contact.set_poses(controls.objects)
        if self.teeth_contact is not None:
            self.teeth_contact.set_poses(self.teeth_poses(controls))

    def _clear_objects(self, controls: Controls, before: Controls | None = None) -> int:
        """Move the objects to their poses in ``controls`` (``ContactPotential.move_to``): a start
        that Newton's barrier accepts, near the equilibrium. When the jaw moves from its pose in
        ``before`` (the equilibrium the unknown holds, carried along the cranium's change), the
        lining resting on the teeth moves with them in a solve that reaches the new bone frames
        (``ContactPotential.carry``). Otherwise the teeth move so only where their new poses would
        take more of a lining node's gap than a collision-free step may and leave it closer than
        PUSH_GAP dhat (the bones closing in on the lining), else with the bone frames in the solve.
        Returns the Newton iterations it took."""
        mend = self._mended_move if self.lips is not None else None
        iterations = self.contact.move_to(controls.objects, self.solver, mend) if self.contact is not None else 0
        if self.teeth_contact is not None and before is not None and not before.jaw.same_as(controls.jaw):
            self.set_controls(controls)
            # The unknown went along the cranium's change already: so did the teeth it rests on.
            change = controls.cranium.compose(before.cranium.inverse())
            self.teeth_contact.set_poses(tuple(change.compose(pose) for pose in self.teeth_poses(before)))
            lips = self.lips.surface.local_blocks if self.lips is not None else None
            return iterations + self.teeth_contact.carry(self.teeth_poses(controls), self.solver, CARRY_REACH,
                                                         free_blocks=lips, mend=self._mended_move)
        if self.teeth_contact is not None:
            poses = self.teeth_poses(controls)
            if self.teeth_contact.closes_in(self.u.x.array, self.teeth_contact.poses, poses):
                iterations += self.teeth_contact.move_to(poses, self.solver, mend)
        return iterations

    def active_force(self, muscle: int, out: PETSc.Vec | None = None) -> PETSc.Vec:
        """f_i = df/da_i at the current shape (zero on Dirichlet dofs): the right-hand side of
        K dX/da_i = f_i (sifakis2005 eq. 5)."""
        direction = np.zeros(self.num_muscles)
        direction[muscle] = 1.0
        self._scatter(direction, self.slots.direction)
        # force = -d(energy)/dx
        return self._assembled_load(self._active_residuals[muscle], out, scale=-1.0)

    def pressure_force(self, out: PETSc.Vec | None = None) -> PETSc.Vec:
        """df/dp, the load of a unit intraoral pressure at the current shape (zero on Dirichlet
        dofs): the right-hand side of K dX/dp = df/dp."""
        if not self.has_pressure:
            raise ValueError("this problem has no intraoral pressure control")
        return self._assembled_load(self._pressure_load, out)

    def _assembled_load(self, form, out: PETSc.Vec | None, scale: float = 1.0) -> PETSc.Vec:
        """``scale`` times the vector of ``form`` in ``out`` (a new vector if None), ghosts summed,
        zero on the Dirichlet dofs."""
        if out is None:
            out = fem_petsc.create_vector(form)
        with out.localForm() as local:
            local.set(0.0)
        fem_petsc.assemble_vector(out, form)
        out.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        if scale != 1.0:
            out.scale(scale)
        fem_petsc.set_bc(out, self.bcs, scale=0.0)
        return out

    def peak_stress(self, muscle: int) -> float:
        return self.model.peak_stress(muscle)

    def energy(self) -> float:
        return self.solver.energy()

    def residual_norm(self) -> float:
        return self.solver.residual_norm()
