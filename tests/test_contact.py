"""Contact with rigid kinematic objects (face_dolfinx.physics.contact): the barrier against the IPC
Toolkit's, its gradient and Hessian against finite differences of its energy, a sphere pressed into
the slab and into the small face (no node inside the sphere at any Newton iterate, equilibrium,
force balance), Newton's energy stop (within its tolerance of the equilibrium, never with the
bones short of their values), Newton's factor kept by the residual's energy norm, the
sensitivities with active contact against central differences, the same result on 1 and 2 ranks,
and bad input.
"""
from dataclasses import replace

from mpi4py import MPI
from petsc4py import PETSc
import numpy as np
import pytest
import dolfinx.fem.petsc as fem_petsc
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh

import ipctk
from face_dolfinx.model.bones import AffineMap
from face_dolfinx.physics.contact import ContactSettings, ContactSurface, HalfSpace, Sphere, barrier, barrier_derivatives
from face_dolfinx.physics.points import PointEvaluator
from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.sensitivities.columns import EquilibriumSensitivity
from slab import slab_model

SKIN = 3
RADIUS = 10.0
CENTRE = np.array([20.0, 10.0, 10.0 + RADIUS])  # touching the slab's top face z = 10
ACTIVATIONS = np.array([0.4, 0.6, 0.3])
MARKERS = np.array([[20.0, 10.0, 10.0], [14.0, 6.0, 10.0], [30.0, 15.0, 5.0]])


def skin_slab(comm=MPI.COMM_WORLD, cells=(16, 8, 4), cantilever=False):
    """The test slab with its top face z = 10 tagged as the skin; ``cantilever``: its far end
    (x = 40) free."""
    model = slab_model(cells=cells, comm=comm)
    top = dmesh.locate_entities_boundary(model.mesh, 2, lambda x: np.isclose(x[2], 10.0))
    kept = model.facet_tags.values != (model.boundary_ids["mandible"] if cantilever else -1)
    facets = np.concatenate([model.facet_tags.indices[kept], top])
    values = np.concatenate([model.facet_tags.values[kept], np.full(len(top), SKIN, dtype=np.int32)])
    order = np.argsort(facets)
    model.facet_tags = dmesh.meshtags(model.mesh, 2, facets[order], values[order])
    model.boundary_ids = {**model.boundary_ids, "skin": SKIN}
    return model


def sphere_at(depth):
    """The sphere's pose pressed ``depth`` mm into the undeformed top face."""
    return AffineMap(np.eye(3), CENTRE - [0.0, 0.0, depth])


def pressed_slab(comm=MPI.COMM_WORLD, depth=1.5, degree=1, faces=False, at=sphere_at, **options):
    """The slab pressed ``depth`` mm by the sphere posed by ``at``; by default with the nodal barrier
    (tests/test_face_contact.py: the skin triangles' one, a sphere's default). ``options``: more
    ``FaceProblem`` keywords."""
    settings = ContactSettings((Sphere(RADIUS),), (at(-1.0),), dhat=0.05, stiffness=10.0, faces=faces)
    problem = FaceProblem(skin_slab(comm), degree=degree, contact=settings, **options)
    problem.solve(activations=ACTIVATIONS, objects=(at(depth),))
    return problem


@pytest.fixture(scope="module")
def slab():
    return pressed_slab()


def test_barrier_is_the_ipc_toolkits():
    dhat = 0.05
    g = np.array([1e-4, 3e-3, 0.01, 0.02, 0.049, 0.05, 0.2])
    first, second = barrier_derivatives(g, dhat)
    for k, gap in enumerate(g):
        assert barrier(g, dhat)[k] == pytest.approx(ipctk.barrier(gap, dhat), rel=1e-12, abs=1e-300)
        assert first[k] == pytest.approx(ipctk.barrier_first_derivative(gap, dhat), rel=1e-12, abs=1e-300)
        assert second[k] == pytest.approx(ipctk.barrier_second_derivative(gap, dhat), rel=1e-12, abs=1e-300)
    assert barrier(np.array([0.0, -1.0]), dhat).tolist() == [np.inf, np.inf]
    assert np.isnan(barrier_derivatives(np.array([-1e-3]), dhat)[0]).all()


def random_direction(problem, seed):
    """A smooth random displacement direction on the free dofs, the same on any partition."""
    X = problem.dof_coordinates
    rng = np.random.default_rng(seed)
    waves = rng.normal(size=(3, 3))
    direction = np.sin(X @ waves * 0.3 + rng.normal(size=3)).reshape(-1)
    vector = problem.u.vector.duplicate()
    size = vector.getLocalSize()
    vector.array[:] = direction[:size]
    fem_petsc.set_bc(vector, problem.bcs, scale=0.0)
    return vector


def assert_barrier_derivatives(problem, contact):
    """Through the assembled vector and matrix at ``problem``'s state: dE . v and (H v) . w of the
    contact term against central differences of its energy and of its assembled gradient (v, w:
    smooth random directions; v of 1e-3 mm, inside the gaps), and the Hessian symmetric."""
    u = problem.u.vector
    v, w = random_direction(problem, 1), random_direction(problem, 2)
    v.scale(1e-3 / v.norm(PETSc.NormType.NORM_INFINITY))

    def energy_at(h):
        x = u.copy()
        x.axpy(h, v)
        return contact.energy(x)

    def gradient_at(h):
        x = u.copy()
        x.axpy(h, v)
        b = u.duplicate()
        b.set(0.0)
        contact.add_gradient(x, b)
        return b

    gradient = gradient_at(0.0)
    for h in (0.1, 0.05):
        fd = (energy_at(h) - energy_at(-h)) / (2 * h)
        assert fd == pytest.approx(gradient.dot(v), rel=2e-5 * (h / 0.05) ** 2 + 1e-9)
    A = fem_petsc.assemble_matrix(problem.solver.jacobian_form)  # the finite-element sparsity ...
    A.assemble()
    A.zeroEntries()  # ... holding the contact Hessian alone
    contact.add_hessian(u, A, np.zeros(0, dtype=np.int32))
    Hv = u.duplicate()
    A.mult(v, Hv)
    h = 0.05
    fd = gradient_at(h)
    fd.axpy(-1.0, gradient_at(-h))
    fd.scale(1.0 / (2 * h))
    assert fd.dot(w) == pytest.approx(Hv.dot(w), rel=1e-5)
    difference = fd.copy()
    difference.axpy(-1.0, Hv)
    assert difference.norm() <= 1e-5 * Hv.norm()
    assert A.isSymmetric(1e-10)


def test_gradient_and_hessian_against_differences_of_the_energy(slab):
    """At the pressed state (active contact; the gaps >= 0.02 mm)."""
    assert slab.contact.contact_nodes(slab.u.x.array) >= 4
    assert_barrier_derivatives(slab, slab.contact)


def gaps_while_pressing(problem, smallest_gap, at=sphere_at) -> list:
    """The sphere pressed 1 and then 2.5 mm in, a solve each: ``smallest_gap(displacement)`` at
    every Newton iterate (the solves must converge)."""
    gaps = []
    problem.solver.snes.setMonitor(lambda snes, iteration, norm: gaps.append(smallest_gap(snes.getSolution().array_r)))
    for depth in (1.0, 2.5):
        assert problem.solve(objects=(at(depth),)).converged
    problem.solver.snes.cancelMonitor()
    return gaps


def test_no_node_enters_the_sphere_at_any_newton_iterate():
    problem = pressed_slab(depth=0.0)
    gaps = gaps_while_pressing(problem, problem.contact.min_gap)
    assert len(gaps) > 5 and min(gaps) > 0.0
    assert 0.0 < problem.contact.min_gap(problem.u.x.array) < problem.contact.dhat
    # Equilibrium of the total energy: the residual, contact included, is at its floor.
    assert problem.residual_norm() < 1e-6


def test_a_push_out_that_would_flatten_cells_is_lifted_into_the_flesh():
    """The sphere moved 2.4 mm into the slab's 2.5 mm layer of cells in one solve: put where it
    pushes them (``ContactPotential.move_to``), the surface nodes would flatten that layer's cells;
    they are lifted there from where they were, as a bone motion is (out of the barrier meanwhile,
    and inside the sphere at the start), and the solve takes one load step, no cell below the
    inversion guard's bound and no node the barrier sees inside the sphere at any Newton iterate, to
    the equilibrium the press reaches in two solves."""
    problem = pressed_slab(depth=0.0)
    contact, guard = problem.contact, problem.solver.inversion_guard
    u = problem.u.x.array
    pushed = contact.push_out(u, (sphere_at(2.4),))[0]
    assert guard.flattens(u, pushed)  # the push-out put as it is
    ratios, gaps = [], []

    def monitor(snes, iteration, norm):
        x = snes.getSolution()
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        with x.localForm() as local:
            ratios.append(guard.min_ratio(local.array_r))
        gaps.append(contact.min_gap(x.array_r))

    problem.solver.snes.setMonitor(monitor)
    report = problem.solve(objects=(sphere_at(2.4),))
    problem.solver.snes.cancelMonitor()
    assert report.converged and report.load_steps == 1
    assert min(ratios) >= guard.min_volume_ratio and min(gaps) > 0.0
    stepwise = pressed_slab(depth=0.0)
    for depth in (1.2, 2.4):
        assert stepwise.solve(objects=(sphere_at(depth),)).converged
    grid = np.stack(np.meshgrid(np.linspace(10.0, 30.0, 9), np.linspace(2.0, 18.0, 5), [5.0, 7.5, 10.0]),
                    axis=-1).reshape(-1, 3)
    displacements = [PointEvaluator(p.V, grid).values(p.u.x.array) for p in (problem, stepwise)]
    assert np.abs(displacements[0] - displacements[1]).max() < 1e-3  # mm, of a 2.4 mm press


def test_newton_energy_tolerance_stops_within_that_energy_of_the_equilibrium():
    """With contact, ``newton_energy_tolerance`` stops Newton once a correction would release less
    energy than it (mN mm): the sphere pressed 1.5 mm in ends within that energy of the equilibrium
    that the step tolerance reaches, in fewer iterations. Without energy terms it is off."""
    tolerance = 0.1
    converged, stopped = pressed_slab(depth=0.0), pressed_slab(depth=0.0, newton_energy_tolerance=tolerance)
    full, early = (problem.solve(objects=(sphere_at(1.5),)) for problem in (converged, stopped))
    assert full.converged and early.converged
    assert converged.solver.energy_stops == 0 and stopped.solver.energy_stops > 0
    assert early.newton_iterations < full.newton_iterations
    minimum = converged.solver.energy()
    assert -1e-9 * abs(minimum) < stopped.solver.energy() - minimum < tolerance
    assert stopped.contact.min_gap(stopped.u.x.array) > 0.0
    assert FaceProblem(skin_slab(), newton_energy_tolerance=tolerance).solver.energy_tolerance is None


def test_newton_stops_on_energy_only_once_the_bones_hold_their_values():
    """The jaw end of the slab pressed by the sphere lifted 1 mm: the sphere's collision-free bound
    shortens Newton's first step, which leaves the bone nodes short of their values. A Newton whose
    energy tolerance every correction meets still goes on until they are there, and converges."""
    problem = pressed_slab(newton_energy_tolerance=1e6)
    solver = problem.solver
    lifted = AffineMap(np.eye(3), np.array([0.0, 0.0, 1.0]))
    problem.set_controls(replace(problem.controls, jaw=lifted))
    converged, iterations, reason = solver.newton()
    assert converged, reason
    assert iterations > 1 and solver.energy_stops > 0
    assert solver.bc_error() == 0.0
    assert problem.contact.min_gap(problem.u.x.array) > 0.0


def test_newton_keeps_a_factor_whose_energy_norm_contracts_and_reaches_the_same_equilibrium():
    """With factorisation reuse and contact, a factor is kept where the residual's energy norm
    contracts though its norm does not (``FactorReusePolicy.keep_factor``): the sphere pressed into
    the slab in four moves reaches the same equilibrium with fewer factorisations than when the
    residual norm alone decides (``judge_factor_by_energy`` off)."""
    runs = []
    for judged in (True, False):
        problem = pressed_slab(depth=0.0, reuse_factorization=True)
        problem.solver.judge_factor_by_energy = judged
        before = problem.solver.factorizations
        for depth in (0.5, 1.0, 1.5, 2.0):
            assert problem.solve(objects=(sphere_at(depth),)).converged
        runs.append((problem, problem.solver.factorizations - before))
    (by_energy, fewer), (by_residual, more) = runs
    assert fewer < more
    # (Two meshes, partitioned each their own way: compared by what does not depend on it.)
    on_sphere = [problem.contact.nodal_forces(problem.u.x.array).sum(axis=0) for problem in (by_energy, by_residual)]
    assert np.abs(on_sphere[0] - on_sphere[1]).max() <= 1e-6 * np.abs(on_sphere[1]).max()
    assert by_energy.solver.energy() == pytest.approx(by_residual.solver.energy(), rel=1e-9)
    assert by_energy.residual_norm() < 1e-6


def assert_force_balance(slab) -> np.ndarray:
    """At equilibrium the force the skin puts on the sphere equals the reactions at the bones;
    returns that force (mN)."""
    internal = fem_petsc.create_vector(slab.solver.residual_form)
    fem_petsc.assemble_vector(internal, slab.solver.residual_form)
    internal.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    owned = slab.bone_blocks[slab.bone_blocks < slab.V.dofmap.index_map.size_local]
    reaction = MPI.COMM_WORLD.allreduce(internal.array_r.reshape(-1, 3)[owned].sum(axis=0), op=MPI.SUM)
    on_sphere = slab.contact.nodal_forces(slab.u.x.array).sum(axis=0)
    assert on_sphere[2] > 5.0  # mN: the slab pushes the sphere back up
    assert np.abs(reaction - on_sphere).max() <= 1e-6 * np.abs(on_sphere).max()
    return on_sphere


def test_contact_force_balances_the_bone_reactions(slab):
    assert_force_balance(slab)


def test_same_result_on_one_rank(slab):
    """The distributed solve against the same problem on this rank alone."""
    serial = pressed_slab(comm=MPI.COMM_SELF)
    here = slab.contact.nodal_forces(slab.u.x.array).sum(axis=0)
    alone = serial.contact.nodal_forces(serial.u.x.array).sum(axis=0)
    assert np.abs(here - alone).max() <= 1e-8 * np.abs(alone).max()
    assert slab.contact.min_gap(slab.u.x.array) == pytest.approx(serial.contact.min_gap(serial.u.x.array), rel=1e-9)


def test_activation_columns_with_active_contact(slab):
    """dX/da by the solver's factor (the contact Hessian included) against central differences."""
    slab.solve(activations=ACTIVATIONS, objects=(sphere_at(1.5),))
    sensitivity, markers = EquilibriumSensitivity(slab), PointEvaluator(slab.V, MARKERS)
    sensitivity.factor()
    columns = markers.values_many(sensitivity.activation_columns())
    base = slab.u.x.array.copy()
    step = 1e-4
    for muscle in range(3):
        bump = np.zeros(3)
        bump[muscle] = step
        slab.solve(activations=ACTIVATIONS + bump)
        plus = markers.values(slab.u.x.array)
        slab.solve(activations=ACTIVATIONS - bump)
        minus = markers.values(slab.u.x.array)
        fd = (plus - minus) / (2 * step)
        assert np.abs(columns[muscle] - fd).max() <= 1e-5 * max(np.abs(fd).max(), 1e-3), f"muscle {muscle}"
    slab.adopt(slab.controls, base)


def test_half_space_pushed_into_the_slab():
    """A tilted plane moving down onto the free end of a cantilever slab (a half-space over a
    clamped end would hold its clamped nodes inside): converges, nothing crosses it, the tip
    follows the plane."""
    angle = -0.1  # rad about y: the plane is lowest over the free end x = 40
    tilt = np.array([[np.cos(angle), 0.0, -np.sin(angle)], [0.0, 1.0, 0.0], [np.sin(angle), 0.0, np.cos(angle)]])
    # Above the slab, its solid side up (outward normal -z).
    settings = ContactSettings((HalfSpace((0.0, 0.0, -1.0)),), (AffineMap(tilt, [40.0, 10.0, 10.5]),),
                               dhat=0.05, stiffness=10.0)
    problem = FaceProblem(skin_slab(cantilever=True), contact=settings)
    report = problem.solve(objects=(AffineMap(tilt, [40.0, 10.0, 8.0]),))
    assert report.converged and problem.contact.min_gap(problem.u.x.array) > 0.0
    assert problem.contact.nodal_forces(problem.u.x.array).sum(axis=0)[2] > 1.0
    tip = PointEvaluator(problem.V, np.array([[40.0, 10.0, 10.0]])).values(problem.u.x.array)[0]
    assert tip[2] == pytest.approx(-2.0, abs=0.1)


def test_object_starting_inside_is_refused():
    settings = ContactSettings((Sphere(RADIUS),), (sphere_at(0.5),), where="sphere.json")
    with pytest.raises(ValueError, match="sphere.json: the sphere of radius 10 mm .* starts inside the skin"):
        FaceProblem(skin_slab(cells=(8, 4, 2)), contact=settings)
    with pytest.raises(ValueError, match="no facets tagged 'lips'"):
        FaceProblem(skin_slab(cells=(8, 4, 2)), contact=ContactSettings((Sphere(1.0),), surface="lips"))


def test_sphere_pressed_into_the_cheek_of_the_small_face(model):
    """The paper's figure 9 on the 5K face: a ball pressed 4 mm into the left cheek of a face with
    the left zygomaticus major on. Newton never leaves a node inside the ball, the equilibrium holds,
    the bones carry the ball's force."""
    radius = 15.0
    outside, inside = cheek_path(model, [0.0, 1.0], radius)
    normal = (outside - inside) / np.linalg.norm(outside - inside)

    def ball(depth):
        return AffineMap(np.eye(3), cheek_path(model, [depth], radius)[0])

    problem = FaceProblem(model, contact=ContactSettings((Sphere(radius),), (ball(-1.0),), dhat=0.05, stiffness=10.0,
                                                         faces=False))
    activations = {"zygomaticus_major_left": 0.5}
    problem.solve(activations=activations)
    gaps = []
    problem.solver.snes.setMonitor(lambda snes, it, norm: gaps.append(problem.contact.min_gap(snes.getSolution().array_r)))
    report = problem.solve(objects=(ball(4.0),))
    problem.solver.snes.cancelMonitor()
    assert report.converged and min(gaps) > 0.0
    assert problem.contact.contact_nodes(problem.u.x.array) >= 3
    on_ball = problem.contact.nodal_forces(problem.u.x.array).sum(axis=0)
    assert on_ball @ normal > 10.0  # mN: the cheek pushes the ball back out
    internal = fem_petsc.create_vector(problem.solver.residual_form)
    fem_petsc.assemble_vector(internal, problem.solver.residual_form)
    internal.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    owned = problem.bone_blocks[problem.bone_blocks < problem.V.dofmap.index_map.size_local]
    reaction = MPI.COMM_WORLD.allreduce(internal.array_r.reshape(-1, 3)[owned].sum(axis=0), op=MPI.SUM)
    assert np.abs(reaction - on_ball).max() <= 1e-5 * np.abs(on_ball).max()


def cheek_path(model, depths, radius=15.0):
    """Sphere centres along the outward normal (area-weighted, of the skin triangles oriented out)
    of the left cheek, at these depths into the skin."""
    points, triangles = model.skin_surface()
    site = model.markers["nasolabial_left_3"]
    corners = points[triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal = normals[np.linalg.norm(corners.mean(axis=1) - site, axis=1) < 12.0].sum(axis=0)
    normal /= np.linalg.norm(normal)
    return [site + (radius - depth) * normal for depth in depths]


def test_simulate_moves_a_sphere_along_a_path(model, builtin_model_path, shared_dir):
    """run.py simulate --object sphere:15 --path FILE: a frame per pose, the object's series, and
    one clear error for a path that starts inside the face or a malformed line."""
    import json
    from face_dolfinx.cli.main import main
    path, out = shared_dir / "path.txt", shared_dir / "pressed"
    centres = cheek_path(model, [-1.0, 2.0, 4.0, 0.0])
    if MPI.COMM_WORLD.rank == 0:
        path.write_text("# x y z\n" + "\n".join(" ".join(f"{v:.6f}" for v in c) for c in centres) + "\n")
    MPI.COMM_WORLD.barrier()
    assert main(["simulate", "--model", str(builtin_model_path), "--object", "sphere:15", "--path", str(path),
                 "--out", str(out), "--no-render"]) == 0
    rows = json.loads((out / "summary.json").read_text())["object"]
    assert [row["pose"] for row in rows] == [0, 1, 2, 3]
    # The sphere keeps the skin's triangles out (its nodes stay further than dhat).
    assert rows[2]["contact_triangles"] >= 3 and rows[2]["min_triangle_gap_mm"] > 0.0 and rows[2]["min_gap_mm"] > 0.0
    # Back at depth 0 the sphere's surface passes through the marker site, on a skin triangle: it
    # only touches the skin there.
    assert rows[3]["min_triangle_gap_mm"] > 0.0
    assert np.linalg.norm(rows[3]["force_on_object_mN"]) < 0.1 * np.linalg.norm(rows[2]["force_on_object_mN"])
    assert (out / "object.xdmf").exists() and (out / "object.h5").exists()
    inside, pressed_in = shared_dir / "inside.txt", cheek_path(model, [3.0])[0]
    if MPI.COMM_WORLD.rank == 0:
        inside.write_text(" ".join(f"{v:.6f}" for v in pressed_in) + "\n")
        (shared_dir / "bad.txt").write_text("1 2 3\n4 five 6\n")
    MPI.COMM_WORLD.barrier()
    with pytest.raises(SystemExit, match="inside.txt .its first pose.: the sphere of radius 15 mm .* starts inside the skin"):
        main(["simulate", "--model", str(builtin_model_path), "--object", "sphere:15", "--path", str(inside),
              "--out", str(shared_dir / "never"), "--no-render"])
    with pytest.raises(SystemExit, match="bad.txt, line 2: expected the three coordinates"):
        main(["simulate", "--model", str(builtin_model_path), "--object", "sphere:15", "--path",
              str(shared_dir / "bad.txt"), "--out", str(shared_dir / "never"), "--no-render"])
    with pytest.raises(SystemExit, match="give sphere:RADIUS"):
        main(["simulate", "--model", str(builtin_model_path), "--object", "cube:3", "--path", str(path),
              "--out", str(shared_dir / "never"), "--no-render"])


@pytest.mark.parametrize("tag", ["skin", "oral"])
def test_contact_surface_holds_every_facet_node_on_any_ranks(model, tag):
    """A facet's node may be owned by a rank that does not hold the facet: the gathered surface
    still has every node, so its lumped areas add up to the facets' area (assembled by DOLFINx)."""
    space = FaceProblem(model).V
    facets = model.facet_tags.find(model.boundary_ids[tag])
    surface = ContactSurface(space, facets)
    ds = ufl.Measure("ds", domain=model.mesh, subdomain_data=model.facet_tags,
                     subdomain_id=model.boundary_ids[tag], metadata={"quadrature_degree": 1})
    area = model.mesh.comm.allreduce(fem.assemble_scalar(fem.form(fem.Constant(model.mesh, 1.0) * ds)), op=MPI.SUM)
    vertices = dmesh.compute_incident_entities(model.mesh, facets, 2, 0)
    global_vertices = model.mesh.topology.index_map(0).local_to_global(vertices)
    assert surface.num_nodes == len(np.unique(np.concatenate(model.mesh.comm.allgather(global_vertices))))
    assert surface.areas.sum() == pytest.approx(area, rel=1e-12)
