"""What the inversion guard and the continuation fallback buy (docs/stability.md), on the small
built-in face: every muscle switched from 0 to 1 in one call.

Measured on the 5K face (benchmarks/stability.py): plain Newton (full steps, no guard, no
continuation) inverts cells at its first step (det F -13, NaN residual); the guard alone keeps
every cell above a tenth of its volume but stalls after 5 Newton iterations; the default (guard +
continuation) reaches the equilibrium in 3 load steps with every cell above 0.6 of its volume.
Also under mpirun -n 2.
"""
import numpy as np
import pytest

from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.equilibrium.solver import EquilibriumError


def test_plain_newton_inverts_where_the_default_converges(model):
    every_muscle = np.ones(len(model.muscles))
    plain = FaceProblem(model, inversion_guard=False, petsc_options={"snes_linesearch_type": "basic"})
    # A NaN residual of the logarithmic volumetric law means a cell with det F <= 0.
    with pytest.raises(EquilibriumError, match="DIVERGED_FNORM_NAN"):
        plain.solve(activations=every_muscle, max_halvings=0)

    guarded = FaceProblem(model)
    with pytest.raises(EquilibriumError, match="DIVERGED_LINE_SEARCH"):  # the guard's stall test
        guarded.solve(activations=every_muscle, max_halvings=0)

    report = guarded.solve(activations=every_muscle)
    assert report.converged and report.load_steps > 1
    assert guarded.residual_norm() < 1e-5  # mN; the initial residual is ~6e5
    assert guarded.solver.inversion_guard.min_ratio(guarded.u.x.array) > 0.5
