"""Dynamic re-simulation (face_dolfinx.equilibrium.dynamics): inertia and damping added to the
quasistatic face, stepped by Newmark's average acceleration or backward Euler, checked against a
cantilever's first bending mode, energy conservation, the quasistatic limit and rigid motion."""
import json
import pathlib
from types import SimpleNamespace

from mpi4py import MPI
import numpy as np
import pytest
from dolfinx import mesh as dmesh

from face_dolfinx.cli.main import main
from face_dolfinx.equilibrium.dynamics import DynamicsError, DynamicSettings, TISSUE_DENSITY
from face_dolfinx.model.bones import AffineMap
from face_dolfinx.physics.problem import Controls, FaceProblem
from face_dolfinx.results.folder import FitFolder
from slab import slab_model

COMM = MPI.COMM_WORLD
SLAB_ACTIVATIONS = [0.3, 0.2, 0.1]
# The slab's slowest vibration after releasing SLAB_ACTIVATIONS has a period of about 11 ms
# (zero crossings of its midpoint every 5.5 ms, measured).
SLAB_PERIOD = 0.011


def global_max(array) -> float:
    return COMM.allreduce(float(np.abs(array).max(initial=0.0)), op=MPI.MAX)


def released_slab(scheme: str, dt: float):
    """The slab at its equilibrium under SLAB_ACTIVATIONS, the muscles then switched off: a free
    vibration between its fixed ends."""
    problem = FaceProblem(slab_model())
    problem.solve(activations=SLAB_ACTIVATIONS)
    problem.set_controls(problem.rest_controls())
    return problem, problem.dynamics(DynamicSettings(scheme=scheme, time_step=dt))


def energy_history(scheme: str, dt: float, duration: float) -> np.ndarray:
    problem, dynamic = released_slab(scheme, dt)
    energies = []
    rest = problem.rest_controls()
    dynamic.run(lambda t: rest, np.arange(0.0, duration + 0.5 * dt, dt),
                lambda index, t, report: energies.append(dynamic.total_energy()))
    return np.array(energies)


def test_units_of_the_tissue_density():
    """mm, kPa, mN: 1 mN = 1 kg mm/s^2, so 1000 kg/m^3 = 1e-6 kg/mm^3 and time is in seconds; the
    shear wave speed of 16 kPa flesh is then sqrt(16e3 Pa / 1000 kg/m^3) = 4 m/s = 4000 mm/s."""
    assert TISSUE_DENSITY == 1e-6
    assert np.sqrt(16.0 / TISSUE_DENSITY) == pytest.approx(4000.0)


def test_average_acceleration_keeps_the_energy_of_a_free_vibration_and_backward_euler_dissipates_it():
    """Two periods of the released slab (large motion, a few mm): Newmark's average acceleration
    keeps the total energy within 1% at 24 steps a period, closer at 48 (second order: the error
    falls faster than the step); backward Euler at the same step loses almost all of it."""
    duration = 2 * SLAB_PERIOD
    coarse = energy_history("newmark", SLAB_PERIOD / 24, duration)
    fine = energy_history("newmark", SLAB_PERIOD / 48, duration)
    euler = energy_history("backward_euler", SLAB_PERIOD / 24, duration)
    assert coarse[0] > 100.0  # uJ: a real vibration
    deviation_coarse = np.abs(coarse / coarse[0] - 1).max()
    deviation_fine = np.abs(fine / fine[0] - 1).max()
    assert deviation_coarse < 0.01
    assert deviation_fine < 0.5 * deviation_coarse
    assert euler[-1] < 0.1 * euler[0]
    assert np.all(np.diff(euler) <= 1e-9 * euler[0])  # backward Euler never gains energy


def bar_model(length=100.0, height=10.0, cells=(20, 2, 2)):
    """A square bar [0, L] x [0, h] x [0, h] clamped at x = 0 (the "cranium"), no mandible, one
    muscle along x in its upper half: activated, it bends the bar like a bimetal strip."""
    domain = dmesh.create_box(COMM, [np.zeros(3), np.array([length, height, height])], list(cells),
                              dmesh.CellType.tetrahedron, ghost_mode=dmesh.GhostMode.shared_facet)
    domain.topology.create_connectivity(2, 3)
    clamped = dmesh.locate_entities_boundary(domain, 2, lambda x: np.isclose(x[0], 0.0))
    tags = dmesh.meshtags(domain, 2, np.sort(clamped), np.ones(len(clamped), dtype=np.int32))
    index_map = domain.topology.index_map(3)
    midpoints = dmesh.compute_midpoints(domain, 3, np.arange(index_map.size_local + index_map.num_ghosts,
                                                             dtype=np.int32))
    upper = np.flatnonzero(midpoints[:, 2] > height / 2)
    muscle = SimpleNamespace(name="upper", kind="linear", peak_stress=None, cells=upper,
                             fraction=np.ones(len(upper)), fiber=np.tile([1.0, 0.0, 0.0], (len(upper), 1)))
    material = {"mu10": 6.0, "mu01": 2.0, "kappa": 60.0, "fiber_stress": 30.0}
    return SimpleNamespace(path="<bar>", name="bar", mesh=domain, facet_tags=tags,
                           boundary_ids={"cranium": 1, "mandible": 2}, muscles=[muscle], material=material,
                           material_overrides=(), muscle_names=["upper"], muscle_index=lambda name: 0,
                           peak_stress=lambda index: material["fiber_stress"])


@pytest.mark.slow
def test_first_bending_mode_of_a_cantilever():
    """The bar bent slightly by its muscle and released swings at its first bending mode:
    Euler-Bernoulli omega_1 = 1.8751^2 sqrt(E I / (rho A L^4)), E = 9 K mu / (3 K + mu) with the
    small-strain moduli of the flesh law (mu = 2 (mu10 + mu01) = 16 kPa, K = kappa = 60 kPa), I = h^4/12,
    A = h^2. Timoshenko's shear and rotary inertia lower it by about 0.6% at L/h = 10; P2 tets and
    40 Newmark steps a period (lengthening it by (omega dt)^2 / 12 = 0.2%) measure it within 2%
    (0.4% short, measured)."""
    length, height = 100.0, 10.0
    problem = FaceProblem(bar_model(length, height), degree=2)
    problem.solve(activations=[0.005])
    mu, bulk = 2 * (6.0 + 2.0), 60.0
    young = 9 * bulk * mu / (3 * bulk + mu)
    omega = 1.8751**2 * np.sqrt(young * height**2 / 12 / (TISSUE_DENSITY * length**4))
    period = 2 * np.pi / omega
    rest = problem.rest_controls()
    problem.set_controls(rest)
    dt = period / 40
    dynamic = problem.dynamics(DynamicSettings(time_step=dt))
    tip = np.isclose(problem.dof_coordinates[:, 0], length)
    owned = np.arange(len(tip)) < problem.V.dofmap.index_map.size_local
    tip &= owned
    count = COMM.allreduce(int(tip.sum()), op=MPI.SUM)
    heights = []
    dynamic.run(lambda t: rest, np.arange(0.0, 2.6 * period, dt), lambda index, t, report: heights.append(
        COMM.allreduce(float(problem.u.x.array.reshape(-1, 3)[tip, 2].sum()), op=MPI.SUM) / count))
    heights = np.array(heights)
    assert 0.1 < abs(heights[0]) < 5.0  # mm: a small swing of the 100 mm bar
    crossing = np.flatnonzero(np.sign(heights[1:]) != np.sign(heights[:-1]))
    times = (crossing + heights[crossing] / (heights[crossing] - heights[crossing + 1])) * dt
    assert len(times) >= 5  # four half periods: the second mode's share averages out
    measured = 2 * np.mean(np.diff(times))
    assert measured == pytest.approx(period, rel=0.02)


def test_slow_driving_approaches_the_quasistatic_equilibrium():
    """The slab's muscles switched on along a smooth ramp of duration D, then held: the dynamic
    shape at D differs from the quasistatic one by the lag and the ringing of the motion, which
    vanish as D grows against the slab's period (11 ms)."""
    model = slab_model()  # one mesh, one partition for all
    quasistatic = FaceProblem(model)
    quasistatic.solve(activations=SLAB_ACTIVATIONS)
    scale = global_max(quasistatic.u.x.array)
    differences = []
    for duration in (0.25 * SLAB_PERIOD, SLAB_PERIOD, 4 * SLAB_PERIOD):
        problem = FaceProblem(model)
        dynamic = problem.dynamics(DynamicSettings(time_step=duration / 24))
        rest = problem.rest_controls()

        def controls_at(t, duration=duration, rest=rest):
            s = min(t / duration, 1.0)
            ramp = s * s * (3 - 2 * s)  # smooth start and stop
            return Controls(ramp * np.array(SLAB_ACTIVATIONS), rest.cranium, rest.jaw)

        dynamic.run(controls_at, [0.0, duration])
        differences.append(global_max(problem.u.x.array - quasistatic.u.x.array) / scale)
    assert scale > 0.5  # mm
    assert differences[0] > 0.3  # a sudden push: far from equilibrium
    assert differences[0] > differences[1] > differences[2]
    assert differences[2] < 0.05  # 0.60, 0.25, 0.013 measured


def test_bones_moving_at_constant_velocity_carry_the_flesh_rigidly():
    """Galilean invariance: both ends of the slab translate at 100 mm/s and the flesh starts with
    that velocity: it moves as a rigid body, undeformed, in both schemes (the bone velocities
    follow from the prescribed displacements)."""
    velocity = np.array([100.0, -50.0, 20.0])
    for scheme in ("newmark", "backward_euler"):
        problem = FaceProblem(slab_model())
        rest = problem.rest_controls()
        dynamic = problem.dynamics(DynamicSettings(scheme=scheme, time_step=0.002))
        dynamic.start(0.0, velocity=np.tile(velocity, len(problem.u.x.array) // 3))
        assert global_max(dynamic.acceleration) < 1e-6

        def translated(t, rest=rest):
            return Controls(rest.activations, AffineMap(np.eye(3), velocity * t), rest.jaw)

        dynamic.run(translated, [0.0, 0.01, 0.02])
        assert dynamic.time == 0.02
        expected = np.tile(velocity * 0.02, len(problem.u.x.array) // 3)
        assert global_max(problem.u.x.array - expected) < 1e-8
        assert global_max(dynamic.velocity - np.tile(velocity, len(problem.u.x.array) // 3)) < 1e-5


def test_damping_takes_the_energy_out():
    """A drag of 200/s on the released slab: after two periods (22 ms) the energy has fallen by
    about exp(-200 * 0.022) = 1.2% of its start: below 5%."""
    problem = FaceProblem(slab_model())
    problem.solve(activations=SLAB_ACTIVATIONS)
    rest = problem.rest_controls()
    problem.set_controls(rest)
    dynamic = problem.dynamics(DynamicSettings(mass_damping=200.0, time_step=SLAB_PERIOD / 24))
    start = dynamic.total_energy()
    dynamic.run(lambda t: rest, [0.0, 2 * SLAB_PERIOD])
    assert dynamic.total_energy() < 0.05 * start


def test_bad_input_names_the_problem():
    for settings, message in ((dict(time_step=0.0), "time_step = 0.0: give a positive number"),
                              (dict(time_step=-1e-3), "time_step"),
                              (dict(density=0.0), "density = 0.0: give a positive number"),
                              (dict(density=float("nan")), "density"),
                              (dict(mass_damping=-1.0), "mass_damping = -1.0: give a non-negative number"),
                              (dict(scheme="rk4"), "scheme 'rk4': give one of newmark, backward_euler")):
        with pytest.raises(DynamicsError, match=message):
            DynamicSettings(**settings)
    problem = FaceProblem(slab_model())
    dynamic = problem.dynamics(DynamicSettings(time_step=0.002, max_halvings=2))
    rest = problem.rest_controls()
    for times, message in (([0.0, 0.01, 0.01], "times must increase: 0.01 s is followed by 0.01 s"),
                           ([], "give one or more finite times"), ([-1.0, 0.0], "lies before the current time")):
        with pytest.raises(DynamicsError, match=message):
            dynamic.run(lambda t: rest, times)
    assert dynamic.time == 0.0

    # After 4 ms the mandible end is thrown 60 mm into the cranium end (a 40 mm slab): no substep
    # converges.
    def crushing(t):
        return Controls(rest.activations, rest.cranium, AffineMap(np.eye(3), [-60.0 if t > 0.004 else 0.0, 0, 0]))

    written = []
    with pytest.raises(DynamicsError, match=r"no converged time step at t = 0\.004 s: a substep of 0\.0005 s "
                                            r"failed .* after 3 halving\(s\) .* the state is left at t = 0\.004 s"):
        dynamic.run(crushing, [0.0, 0.004, 0.01], lambda index, t, report: written.append(t))
    assert written == [0.0, 0.004]
    assert dynamic.time == pytest.approx(0.004)
    assert global_max(problem.u.x.array) < 1e-6  # the state of t = 0.004 s: at rest


def test_simulate_dynamic_plays_expressions_in_time(builtin_model_path, tmp_path):
    """``simulate --dynamic``: the smile reached in 50 ms and held, frames at 60 Hz, one XDMF frame
    and one summary row per frame; bad dynamic options stop it before any solve."""
    folder = pathlib.Path(COMM.bcast(str(tmp_path), root=0))
    common = ["simulate", "smile", "--model", str(builtin_model_path), "--dynamic", "--expression-time", "0.05"]
    assert main([*common, "--out", str(folder / "smile")]) == 0
    summary = json.loads((folder / "smile" / "summary.json").read_text())
    frames = summary["frames"]
    assert [row["frame"] for row in frames] == list(range(7))  # 0 to 0.1 s at 60 Hz
    assert summary["failure"] is None and summary["dynamic"]["scheme"] == "newmark"
    assert frames[0]["max_displacement_mm"] == 0.0 and frames[-1]["max_displacement_mm"] > 1.0
    assert all(row["substeps"] == 4 for row in frames[1:])  # 1/60 s in steps of 1/240 s
    assert (folder / "smile" / "face.xdmf").exists()
    for option, message in ((["--time-step", "0"], "time_step = 0.0: give a positive number"),
                            (["--density=-1e-6"], "density = -1e-06: give a positive number"),
                            (["--expression-time", "0"], "--expression-time 0.0: give a positive number")):
        with pytest.raises(SystemExit, match=message):
            main([*common, *option, "--out", str(folder / "bad")])
    assert not (folder / "bad").exists()


def test_simulate_animation_dynamic(builtin_model_path, tmp_path):
    """``simulate --animation FILE --dynamic``: an animation's controls integrated in time, one frame
    at each of its times, into a results folder like a fit's that ``run.py video`` plays; the soft
    face lags the quasistatic playback of the same animation."""
    folder = pathlib.Path(COMM.bcast(str(tmp_path), root=0))
    animation = folder / "smile.toml"
    if COMM.rank == 0:
        animation.write_text("frame_rate = 20\nduration = 0.15\n[muscles.zygomaticus_major_left]\n"
                             "times = [0.0, 0.1]\nvalues = [0.0, 0.6]\n")
    COMM.barrier()
    model = ["--model", str(builtin_model_path)]
    assert main(["simulate", "--animation", str(animation), "--dynamic", *model, "--time-step", "0.025",
                 "--out", str(folder / "played")]) == 0
    assert main(["simulate", "--animation", str(animation), *model, "--out", str(folder / "static")]) == 0
    played, static = FitFolder(folder / "played"), FitFolder(folder / "static")
    assert played.finished and json.loads((folder / "played" / "run.json").read_text())["dynamic"]["time_step"] == 0.025
    assert list(played.times) == [0.0, 0.05, 0.1, 0.15]
    # Frame 0 is the same equilibrium; later frames differ by the motion the inertia holds back.
    assert np.abs(played.displacement(0) - static.displacement(0)).max() < 1e-9
    lag = [np.abs(played.displacement(f) - static.displacement(f)).max() for f in range(1, 4)]
    motion = np.abs(static.displacement(3)).max()
    assert motion > 1.0 and 1e-4 < max(lag) < 0.5 * motion
    assert main(["video", str(folder / "played"), "--gif"]) == 0
    assert (folder / "played" / "face.gif").stat().st_size > 0
    with pytest.raises(SystemExit, match="cannot resume|runs whole"):
        main(["simulate", "--animation", str(animation), "--dynamic", *model, "--stop-after", "2",
              "--out", str(folder / "partial")])
