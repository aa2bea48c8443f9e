"""Dynamics with contact (face_dolfinx.equilibrium.dynamics, docs/dynamics.md): the barrier in the
incremental potential. The slab of ``test_contact`` (its top face the skin) thrown against a sphere
bounces off it with no node ever inside, Newmark keeping the total energy (strain, barrier,
kinetic) to the step's accuracy and backward Euler never gaining; a sphere driven into the slab
faster than the barrier alone could follow (the held move) leaves no node inside either; the
result on two ranks is the one on one; ``simulate --dynamic --object --path``: frames, object and
one message for a path that starts inside the skin; the small face's lips pressed in time with the
lips' and the teeth's contact."""
from dataclasses import replace
import json

from mpi4py import MPI
import numpy as np
import pytest

from face_dolfinx.cli.main import main
from face_dolfinx.equilibrium.dynamics import DynamicSettings
from face_dolfinx.model.bones import AffineMap
from face_dolfinx.physics.contact import ContactSettings, Sphere
from face_dolfinx.physics.points import PointEvaluator
from face_dolfinx.physics.problem import FaceProblem
from test_contact import CENTRE, RADIUS, skin_slab

COMM = MPI.COMM_WORLD
# The slab's slowest vibration has a period of about 11 ms (test_dynamics.SLAB_PERIOD).
SLAB_PERIOD = 0.011
SPEED = 300.0  # mm/s: the slab's midline thrown up at this speed (a half sine between its bones)
PROBES = np.array([[20.0, 10.0, 10.0], [12.0, 6.0, 10.0], [30.0, 15.0, 5.0]])


def sphere_at(height):
    """The sphere ``height`` mm above the slab's undeformed top face (negative: pressed in)."""
    return AffineMap(np.eye(3), CENTRE + [0.0, 0.0, height])


def slab_under_sphere(height, settings: DynamicSettings, comm=COMM):
    """With the nodal barrier, whose gaps, contact nodes and forces the tests read (the skin
    triangles' barrier, a sphere's default, in time: ``simulate --dynamic --object`` below)."""
    problem = FaceProblem(skin_slab(comm), contact=ContactSettings((Sphere(RADIUS),), (sphere_at(height),),
                                                                   dhat=0.05, stiffness=10.0, faces=False))
    return problem, problem.dynamics(settings)


def watch_gaps(problem, dynamic) -> list:
    """The smallest gap of every Newton iterate of the time steps (appended as they come)."""
    gaps = []
    dynamic.solver.snes.setMonitor(lambda snes, it, norm: gaps.append(problem.contact.min_gap(snes.getSolution().array_r)))
    return gaps


def bounce(scheme: str, dt: float) -> dict:
    """The slab thrown at a sphere hovering 0.2 mm above it (two periods): per step the total and
    the barrier energy, the contact nodes; the smallest gap of any Newton iterate."""
    problem, dynamic = slab_under_sphere(0.2, DynamicSettings(scheme=scheme, time_step=dt))
    velocity = np.zeros_like(problem.u.x.array)
    velocity.reshape(-1, 3)[:, 2] = SPEED * np.sin(np.pi * problem.dof_coordinates[:, 0] / 40.0)
    dynamic.start(0.0, velocity)
    gaps = watch_gaps(problem, dynamic)
    rest = problem.rest_controls()
    history = dict(total=[], barrier=[], kinetic=[], nodes=[])

    def frame(index, t, report):
        history["total"].append(dynamic.total_energy())
        history["kinetic"].append(dynamic.kinetic_energy())
        history["barrier"].append(problem.contact.energy(problem.u.vector))
        history["nodes"].append(problem.contact.contact_nodes(problem.u.x.array))

    dynamic.run(lambda t: rest, np.arange(0.0, 2 * SLAB_PERIOD + 0.5 * dt, dt), frame)
    return {**{key: np.array(values) for key, values in history.items()}, "min_gap": min(gaps)}


def test_a_slab_bouncing_on_a_sphere_keeps_its_energy_with_newmark_and_loses_it_with_backward_euler():
    """The barrier is conservative: while the slab presses on the sphere and leaves it again,
    Newmark keeps the total energy within 1% at 24 steps a period and closer at 48 (measured 0.53%
    and 0.23%); backward Euler never gains. No Newton iterate of any step has a node inside."""
    coarse = bounce("newmark", SLAB_PERIOD / 24)
    fine = bounce("newmark", SLAB_PERIOD / 48)
    euler = bounce("backward_euler", SLAB_PERIOD / 24)
    for run in (coarse, fine, euler):
        assert run["min_gap"] > 0.0
        assert run["nodes"].max() >= 5 and run["barrier"].max() > 0.5  # uJ: a real contact ...
    # ... that stops the slab (its kinetic energy nearly all turned into strain) and lets it go.
    assert coarse["kinetic"].min() < 0.1 * coarse["kinetic"][0] and coarse["nodes"][-1] == 0
    deviation = {name: np.abs(run["total"] / run["total"][0] - 1.0).max() for name, run in
                 (("coarse", coarse), ("fine", fine))}
    assert deviation["coarse"] < 0.01 and deviation["fine"] < 0.6 * deviation["coarse"]
    assert np.all(np.diff(euler["total"]) <= 1e-9 * euler["total"][0])
    assert euler["total"][-1] < 0.7 * euler["total"][0]


def pressed_in_time(comm=COMM) -> tuple:
    """The sphere driven from 0.5 mm above the slab to 1.5 mm into it in 10 ms (200 mm/s), then held
    for 5 ms, by backward Euler at 0.5 ms steps: the probes' displacements, the force on the sphere,
    the smallest gap of any Newton iterate and of the end, the held moves' count."""
    problem, dynamic = slab_under_sphere(0.5, DynamicSettings(scheme="backward_euler", time_step=5e-4,
                                                              mass_damping=1000.0), comm)
    gaps = watch_gaps(problem, dynamic)
    rest = problem.rest_controls()

    def controls_at(t):
        return replace(rest, objects=(sphere_at(0.5 - 2.0 * min(t / 0.01, 1.0)),))

    dynamic.run(controls_at, np.arange(0.0, 0.015 + 1e-9, 1e-3))
    u = problem.u.x.array
    probes = PointEvaluator(problem.V, PROBES).values(u)
    force = problem.contact.nodal_forces(u).sum(axis=0)
    return probes, force, min(gaps), problem.contact.min_gap(u), dynamic.held_moves, problem.contact.contact_nodes(u)


@pytest.fixture(scope="module")
def pressed():
    return pressed_in_time()


def test_a_sphere_driven_into_the_slab_never_has_a_node_inside(pressed):
    probes, force, smallest, last, held, nodes = pressed
    assert smallest > 0.0 and 0.0 < last < 0.05
    assert held >= 5  # steps that the barrier alone could not have started
    assert nodes >= 3 and force[2] > 50.0  # mN: the slab pushes the sphere back up
    assert probes[0, 2] == pytest.approx(-1.5, abs=0.1)  # the top face under the sphere went with it


def test_the_same_result_on_one_rank(pressed):
    """The distributed run against the same run on this rank alone (under mpirun -n 2)."""
    if COMM.size == 1:
        pytest.skip("one rank: the comparison needs mpirun -n 2")
    probes, force, _, last, held, nodes = pressed_in_time(MPI.COMM_SELF)
    assert np.abs(pressed[0] - probes).max() <= 1e-9  # mm (measured 7e-14)
    assert np.abs(pressed[1] - force).max() <= 1e-9 * np.abs(force).max()
    assert pressed[3] == pytest.approx(last, rel=1e-9) and (pressed[4], pressed[5]) == (held, nodes)


def test_simulate_dynamic_moves_a_sphere_into_the_cheek(model, builtin_model_path, shared_dir):
    """run.py simulate --dynamic --object sphere:15 --path FILE: the face at rest, then the sphere
    along its path at one pose per frame (60 Hz) into the cheek and held there; a frame per time with
    the object's contact, object.xdmf; a path starting inside the face: one message, no folder."""
    from test_contact import cheek_path
    path, out = shared_dir / "path.txt", shared_dir / "pressed"
    # One path for all ranks (each rank's part of the skin gives its own normal).
    centres = COMM.bcast(cheek_path(model, [-0.5, 1.0, 2.0, 1.0]), root=0)
    start_inside, centres = centres[-1:], centres[:3]
    if COMM.rank == 0:
        path.write_text("\n".join(" ".join(f"{v:.6f}" for v in c) for c in centres) + "\n")
    COMM.barrier()
    options = ["simulate", "--model", str(builtin_model_path), "--dynamic", "--object", "sphere:15", "--path",
               str(path), "--expression-time", "0.02", "--time-step", str(1 / 240)]
    assert main([*options, "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    frames = summary["frames"]
    # The rest held 0.02 s, the path from the next frame on (2/60 s), a pose a frame, its end held
    # 0.02 s.
    assert [f["time_s"] for f in frames] == pytest.approx(np.arange(6) / 60.0, abs=1e-6)
    assert frames[0]["object"]["contact_nodes"] == 0 and frames[0]["object"]["min_gap_mm"] > 0.4
    for index, centre in zip((1, 2, 3, 4, 5), (centres[0], centres[0], centres[1], centres[2], centres[2])):
        assert np.allclose(frames[index]["object"]["centre_mm"], centre, atol=1e-4)
    # The sphere presses on the skin's triangles (its default barrier), never entering one.
    pressed = frames[-1]["object"]
    assert 0.0 < pressed["min_triangle_gap_mm"] < 0.05 and pressed["contact_triangles"] >= 1
    assert all(f["object"]["min_triangle_gap_mm"] > 0.0 and f["object"]["min_gap_mm"] > 0.0 for f in frames)
    assert summary["source"]["object"] == "sphere:15" and summary["failure"] is None
    assert (out / "object.xdmf").is_file() and (out / "face.xdmf").is_file()

    inside = shared_dir / "inside.txt"
    if COMM.rank == 0:
        inside.write_text("\n".join(" ".join(f"{v:.6f}" for v in c) for c in start_inside + centres[-1:]) + "\n")
    COMM.barrier()
    with pytest.raises(SystemExit, match=rf"{inside} \(its first pose\): the sphere of radius 15 mm .* starts inside"):
        main([*options, "--path", str(inside), "--out", str(shared_dir / "never")])
    assert not (shared_dir / "never").exists()


def test_lips_pressed_in_time_on_the_small_face(model):
    """The 5K face's pucker (orbicularis oris at 0.9) switched on in 1/60 s with the lips' and the
    teeth's contact, Newmark at 1/240 s: the lips meet and press (barrier pairs), no Newton iterate
    of any step lets them pass through each other, the lining stays off the teeth."""
    from face_dolfinx.physics.contact import TEETH_STIFFNESS
    from face_dolfinx.physics.problem import Controls
    from face_dolfinx.physics.self_contact import LipContactSettings
    problem = FaceProblem(model, contact=ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS),
                          lip_contact=LipContactSettings())
    dynamic = problem.dynamics(DynamicSettings(time_step=1 / 240))
    distances = []
    dynamic.solver.snes.setMonitor(lambda snes, it, norm: distances.append(
        problem.lips.min_distance(snes.getSolution().array_r, reach=1.0)))
    rest = problem.rest_controls()
    pucker = problem.activation_vector(model.expressions["pucker"])

    def controls_at(t):
        s = min(t * 60.0, 1.0)
        return Controls(s * s * (3 - 2 * s) * pucker, rest.cranium, rest.jaw)

    reports = dynamic.run(controls_at, [0.0, 1 / 60, 2 / 60])
    u = problem.u.x.array
    assert problem.lips.pairs(u) >= 10 and min(distances) > 0.0
    assert problem.lips.penetration(u) == 0.0
    assert problem.teeth_contact.min_gap(u) > 0.0
    assert all(report.substeps >= 4 for report in reports[1:])
