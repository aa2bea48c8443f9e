"""Regional material overrides (face_dolfinx.model.regions): softer or stiffer flesh in a muscle's
cells, a sphere or a box, honoured by FaceProblem and by simulate and fit."""
import json
import pathlib
from types import SimpleNamespace

from mpi4py import MPI
import numpy as np
import pytest
import ufl
from face_dolfinx.equilibrium.solver import compile_form
import dolfinx.fem.petsc as fem_petsc

import forms
from face_dolfinx.cli.main import main, parse_arguments
from face_dolfinx.model.bones import AffineMap
from face_dolfinx.model.folder import ModelError, cell_midpoints
from face_dolfinx.model.regions import (MaterialError, MaterialOverride, Region, parse_material_option,
                                        read_material_file)
from face_dolfinx.physics.material import FaceMaterial, FiberSlot
from face_dolfinx.physics.problem import FaceProblem
from slab import slab_model

COMM = MPI.COMM_WORLD
WHOLE_SLAB = "box:-1,-1,-1,41,21,11"
LEFT_HALF = "box:-1,-1,-1,20,21,11"


def overridden(model, *specs):
    """The slab with overrides (the slab is a plain namespace, without FaceModel.with_material)."""
    overrides = tuple(parse_material_option(spec) for spec in specs)
    return SimpleNamespace(**{**vars(model), "material_overrides": overrides})


def global_max(array) -> float:
    return COMM.allreduce(float(np.abs(array).max(initial=0.0)), op=MPI.MAX)


def test_a_uniform_model_keeps_its_forms_to_the_bit():
    """Without overrides the residual is the one of the flesh laws with the model's numbers (no DG0
    material fields): the results of a uniform model stay what they were, to the bit. An override
    of factor 1 everywhere (DG0 fields of the same values) agrees to round-off."""
    model = slab_model()
    uniform = FaceProblem(model)
    assert uniform.material_fields is None
    uniform.solve(activations=[0.5, 0.3, 0.2], jaw=AffineMap(np.eye(3), np.array([2.0, 0.0, 1.0])))
    F = forms.deformation_gradient(uniform.u)
    laws = FaceMaterial.from_parameters(model.material, [FiberSlot(f0, w, a) for w, f0, a in zip(
        uniform.slots.weight, uniform.slots.fiber, uniform.slots.activation)])
    dx = ufl.dx(domain=model.mesh, metadata={"quadrature_degree": 1})
    residual = compile_form(ufl.inner(laws.first_piola(F), ufl.grad(ufl.TestFunction(uniform.V))) * dx)
    expected = fem_petsc.assemble_vector(residual)
    got = fem_petsc.assemble_vector(uniform.solver.residual_form)
    assert np.array_equal(expected.array, got.array)

    same = FaceProblem(overridden(model, f"{WHOLE_SLAB}:all=1"))
    assert same.material_fields is not None
    same.solve(activations=[0.5, 0.3, 0.2], jaw=AffineMap(np.eye(3), np.array([2.0, 0.0, 1.0])))
    assert global_max(same.u.x.array - uniform.u.x.array) < 1e-12


def test_softening_everything_equals_doubling_the_activation():
    """Psi = s (flesh + passive) + a active has the equilibrium of flesh + passive + (a / s) active:
    the whole slab at half stiffness and activation 0.3 moves as the plain slab at 0.6."""
    model = slab_model()  # one mesh, one partition for both
    soft = FaceProblem(overridden(model, f"{WHOLE_SLAB}:all=0.5"))
    plain = FaceProblem(model)
    soft.solve(activations=[0.3, 0.2, 0.1])
    plain.solve(activations=[0.6, 0.4, 0.2])
    assert global_max(plain.u.x.array) > 1.0
    assert global_max(soft.u.x.array - plain.u.x.array) < 1e-7


def test_a_soft_half_takes_two_thirds_of_a_stretch():
    """The slab stretched by 0.2 mm between its bones, its left half at half stiffness (all four
    parameters, so the same Poisson ratio): two springs in series put 2/3 of the stretch into the
    soft half (a bar's 1D answer; the clamped ends shift it by 2% on this mesh), 1/2 into a
    uniform slab."""
    stretch = AffineMap(np.eye(3), np.array([0.2, 0.0, 0.0]))
    share = {}
    for name, model in (("uniform", slab_model()), ("soft", overridden(slab_model(), f"{LEFT_HALF}:all=0.5"))):
        problem = FaceProblem(model)
        problem.solve(jaw=stretch)
        middle = np.isclose(problem.dof_coordinates[:, 0], 20.0)
        owned = np.arange(len(problem.dof_coordinates)) < problem.V.dofmap.index_map.size_local
        values = problem.u.x.array.reshape(-1, 3)[middle & owned, 0]
        share[name] = COMM.allreduce(values.sum(), op=MPI.SUM) / COMM.allreduce(len(values), op=MPI.SUM) / 0.2
    assert share["uniform"] == pytest.approx(0.5, abs=0.002)
    assert share["soft"] == pytest.approx(2.0 / 3.0, rel=0.03)


@pytest.mark.parametrize("parameter", ["mu10", "mu01", "kappa", "passive"])
def test_the_energy_is_affine_in_each_factor_and_local_to_the_region(parameter):
    """At one deformed shape the strain energy grows linearly with each parameter's factor (every
    law is linear in its modulus), and a region's factor acts on its cells only."""
    model = slab_model()  # one mesh, one partition for all
    base = FaceProblem(model)
    base.solve(activations=[0.0, 0.0, 0.0], jaw=AffineMap(np.eye(3), np.array([6.0, 0.0, 2.0])))
    shape = base.u.x.array.copy()
    energies = {}
    for factor in (1.0, 2.0, 3.0):
        problem = FaceProblem(overridden(model, f"{LEFT_HALF}:{parameter}={factor}"))
        problem.adopt(base.controls, shape)
        energies[factor] = problem.energy()
    assert energies[1.0] == pytest.approx(base.energy(), rel=1e-12)
    assert energies[2.0] > energies[1.0] * 1.001  # the stretched passive fibres too
    assert energies[3.0] - energies[1.0] == pytest.approx(2.0 * (energies[2.0] - energies[1.0]), rel=1e-9)
    everywhere = FaceProblem(overridden(model, f"{WHOLE_SLAB}:{parameter}=2"))
    everywhere.adopt(base.controls, shape)
    assert everywhere.energy() - energies[1.0] > 1.2 * (energies[2.0] - energies[1.0])


def test_values_replace_and_later_overrides_act_on_earlier_ones(tmp_path):
    """A box sets mu10 = 3 in the left half; a sphere inside it then doubles everything and halves
    kappa: mu10 6, mu01 4, kappa 60, passive 2 in the sphere, the slab's own values outside the box."""
    folder = pathlib.Path(COMM.bcast(str(tmp_path), root=0))
    path = folder / "material.toml"
    if COMM.rank == 0:
        path.write_text("""[[region]]
box = [-1, -1, -1, 20, 21, 11]
value = { mu10 = 3.0 }

[[region]]
sphere = [10.0, 10.0, 5.0, 6.0]
scale = { all = 2.0, kappa = 0.5 }
""")
    COMM.barrier()
    model = SimpleNamespace(**{**vars(slab_model()), "material_overrides": tuple(read_material_file(path))})
    problem = FaceProblem(model)
    dofs = problem.material_fields["mu10"].function_space.dofmap.list.array.reshape(-1)
    midpoints = cell_midpoints(problem.mesh)
    in_sphere = np.linalg.norm(midpoints - [10.0, 10.0, 5.0], axis=1) <= 6.0
    in_box = (midpoints[:, 0] <= 20.0) & ~in_sphere
    outside = ~(in_sphere | in_box)
    expected = {"mu10": (6.0, 3.0, 6.0), "mu01": (4.0, 2.0, 2.0), "kappa": (60.0, 60.0, 60.0),
                "passive": (2.0, 1.0, 1.0)}
    for name, (sphere, box, rest) in expected.items():
        values = problem.material_fields[name].x.array[dofs]
        assert np.all(values[in_sphere] == sphere) and np.all(values[in_box] == box)
        assert np.all(values[outside] == rest), name
    assert COMM.allreduce(int(in_sphere.sum()), op=MPI.SUM) > 0


def test_bad_overrides_name_the_problem(model, tmp_path):
    with pytest.raises(ModelError, match="unknown muscle 'mentalis_lft'"):
        model.with_material([parse_material_option("muscle:mentalis_lft:all=0.5")])
    with pytest.raises(ModelError, match="sphere:1000,0,0,5 holds no cell"):
        model.with_material([parse_material_option("sphere:1000,0,0,5:all=0.5")])
    for text, message in (("sphere:0,0,0,5:all=0", "all must be a positive number"),
                          ("sphere:0,0,0,5:mu10=-2", "mu10 must be a positive number"),
                          ("sphere:0,0,0,5:stiffness=2", "unknown parameter 'stiffness'"),
                          ("sphere:0,0,0:all=2", r"give sphere:X,Y,Z,R"),
                          ("sphere:0,0,0,-1:all=2", "radius must be positive"),
                          ("box:0,0,0,1,1,-1:all=2", "lower corner"),
                          ("cylinder:0,0,0,1:all=2", "give one of muscle, sphere, box"),
                          ("sphere:0,0,0,5", "REGION:PARAM=FACTOR")):
        with pytest.raises(MaterialError, match=message):
            parse_material_option(text)
    with pytest.raises(SystemExit):
        parse_arguments(["simulate", "smile", "--material", "sphere:0,0,0,5:all=0"])
    folder = pathlib.Path(COMM.bcast(str(tmp_path), root=0))
    bad = folder / "bad.toml"
    if COMM.rank == 0:
        bad.write_text("[[region]]\nsphere = [0, 0, 0, 5]\nmuscle = 'x'\nscale = { all = 2 }\n")
    COMM.barrier()
    with pytest.raises(MaterialError, match="bad.toml: region 1: give exactly one of"):
        read_material_file(bad)
    with pytest.raises(MaterialError, match="missing.toml: cannot read"):
        read_material_file(folder / "missing.toml")
    assert MaterialOverride(Region("muscle", name="m"), {"passive": 2}).factors()["passive"] == 2


def test_simulate_and_fit_honour_and_record_the_material(builtin_model_path, model, tmp_path):
    """simulate with a soft nose moves differently and says so in summary.json; fit records the
    overrides in run.json."""
    folder = pathlib.Path(COMM.bcast(str(tmp_path), root=0))
    nose = model.landmarks.get("nose_tip", None)
    assert nose is not None
    soft = f"sphere:{nose[0]:.3f},{nose[1]:.3f},{nose[2]:.3f},15:all=0.2"
    common = ["--model", str(builtin_model_path), "--no-render"]
    assert main(["simulate", "smile", *common, "--out", str(folder / "plain")]) == 0
    assert main(["simulate", "smile", *common, "--material", soft, "--out", str(folder / "soft")]) == 0
    plain = json.loads((folder / "plain" / "summary.json").read_text())
    summary = json.loads((folder / "soft" / "summary.json").read_text())
    assert plain["material"] == []
    assert summary["material"] == [dict(region=soft.rpartition(":")[0], scale={"all": 0.2}, value={})]
    assert summary["expressions"][0]["max_displacement_mm"] != plain["expressions"][0]["max_displacement_mm"]

    model_args = ["--model", str(builtin_model_path), "--material", soft]
    take = folder / "take.trc"
    assert main(["synth", *model_args, "--frames", "2", "--noise", "0", "--out", str(take)]) == 0
    assert main(["fit", str(take), *model_args, "--out", str(folder / "fit")]) == 0
    run = json.loads((folder / "fit" / "run.json").read_text())
    assert run["material"] == summary["material"]
    rows = (folder / "fit" / "frames.csv").read_text().splitlines()
    assert max(float(row.split(",")[1]) for row in rows[1:]) < 0.05  # the same model: markers reached
