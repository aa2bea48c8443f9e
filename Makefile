# Two entry points (see README): `make demo` and `make test`. Both install what they need.
PYTHON := .venv/bin/python
# Open MPI refuses root without these; CI and containers run as root.
export OMPI_ALLOW_RUN_AS_ROOT := 1
export OMPI_ALLOW_RUN_AS_ROOT_CONFIRM := 1
export OMPI_MCA_rmaps_base_oversubscribe := 1
# One BLAS thread per MPI rank: two ranks on two cores must not fight over four threads.
export OPENBLAS_NUM_THREADS := 1
export OMP_NUM_THREADS := 1
NP ?= 2

.PHONY: install demo lint test test-serial test-mpi

install:
	bash scripts/install.sh

# Build the face, synthesise a take, fit it; results/demo/fit/ (see README). Resumes if interrupted.
demo: install
	mpirun -n $(NP) $(PYTHON) run.py demo

# Pyflakes and bugbear's likely bugs ([tool.ruff] in pyproject.toml): seconds, so it runs first.
lint:
	.venv/bin/ruff check .

test: install lint test-serial test-mpi

test-serial:
	$(PYTHON) -m pytest tests -q

test-mpi:
	mpirun -n 2 $(PYTHON) -m pytest tests -q -p no:cacheprovider --color=no
