"""Hertz verification (face_dolfinx.verification.hertz): a rigid sphere pressed into a thick,
nearly incompressible P2 block; the force against F = 4/3 E* sqrt(R) d^(3/2) within 5 %, on the
coarsest mesh of the table in docs/verification.md, serial and under mpirun -n 2."""
import pytest

from face_dolfinx.verification.hertz import HertzCase, solve_hertz


@pytest.mark.slow
def test_force_against_hertz():
    case = HertzCase(fine=0.5)
    point, = solve_hertz(case, [0.1])
    assert point.contact_nodes >= 10
    assert 0.0 < point.gap < case.dhat
    assert abs(point.error) <= 0.05, f"{point.force:.5f} mN against Hertz's {point.hertz:.5f} mN"
