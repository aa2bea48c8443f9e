#!/usr/bin/env bash
# Idempotent set-up on Debian bookworm (as root, or with sudo): the FEniCSx stack from Debian,
# an optimised BLAS (PETSc and MUMPS fall back to the reference BLAS without it, 17x slower),
# and a venv on /usr/bin/python3 that sees the Debian packages and holds face_dolfinx (with ruff,
# the linter `make test` runs first).
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PACKAGES=(python3-dolfinx python3-gmsh python3-meshio python3-h5py python3-scipy
              python3-matplotlib python3-venv python3-pytest libopenblas0-pthread openmpi-bin)

missing=()
for pkg in "${APT_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "[install] apt packages: ${missing[*]}"
  $SUDO apt-get update -q
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends "${missing[@]}"
fi

if [ ! -x .venv/bin/python ]; then
  echo "[install] creating .venv from /usr/bin/python3 (system site packages)"
  /usr/bin/python3 -m venv --system-site-packages .venv
fi
stamp=.venv/.face_dolfinx-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "[install] installing face_dolfinx into .venv"
  .venv/bin/python -m pip install -q --disable-pip-version-check -e ".[dev]"
  touch "$stamp"
fi
