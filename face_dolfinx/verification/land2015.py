"""Land et al. (2015) cardiac-mechanics verification problems, with this project's forms and solver.

S. Land et al., "Verification of cardiac mechanics software: benchmark problems and solutions for
testing active and passive material behaviour", Proc. R. Soc. A 471: 20150641 (2015). Eleven codes
agreed on the answers to about 0.5 %. The problems exercise what the face model needs: nearly
incompressible, fiber-reinforced exponential hyperelasticity at large strain, an active fiber
stress, and a pressure that follows the deformed surface. Units: mm and kPa (forces in mN).

Problem 1, beam. The box [0, 10] x [0, 1] x [0, 1] is clamped at x = 0; fibers run along x;
Guccione law with C = 2 kPa, b_f = 8, b_t = 2, b_fs = 4. A pressure ramped to 0.004 kPa on the
bottom face z = 0 bends it upwards. Reported: the deformed z of the material point (10, 0.5, 1),
which the benchmark's codes converge to 4.17 mm.

Problem 2, passive inflation of a truncated ellipsoid. The wall lies between the prolate spheroids
    x = r_s sin(mu) cos(theta),  y = r_s sin(mu) sin(theta),  z = r_l cos(mu)
with (r_s, r_l) = (7, 17) mm (endocardium) and (10, 20) mm (epicardium), cut by the base plane
z = 5, which is fixed. Isotropic Guccione (C = 10 kPa, b_f = b_t = b_fs = 1); endocardial pressure
10 kPa. Reported: the deformed z of the endocardial apex (0, 0, -17) and of the epicardial apex
(0, 0, -20), and the cavity volume.

Problem 3, inflation and active contraction of the same ellipsoid. The fiber makes the helix angle
alpha with the circumferential direction, +90 deg at the endocardium falling linearly to -90 deg
at the epicardium; Guccione as in problem 1; endocardial pressure 15 kPa and active tension
Ta = 60 kPa along the fiber (second Piola stress Ta f0 (x) f0), ramped together. Reported: the two
apex positions (and the cavity volume).

The ellipsoid is meshed by gmsh: the region between the two ellipse arcs in the xz-plane is revolved
about the z-axis (OpenCASCADE), so both apexes are mesh vertices, and the tetrahedra are second
order, so that the curved surfaces and the cavity volume are accurate on coarse meshes.

Formulations (``--formulation``, ``--degree``):

- ``mixed``: Taylor-Hood, P2 displacement and P1 pressure, J = 1 by a Lagrange multiplier
  (forms.incompressible). Exactly incompressible and free of locking.
- ``displacement``: displacement only, with the penalty kappa/2 (ln J)^2 of forms.flesh and bulk
  modulus kappa (``--bulk-modulus``, default 1000 C). P1 tetrahedra lock, which the benchmark
  shows as a far too stiff answer; P2 locks much less, but still measurably at kappa = 1000 C.

The pressure is a follower load (forms.loads), which makes the tangent non-symmetric, so the solver
factorises with MUMPS LU instead of the project's default Cholesky and, having no energy to
minimise, its line search backtracks on the residual norm.

Usage (lengths in mm, volumes in mm^3, one ``name = value`` line per result):
    python -m face_dolfinx.verification.land2015 --problem 1 --refine 2
    mpirun -n 2 python -m face_dolfinx.verification.land2015 --problem 3 --refine 1 --formulation mixed

``--table`` runs a set of cases, each in its own process on 1 and on 2 ranks, and prints the
markdown tables of docs/verification.md:
    python -m face_dolfinx.verification.land2015 --table --problems 2 3 --levels 0 1
"""
import argparse
from dataclasses import dataclass
import logging
import math
import os
import re
import subprocess
import sys
import time

from mpi4py import MPI
from petsc4py import PETSc
import numpy as np
import ufl
from dolfinx import fem, geometry
from dolfinx import mesh as dmesh

from face_dolfinx.equilibrium.solver import EquilibriumError, QuasistaticSolver, compile_form
from forms.flesh import LogVolumetric
from forms.guccione import ActiveFiberStress, Guccione
from forms.incompressible import IncompressibilityMultiplier
from forms.kinematics import deformation_gradient
from forms.loads import FollowerPressure

BEAM_SIZE = (10.0, 1.0, 1.0)
BEAM_POINT = (10.0, 0.5, 1.0)
BEAM_REFERENCE_Z = 4.17  # the benchmark's converged answer, mm

ENDO_RADII = (7.0, 17.0)  # (short, long) semi-axes of the prolate spheroids, mm
EPI_RADII = (10.0, 20.0)
BASE_Z = 5.0
ENDO_APEX = (0.0, 0.0, -ENDO_RADII[1])
EPI_APEX = (0.0, 0.0, -EPI_RADII[1])

# The follower load makes the tangent non-symmetric: LU, not the default Cholesky. There is no
# energy to backtrack on, and backtracking on |R| crawls (|R| often rises on the way to the
# solution under this exponential law: problem 1 at level 0 took 249 Newton iterations instead of
# 20, problem 2 at level 1 514 instead of about 130), so Newton takes full steps; when it diverges
# the solver's continuation halves the load increment.
PETSC_OPTIONS = {"pc_type": "lu", "snes_linesearch_type": "basic"}

# Facet tags: Dirichlet (beam end x = 0, ventricle base), pressure (beam bottom, endocardium).
FIXED, PRESSURISED, EPICARDIUM = 1, 2, 3


@dataclass(frozen=True)
class Problem:
    """Material, loads and the default number of load steps of one benchmark problem."""

    number: int
    C: float  # kPa
    b_f: float
    b_t: float
    b_fs: float
    pressure: float  # final pressure on the PRESSURISED facets, kPa
    active_tension: float  # final Ta, kPa
    load_steps: int
    # Newton stops when the residual norm (nodal forces, mN) falls below this. The ellipsoid's
    # loads are about 10^4 mN, and with the penalty kappa = 10^4 kPa its residual has a round-off
    # floor near 1.1e-9 mN (P2, K = 1): the solver's default 1e-9 there made Newton, converged,
    # run to its iteration limit and the continuation give up at 3.75 kPa.
    residual_tolerance: float

    @property
    def is_beam(self) -> bool:
        return self.number == 1


PROBLEMS = {
    1: Problem(1, C=2.0, b_f=8.0, b_t=2.0, b_fs=4.0, pressure=0.004, active_tension=0.0,
               load_steps=4, residual_tolerance=1e-9),
    2: Problem(2, C=10.0, b_f=1.0, b_t=1.0, b_fs=1.0, pressure=10.0, active_tension=0.0,
               load_steps=20, residual_tolerance=1e-8),
    3: Problem(3, C=2.0, b_f=8.0, b_t=2.0, b_fs=4.0, pressure=15.0, active_tension=60.0,
               load_steps=10, residual_tolerance=1e-8),
}


# -- geometry ------------------------------------------------------------------------------------
def _tag_facets(domain, markers: dict[int, callable]) -> dmesh.MeshTagsMetaClass:
    """Facet tags from {tag: locator(x)} on the boundary."""
    fdim = domain.topology.dim - 1
    found = [(dmesh.locate_entities_boundary(domain, fdim, where), tag)
             for tag, where in markers.items()]
    facets = np.concatenate([f for f, _ in found])
    values = np.concatenate([np.full(len(f), tag, dtype=np.int32) for f, tag in found])
    order = np.argsort(facets)
    return dmesh.meshtags(domain, fdim, facets[order], values[order])


def beam_mesh(comm: MPI.Comm, refine: int):
    """The beam as 10n x n x n cubes of side h = 1/n mm, n = 2^refine, six tetrahedra each."""
    n = 2**refine
    domain = dmesh.create_box(comm, [np.zeros(3), np.array(BEAM_SIZE)],
                              [10 * n, n, n], dmesh.CellType.tetrahedron)
    tags = _tag_facets(domain, {FIXED: lambda x: np.isclose(x[0], 0.0),
                                PRESSURISED: lambda x: np.isclose(x[2], 0.0)})
    return domain, tags


def _meridian_arc(occ, short_radius: float, long_radius: float) -> int:
    """The spheroid's meridian (y = 0, x >= 0) from the apex to the base plane, as an OCC curve.

    gmsh draws ellipses in the xy-plane with the major axis along x: (r_l cos mu, r_s sin mu, 0)
    for mu in [-pi, -acos(5/r_l)]. Two quarter turns map that to (-r_s sin mu, 0, r_l cos mu),
    the benchmark's parametrisation at theta = pi.
    """
    arc = occ.addEllipse(0.0, 0.0, 0.0, long_radius, short_radius, -1,
                         -math.pi, -math.acos(BASE_Z / long_radius))
    occ.rotate([(1, arc)], 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, math.pi / 2)
    occ.rotate([(1, arc)], 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, -math.pi / 2)
    return arc


def ventricle_mesh(comm: MPI.Comm, refine: float, apex_size: float | None = None):
    """Second-order tetrahedra of size h = 3/2^refine mm (3 mm is the wall thickness at the apex);
    ``refine`` need not be an integer. With ``apex_size`` the size falls to it within 1 mm of the
    axis at the apex (where the endocardial apex converges slowest, docs/verification.md) and grows
    back to h over the next 4 mm.

    Built on rank 0 and distributed by dolfinx, so every number of ranks meshes the same wall.
    """
    import gmsh
    from dolfinx.io import gmshio

    if comm.rank == 0:
        gmsh.initialize()
        gmsh.option.setNumber("General.Terminal", 0)
        occ = gmsh.model.occ
        endo, epi = _meridian_arc(occ, *ENDO_RADII), _meridian_arc(occ, *EPI_RADII)
        occ.synchronize()

        def end_points(curve):  # (apex, base-rim) point tags of a meridian arc
            points = [tag for _, tag in gmsh.model.getBoundary([(1, curve)])]
            return sorted(points, key=lambda p: occ.getBoundingBox(0, p)[2])

        (endo_apex, endo_rim), (epi_apex, epi_rim) = end_points(endo), end_points(epi)
        section = occ.addPlaneSurface([occ.addCurveLoop(
            [endo, occ.addLine(endo_rim, epi_rim), epi, occ.addLine(epi_apex, endo_apex)])])
        revolved = occ.revolve([(2, section)], 0, 0, 0, 0, 0, 1, 2 * math.pi)
        # The meridian section is left over as a free face; meshed, it would break the import.
        occ.remove([(2, section)], recursive=True)
        occ.synchronize()

        wall = [tag for dim, tag in revolved if dim == 3]
        surfaces = {FIXED: [], PRESSURISED: [], EPICARDIUM: []}
        for _, surface in gmsh.model.getBoundary([(3, tag) for tag in wall], oriented=False):
            x_min, _, z_min, x_max, _, z_max = occ.getBoundingBox(2, surface)
            if z_max - z_min < 1e-6:
                surfaces[FIXED].append(surface)
            elif x_max < 0.5 * (ENDO_RADII[0] + EPI_RADII[0]):
                surfaces[PRESSURISED].append(surface)
            else:
                surfaces[EPICARDIUM].append(surface)
        gmsh.model.addPhysicalGroup(3, wall, 1)
        for tag, tags in surfaces.items():
            gmsh.model.addPhysicalGroup(2, tags, tag)

        size = 3.0 / 2**refine
        if apex_size is None:
            gmsh.option.setNumber("Mesh.MeshSizeMin", size)
            gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        else:
            # Distance from the axis below z = -16 (the apexes lie at -17 and -20 mm).
            field = gmsh.model.mesh.field
            graded = field.add("MathEval")
            field.setString(graded, "F", f"Min({size}, Max({apex_size}, {apex_size} + ({size} - {apex_size}) * "
                                         "(Sqrt(x*x + y*y + Max(0, z + 16)^2) - 1) / 4))")
            field.setAsBackgroundMesh(graded)
            gmsh.option.setNumber("Mesh.MeshSizeMin", apex_size)
            gmsh.option.setNumber("Mesh.MeshSizeMax", size)
            for option in ("MeshSizeExtendFromBoundary", "MeshSizeFromPoints", "MeshSizeFromCurvature"):
                gmsh.option.setNumber(f"Mesh.{option}", 0)
        gmsh.model.mesh.generate(3)
        gmsh.model.mesh.setOrder(2)
    domain, _, facet_tags = gmshio.model_to_mesh(gmsh.model, comm, 0)
    if comm.rank == 0:
        gmsh.finalize()
    return domain, facet_tags


def transmural_coordinate(x, newton_steps: int = 5):
    """t in [0, 1] (0 endocardium, 1 epicardium) of the spheroid through x, as a UFL expression.

    The benchmark's wall is the family of spheroids with r_s = 7 + 3t, r_l = 17 + 3t, so t solves
        g(t) = rho^2 / r_s(t)^2 + z^2 / r_l(t)^2 - 1 = 0,     rho^2 = x^2 + y^2.
    g is convex and decreasing on the wall, so Newton from t = 1/2 converges monotonically after
    its first step; five steps reach machine precision everywhere in the wall.
    """
    rho2, z2 = x[0]**2 + x[1]**2, x[2]**2
    thickness = EPI_RADII[0] - ENDO_RADII[0]  # the same 3 mm for both semi-axes
    t = 0.5
    for _ in range(newton_steps):
        r_s, r_l = ENDO_RADII[0] + thickness * t, ENDO_RADII[1] + thickness * t
        g = rho2 / r_s**2 + z2 / r_l**2 - 1.0
        dg = -2.0 * thickness * (rho2 / r_s**3 + z2 / r_l**3)
        t = t - g / dg
    return t


def helix_fiber(x):
    """Problem 3's unit fiber at the reference point x (UFL), from the benchmark's definition

        f = sin(alpha) e_mu + cos(alpha) e_theta,   alpha = pi/2 - pi t,

    with e_mu, e_theta the unit tangents dx/dmu, dx/dtheta of the spheroid through x. In Cartesian
    form (sin mu = -rho/r_s, cos mu = z/r_l) they need no trigonometry:
        dx/dmu    = (-r_s z x / (r_l rho), -r_s z y / (r_l rho), r_l rho / r_s),
        dx/dtheta = (-y, x, 0).
    Both are singular on the axis rho = 0 (the apex), which quadrature points never reach.
    """
    t = transmural_coordinate(x)
    thickness = EPI_RADII[0] - ENDO_RADII[0]
    r_s, r_l = ENDO_RADII[0] + thickness * t, ENDO_RADII[1] + thickness * t
    rho = ufl.sqrt(x[0]**2 + x[1]**2)
    d_mu = ufl.as_vector((-r_s * x[2] * x[0] / (r_l * rho), -r_s * x[2] * x[1] / (r_l * rho),
                          r_l * rho / r_s))
    e_mu = d_mu / ufl.sqrt(ufl.dot(d_mu, d_mu))
    e_theta = ufl.as_vector((-x[1] / rho, x[0] / rho, 0.0))
    alpha = math.pi / 2 - math.pi * t
    return ufl.sin(alpha) * e_mu + ufl.cos(alpha) * e_theta


# -- discretisation ------------------------------------------------------------------------------
@dataclass
class Discretisation:
    """The unknown, its residual and Dirichlet conditions, and the load controls (Constants)."""

    formulation: str
    state: fem.Function  # displacement, or (displacement, pressure) for the mixed formulation
    displacement: ufl.core.expr.Expr  # u, a part of ``state`` for the mixed formulation
    residual: ufl.Form
    bcs: list
    pressure: fem.Constant
    active_tension: fem.Constant
    ds: ufl.Measure

    def displacement_function(self) -> fem.Function:
        """u as a stand-alone Function (collapsed out of the mixed state), e.g. to evaluate."""
        if self.formulation == "mixed":
            return self.state.sub(0).collapse()
        return self.state

    def cavity_volume_form(self) -> fem.FormMetaClass:
        """Volume enclosed by the deformed endocardium and the base plane, V = -1/3 int (x - c).n da.

        c lies in the base plane, where (x - c).n vanishes on the lid, so only the endocardium
        (normal n pointing into the cavity, hence the sign) contributes: Nanson, n da = J F^-T N dA.
        """
        u = self.displacement
        domain = self.state.function_space.mesh
        F = ufl.Identity(3) + ufl.grad(u)
        x = ufl.SpatialCoordinate(domain) + u
        lid_centre = ufl.as_vector((0.0, 0.0, BASE_Z))
        area_vector = ufl.det(F) * ufl.inv(F).T * ufl.FacetNormal(domain)
        return compile_form(-ufl.dot(x - lid_centre, area_vector) / 3.0 * self.ds(PRESSURISED))


def default_quadrature_degree(degree: int, domain) -> int:
    """Exact for P1 on straight tetrahedra (everything is constant), 4 otherwise.

    FFCx's own estimate for exp(Q) of a P2 field is in the dozens of points per direction.
    """
    affine = domain.geometry.cmap.degree == 1
    return 2 if degree == 1 and affine else 4


def discretise(problem: Problem, domain, facet_tags, formulation: str, degree: int,
               bulk_modulus: float, quadrature_degree: int) -> Discretisation:
    metadata = {"quadrature_degree": quadrature_degree}
    dx = ufl.Measure("dx", domain=domain, metadata=metadata)
    ds = ufl.Measure("ds", domain=domain, subdomain_data=facet_tags, metadata=metadata)
    fdim = domain.topology.dim - 1
    fixed_facets = facet_tags.indices[facet_tags.values == FIXED]

    cell = domain.ufl_cell()
    if formulation == "mixed":
        space = fem.FunctionSpace(domain, ufl.MixedElement(
            [ufl.VectorElement("Lagrange", cell, degree), ufl.FiniteElement("Lagrange", cell, degree - 1)]))
        state = fem.Function(space)
        u, p = ufl.split(state)
        test = ufl.TestFunction(space)
        v, _ = ufl.split(test)
        incompressibility = IncompressibilityMultiplier(p)
        displacement_space = space.sub(0)
    elif formulation == "displacement":
        space = fem.VectorFunctionSpace(domain, ("Lagrange", degree))
        state = fem.Function(space)
        u = state
        test = v = ufl.TestFunction(space)
        incompressibility = LogVolumetric(bulk_modulus)
        displacement_space = space
    else:
        raise ValueError(f"unknown formulation {formulation!r}")

    # Zero displacement on the FIXED facets, one scalar condition per component (a Constant
    # value must match the block size of the constrained space, also inside the mixed space).
    clamped = [displacement_space.sub(i) for i in range(3)]
    bcs = [fem.dirichletbc(PETSc.ScalarType(0.0),
                           fem.locate_dofs_topological(component, fdim, fixed_facets), component)
           for component in clamped]

    # Problem 2 is isotropic (b_f = b_t = b_fs), where any fiber gives the same energy.
    fiber = (helix_fiber(ufl.SpatialCoordinate(domain)) if problem.number == 3
             else ufl.as_vector((1.0, 0.0, 0.0)))
    pressure = fem.Constant(domain, PETSc.ScalarType(0.0))
    active_tension = fem.Constant(domain, PETSc.ScalarType(0.0))
    laws = [Guccione(problem.C, problem.b_f, problem.b_t, problem.b_fs, fiber), incompressibility]
    if problem.active_tension:
        laws.append(ActiveFiberStress(fiber, active_tension))

    F = deformation_gradient(u)
    lagrangian = sum(law.strain_energy(F) for law in laws) * dx
    load = FollowerPressure(pressure).virtual_work(F, ufl.FacetNormal(domain), v) * ds(PRESSURISED)
    residual = ufl.derivative(lagrangian, state, test) - load
    return Discretisation(formulation, state, u, residual, bcs, pressure, active_tension, ds)


# -- measuring -----------------------------------------------------------------------------------
def evaluate_at_points(function: fem.Function, points) -> np.ndarray:
    """Values of ``function`` at ``points`` (the same on every rank), returned on every rank.

    Each point is evaluated by the lowest rank whose cells (owned or ghost) contain it, and the
    result is summed over ranks, so every rank gets the same values whatever the partition.
    """
    domain = function.function_space.mesh
    comm = domain.comm
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    tree = geometry.BoundingBoxTree(domain, domain.topology.dim)
    cells = geometry.compute_colliding_cells(
        domain, geometry.compute_collisions(tree, points), points)
    has_point = np.array([len(cells.links(i)) > 0 for i in range(len(points))])
    claim = np.where(has_point, comm.rank, comm.size).astype(np.int32)
    owner = np.empty_like(claim)
    comm.Allreduce(claim, owner, op=MPI.MIN)
    if np.any(owner == comm.size):
        raise ValueError(f"points outside the mesh: {points[owner == comm.size]}")
    values = np.zeros((len(points), function.function_space.dofmap.index_map_bs))
    for i in np.flatnonzero(owner == comm.rank):
        values[i] = function.eval(points[i], cells.links(i)[:1])
    comm.Allreduce(MPI.IN_PLACE, values, op=MPI.SUM)
    return values


@dataclass
class Result:
    quantities: dict[str, float]  # name -> value, lengths in mm, volumes in mm^3
    dofs: int
    newton_iterations: int
    load_steps: int  # steps actually taken, including any the continuation fallback added
    solve_seconds: float
    ranks: int


def run(problem_number: int, refine: float = 1, formulation: str = "mixed", degree: int = 2, *,
        load_steps: int | None = None, bulk_modulus: float | None = None,
        quadrature_degree: int | None = None, apex_size: float | None = None,
        comm: MPI.Comm = MPI.COMM_WORLD) -> Result:
    """Mesh, discretise and solve one problem; ramp the loads in equal steps. The beam takes an
    integer ``refine`` and no ``apex_size``."""
    problem = PROBLEMS[problem_number]
    if formulation == "mixed" and degree < 2:
        raise ValueError("the mixed formulation is Taylor-Hood P(k)/P(k-1): degree must be >= 2")
    if problem.is_beam:
        if apex_size is not None or refine != int(refine):
            raise ValueError("the beam's mesh level is an integer and it has no apex to grade towards")
        domain, facet_tags = beam_mesh(comm, int(refine))
    else:
        domain, facet_tags = ventricle_mesh(comm, refine, apex_size)
    model = discretise(
        problem, domain, facet_tags, formulation, degree,
        bulk_modulus=1000.0 * problem.C if bulk_modulus is None else bulk_modulus,
        quadrature_degree=quadrature_degree or default_quadrature_degree(degree, domain))
    petsc_options = {**PETSC_OPTIONS, "snes_atol": problem.residual_tolerance}
    solver = QuasistaticSolver(model.residual, model.state, model.bcs, tangent="general",
                               petsc_options=petsc_options, options_prefix="land2015_")

    quantities = {}
    if not problem.is_beam:
        quantities["undeformed_cavity_volume_mm3"] = comm.allreduce(
            fem.assemble_scalar(model.cavity_volume_form()), op=MPI.SUM)

    # Equal load steps, each started from the last equilibrium; where Newton fails the solver's
    # continuation subdivides the step. (Extrapolating the previous increment as a predictor
    # overshoots on this stiffening law and costs more iterations than it saves.)
    steps = load_steps or problem.load_steps
    newton_iterations = steps_taken = 0
    solve_seconds = 0.0
    for step in range(steps):
        def set_load(t: float, step=step) -> None:
            fraction = (step + t) / steps
            model.pressure.value = fraction * problem.pressure
            model.active_tension.value = fraction * problem.active_tension

        try:
            report = solver.solve_continuation(set_load)
        except EquilibriumError as error:
            # The solver left the controls at the last equilibrium: say where that was.
            raise EquilibriumError(f"no equilibrium beyond pressure {model.pressure.value:.6g} kPa, "
                                   f"active tension {model.active_tension.value:.6g} kPa: {error}")
        newton_iterations += report.newton_iterations
        steps_taken += report.load_steps
        solve_seconds += report.seconds

    u = model.displacement_function()
    if problem.is_beam:
        quantities["point_z_mm"] = BEAM_POINT[2] + evaluate_at_points(u, BEAM_POINT)[0, 2]
    else:
        displacement = evaluate_at_points(u, [ENDO_APEX, EPI_APEX])
        quantities["endo_apex_z_mm"] = ENDO_APEX[2] + displacement[0, 2]
        quantities["epi_apex_z_mm"] = EPI_APEX[2] + displacement[1, 2]
        quantities["cavity_volume_mm3"] = comm.allreduce(
            fem.assemble_scalar(model.cavity_volume_form()), op=MPI.SUM)
    return Result(quantities, model.state.vector.getSize(), newton_iterations, steps_taken,
                  solve_seconds, comm.size)


# -- the results table ---------------------------------------------------------------------------
MODULE = "face_dolfinx.verification.land2015"
# (formulation, degree) rows of the table, in this order.
TABLE_FORMULATIONS = (("mixed", 2), ("displacement", 2), ("displacement", 1))
FORMULATION_LABELS = {("mixed", 2): "Taylor-Hood P2/P1",
                      ("displacement", 2): "P2, penalty 1000 C",
                      ("displacement", 1): "P1, penalty 1000 C"}
# Printed name -> column heading, per problem.
TABLE_QUANTITIES = {
    1: {"point_z_mm": "z of (10, 0.5, 1), mm"},
    2: {"endo_apex_z_mm": "endo apex z, mm", "epi_apex_z_mm": "epi apex z, mm",
        "cavity_volume_mm3": "cavity volume, mm^3"},
}
TABLE_QUANTITIES[3] = TABLE_QUANTITIES[2]
_PRINTED_LINE = re.compile(r"^(\w+) = (.*)$")


def run_printed(case_args: list[str], ranks: int, mpiexec: str) -> dict[str, str]:
    """Run this module's CLI with ``case_args`` on ``ranks`` ranks; its ``name = value`` lines.

    A problem without equilibrium comes back as {"failed": reason}; any other error raises.
    """
    command = [sys.executable, "-m", MODULE, *case_args]
    if ranks > 1:
        command = [mpiexec, "-n", str(ranks), *command]
    print("running:", " ".join(command), file=sys.stderr, flush=True)
    # os.environ is Python's copy of the environment from start-up, without the variables MPI_Init
    # of this (singleton) process put in the C environment: inheriting those, mpirun fails.
    completed = subprocess.run(command, capture_output=True, text=True, env=dict(os.environ))
    printed = dict(match.groups() for line in (completed.stdout + completed.stderr).splitlines()
                   if (match := _PRINTED_LINE.match(line)))
    if completed.returncode != 0 and "failed" not in printed:
        raise RuntimeError(f"{' '.join(command)} exited with {completed.returncode}:\n"
                           f"{completed.stderr[-2000:]}")
    return printed


def _agreeing(values: list[str]) -> str:
    """One cell for a value printed by runs on different numbers of ranks: "a", or "a / b"."""
    return values[0] if len(set(values)) == 1 else " / ".join(values)


def results_table(problem: int, levels: list[int], ranks: list[int], mpiexec: str,
                  formulations=TABLE_FORMULATIONS):
    """Markdown table of one problem, line by line as the runs finish (a long table is not lost
    to an interruption): a row per formulation and level, run on each of ``ranks``.

    Quantities, Newton iterations and load steps are one value where all rank counts printed the
    same (to the six printed digits), else "1-rank value / 2-rank value"; a row that found no
    equilibrium says where it stopped.
    """
    quantities = TABLE_QUANTITIES[problem]
    header = (["formulation", "K", "dofs", *quantities.values(), "Newton", "steps"]
              + [f"solve s, {n} rank{'s' if n > 1 else ''}" for n in ranks])
    yield "| " + " | ".join(header) + " |"
    yield "|" + "---|" * len(header)
    undeformed_volumes = {}
    for formulation, degree in formulations:
        for refine in levels:
            case_args = ["--problem", str(problem), "--refine", str(refine),
                         "--formulation", formulation, "--degree", str(degree)]
            runs = [run_printed(case_args, n, mpiexec) for n in ranks]
            row = [FORMULATION_LABELS[formulation, degree], str(refine)]
            failed = [run["failed"].split(":")[0] for run in runs if "failed" in run]
            if failed:
                row += ["-", _agreeing(failed)] + ["-"] * (len(quantities) + 1)
            else:
                row.append(_agreeing([run["dofs"] for run in runs]))
                row += [_agreeing([run[name] for run in runs]) for name in quantities]
                row += [_agreeing([run["newton_iterations"] for run in runs]),
                        _agreeing([run["load_steps"] for run in runs])]
                if "undeformed_cavity_volume_mm3" in runs[0]:
                    undeformed_volumes[refine] = runs[0]["undeformed_cavity_volume_mm3"]
            row += [run.get("solve_seconds", "-") for run in runs]
            yield "| " + " | ".join(row) + " |"
    if undeformed_volumes:
        yield ""
        yield "Undeformed cavity volume (mm^3, exact 2492.13): " + ", ".join(
            f"K = {refine}: {volume}" for refine, volume in sorted(undeformed_volumes.items()))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m face_dolfinx.verification.land2015",
        description="Land et al. 2015 cardiac mechanics verification problems.")
    parser.add_argument("--problem", type=int, choices=sorted(PROBLEMS))
    parser.add_argument("--refine", type=float, default=1,
                        help="mesh level K: beam cubes of 1/2^K mm (K an integer), ventricle tetrahedra of 3/2^K mm")
    parser.add_argument("--apex-size", type=float, metavar="MM",
                        help="ventricle: tetrahedra of this size within 1 mm of the axis at the apex")
    parser.add_argument("--formulation", choices=["mixed", "displacement"], default="mixed")
    parser.add_argument("--degree", type=int, choices=[1, 2], default=2,
                        help="displacement degree (the mixed formulation needs 2)")
    parser.add_argument("--load-steps", type=int, help="equal load steps (default per problem)")
    parser.add_argument("--bulk-modulus", type=float,
                        help="penalty kappa of the displacement formulation, kPa (default 1000 C)")
    parser.add_argument("--quadrature-degree", type=int)
    table = parser.add_argument_group(
        "results table", "--table runs every formulation at each level, each case in its own "
        "process on each number of ranks, and prints markdown")
    table.add_argument("--table", action="store_true")
    table.add_argument("--problems", type=int, nargs="+", choices=sorted(PROBLEMS),
                       default=sorted(PROBLEMS))
    table.add_argument("--levels", type=int, nargs="+", default=[0, 1])
    table.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    table.add_argument("--formulations", nargs="+", metavar="FORMULATION:DEGREE",
                       choices=[f"{name}:{degree}" for name, degree in TABLE_FORMULATIONS],
                       default=[f"{name}:{degree}" for name, degree in TABLE_FORMULATIONS])
    table.add_argument("--mpiexec", default="mpirun")
    args = parser.parse_args(argv)
    if args.table:
        if MPI.COMM_WORLD.size > 1:
            parser.error("--table starts its own MPI runs: run it on one process")
        for problem in args.problems:
            print(f"### Problem {problem}\n", flush=True)
            formulations = [(name, int(degree)) for name, degree in
                            (item.split(":") for item in args.formulations)]
            for line in results_table(problem, args.levels, args.ranks, args.mpiexec, formulations):
                print(line, flush=True)
            print(flush=True)
        return
    if args.problem is None:
        parser.error("--problem is required (or --table)")
    if args.formulation == "mixed" and args.degree < 2:
        parser.error("--formulation mixed is Taylor-Hood P2/P1: use --degree 2")

    # The solver reports its continuation steps at INFO (dolfinx has already configured logging).
    logging.getLogger("face_dolfinx").setLevel(logging.INFO)
    start = time.perf_counter()
    try:
        result = run(args.problem, args.refine, args.formulation, args.degree,
                     load_steps=args.load_steps, bulk_modulus=args.bulk_modulus,
                     quadrature_degree=args.quadrature_degree, apex_size=args.apex_size)
    except EquilibriumError as error:
        if MPI.COMM_WORLD.rank == 0:
            print(f"failed = {error}", file=sys.stderr)
        sys.exit(1)
    wall_seconds = time.perf_counter() - start
    if MPI.COMM_WORLD.rank == 0:
        lines = {"problem": args.problem, "formulation": args.formulation, "degree": args.degree,
                 "refine": f"{args.refine:g}", "ranks": result.ranks, "dofs": result.dofs,
                 "newton_iterations": result.newton_iterations, "load_steps": result.load_steps,
                 "solve_seconds": f"{result.solve_seconds:.2f}",
                 "wall_seconds": f"{wall_seconds:.2f}"}
        lines.update({name: f"{value:.6g}" for name, value in result.quantities.items()})
        for name, value in lines.items():
            print(f"{name} = {value}")


if __name__ == "__main__":
    main()
