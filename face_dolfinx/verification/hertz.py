"""Hertz contact: a rigid sphere pressed into a thick, nearly incompressible block.

For a rigid sphere of radius R pressed a depth d into an elastic half-space (Young's modulus E,
Poisson's ratio nu), Hertz's theory gives the force and the contact radius

    F = 4/3 E* sqrt(R) d^(3/2),   a = sqrt(R d),   E* = E / (1 - nu^2),

for small indentations (a << R). Here the half-space is the quarter block [0, L]^2 x [-L, 0] mm
(symmetry planes x = 0 and y = 0 hold the normal displacement, the bottom is clamped, the far
sides are free), meshed by gmsh with tetrahedra of size ``fine`` within ``fine_radius`` of the
contact point, growing by ``growth`` per mm beyond (``--fine`` is the mesh level), of
the project's flesh: Mooney-Rivlin with mu01 = 0 (shear modulus mu = 2 mu10) and the volumetric
penalty kappa / 2 (ln J)^2, so E = 9 kappa mu / (3 kappa + mu), nu = (3 kappa - 2 mu) / (6 kappa + 2 mu).
The sphere is the contact module's (face_dolfinx.physics.contact): its IPC barrier on the top face,
its pose stepped down through the indentations, each an equilibrium of the project's solver. The
force is the barrier's force on the sphere (four times the quarter's). Units: mm, kPa, mN.

Usage:
    python -m face_dolfinx.verification.hertz --fine 0.2 --degree 2
    mpirun -n 2 python -m face_dolfinx.verification.hertz --fine 0.4 --depths 0.1 0.2 0.3
"""
import argparse
from dataclasses import dataclass
import math
import time

from mpi4py import MPI
import numpy as np
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh

import forms
from face_dolfinx.equilibrium.solver import FactorReusePolicy, InversionGuard, QuasistaticSolver
from face_dolfinx.model.bones import AffineMap
from face_dolfinx.physics.contact import ContactPotential, ContactSettings, Sphere


@dataclass
class HertzCase:
    """The block, its material and mesh, the sphere and the barrier."""

    radius: float = 10.0      # mm, the sphere's
    size: float = 160.0       # mm, L: the quarter block's width and depth (finite size stiffens like a / L)
    fine: float = 0.4         # mm, the tetrahedra's size near the contact ...
    fine_radius: float = 2.5  # mm, ... within this distance of it (the contact radius is at most 1.7 mm),
    growth: float = 0.25      # ... beyond which the size grows by this much per mm
    degree: int = 2
    mu: float = 1.0           # kPa, shear modulus
    kappa: float = 100.0      # kPa, bulk penalty
    dhat: float = 5e-4        # mm
    stiffness: float = 0.5    # kPa, about the peak Hertz pressure (0.2-0.6 kPa)

    @property
    def youngs_modulus(self) -> float:
        return 9.0 * self.kappa * self.mu / (3.0 * self.kappa + self.mu)

    @property
    def poisson_ratio(self) -> float:
        return (3.0 * self.kappa - 2.0 * self.mu) / (6.0 * self.kappa + 2.0 * self.mu)

    def hertz_force(self, depth: float) -> float:
        effective = self.youngs_modulus / (1.0 - self.poisson_ratio ** 2)
        return 4.0 / 3.0 * effective * math.sqrt(self.radius) * depth ** 1.5


@dataclass
class HertzPoint:
    depth: float        # mm, the sphere's indentation into the undeformed top face
    force: float        # mN, measured
    hertz: float        # mN
    gap: float          # mm, the smallest gap left between the surface and the sphere
    contact_nodes: int  # nodes within dhat (of the quarter)
    newton_iterations: int
    seconds: float
    tets: int
    dofs: int

    @property
    def error(self) -> float:
        return self.force / self.hertz - 1.0


def refined_block(case: HertzCase, comm=MPI.COMM_WORLD):
    """The quarter block, refined around the contact point; meshed on rank 0 and distributed by
    dolfinx, so every number of ranks solves on the same mesh."""
    import gmsh
    from dolfinx.io import gmshio

    if comm.rank == 0:
        gmsh.initialize()
        gmsh.option.setNumber("General.Terminal", 0)
        L = case.size
        box = gmsh.model.occ.addBox(0.0, 0.0, -L, L, L, L)
        gmsh.model.occ.synchronize()
        gmsh.model.addPhysicalGroup(3, [box], 1)
        fields = gmsh.model.mesh.field
        size = fields.add("MathEval")
        fields.setString(size, "F", f"Max({case.fine}, {case.growth} * (Sqrt(x^2 + y^2 + z^2) - {case.fine_radius}))")
        fields.setAsBackgroundMesh(size)
        for option in ("Mesh.MeshSizeExtendFromBoundary", "Mesh.MeshSizeFromPoints", "Mesh.MeshSizeFromCurvature"):
            gmsh.option.setNumber(option, 0)
        gmsh.model.mesh.generate(3)
    mesh, _, _ = gmshio.model_to_mesh(gmsh.model, comm, 0)
    if comm.rank == 0:
        gmsh.finalize()
    return mesh


def solve_hertz(case: HertzCase, depths, comm=MPI.COMM_WORLD) -> list[HertzPoint]:
    mesh = refined_block(case, comm)
    V = fem.VectorFunctionSpace(mesh, ("CG", case.degree))
    u = fem.Function(V, name="displacement")
    L = case.size

    def on(condition):
        return dmesh.locate_entities_boundary(mesh, 2, condition)

    def fixed(facets, component=None):
        if component is None:
            return fem.dirichletbc(np.zeros(3), fem.locate_dofs_topological(V, 2, facets), V)
        space = V.sub(component)
        return fem.dirichletbc(np.float64(0.0), fem.locate_dofs_topological(space, 2, facets), space)

    bcs = [fixed(on(lambda x: np.isclose(x[2], -L))),
           fixed(on(lambda x: np.isclose(x[0], 0.0)), 0),
           fixed(on(lambda x: np.isclose(x[1], 0.0)), 1)]
    top = on(lambda x: np.isclose(x[2], 0.0))
    dx = ufl.dx(domain=mesh, metadata={"quadrature_degree": max(1, 2 * (case.degree - 1))})
    F = forms.deformation_gradient(u)
    laws = [forms.MooneyRivlin(0.5 * case.mu, 0.0), forms.LogVolumetric(case.kappa)]
    v = ufl.TestFunction(V)
    residual = ufl.inner(sum(law.first_piola(F) for law in laws), ufl.grad(v)) * dx
    energy = sum(law.strain_energy(F) for law in laws) * dx

    def pose(depth):
        return AffineMap(np.eye(3), np.array([0.0, 0.0, case.radius - depth]))

    settings = ContactSettings((Sphere(case.radius),), (pose(-0.01),), dhat=case.dhat, stiffness=case.stiffness,
                               surface="top", where="the Hertz block")
    contact = ContactPotential(V, top, settings)
    # Every Newton iteration with its own tangent: the default keeps the factor once corrections
    # fall below 0.1 mm, which here is the whole solve.
    solver = QuasistaticSolver(residual, u, bcs, tangent="spd", energy=energy, inversion_guard=InversionGuard(V),
                               options_prefix="hertz_", energy_terms=(contact,),
                               reuse_policy=FactorReusePolicy(converging_correction=0.0))
    points, at = [], pose(-0.01)
    for depth in depths:
        began = time.perf_counter()
        target = pose(depth)
        start = at

        def set_pose(t, start=start, target=target):
            contact.set_poses((start.interpolate(target, t),))
            solver.controls_changed()

        held = []

        def push(t0, t1, start=start, target=target, held=held):
            held.append(contact.move_to((start.interpolate(target, t1),), solver))

        report = solver.solve_continuation(set_pose, predictor=push)
        at = target
        force = 4.0 * contact.nodal_forces(u.x.array).sum(axis=0)[2]
        points.append(HertzPoint(depth, force, case.hertz_force(depth), contact.min_gap(u.x.array),
                                 contact.contact_nodes(u.x.array), report.newton_iterations + sum(held),
                                 time.perf_counter() - began, mesh.topology.index_map(3).size_global,
                                 3 * V.dofmap.index_map.size_global))
    return points


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fine", type=float, default=0.4, help="mm, the tetrahedra's size at the contact")
    parser.add_argument("--degree", type=int, default=2)
    parser.add_argument("--size", type=float, default=160.0, help="mm, the quarter block's width and depth")
    parser.add_argument("--kappa", type=float, default=100.0)
    parser.add_argument("--dhat", type=float, default=5e-4)
    parser.add_argument("--stiffness", type=float, default=0.5)
    parser.add_argument("--depths", type=float, nargs="+", default=[0.1, 0.2, 0.3])
    args = parser.parse_args(argv)
    case = HertzCase(fine=args.fine, degree=args.degree, size=args.size, kappa=args.kappa, dhat=args.dhat,
                     stiffness=args.stiffness)
    began = time.perf_counter()
    points = solve_hertz(case, args.depths)
    if MPI.COMM_WORLD.rank == 0:
        print(f"# {points[0].tets} tets, {points[0].dofs} dofs, P{case.degree}, L = {case.size} mm, "
              f"fine {case.fine} mm within {case.fine_radius} mm, "
              f"E = {case.youngs_modulus:.4f} kPa, nu = {case.poisson_ratio:.5f}, dhat = {case.dhat:g} mm, "
              f"stiffness = {case.stiffness:g} kPa, {MPI.COMM_WORLD.size} ranks, {time.perf_counter() - began:.1f} s")
        print("| depth (mm) | force (mN) | Hertz (mN) | error | min gap (mm) | contact nodes | Newton its | s |")
        print("|---|---|---|---|---|---|---|---|")
        for p in points:
            print(f"| {p.depth:g} | {p.force:.5f} | {p.hertz:.5f} | {100 * p.error:+.2f} % | {p.gap:.2e} | "
                  f"{p.contact_nodes} | {p.newton_iterations} | {p.seconds:.1f} |")


if __name__ == "__main__":
    main()
