#!/usr/bin/env python3
"""face_dolfinx driver: ``python run.py demo``, ``mpirun -n 2 python run.py simulate smile``.

Run ``python run.py --help`` (and ``python run.py SUBCOMMAND --help``) for the options.
"""
import sys

from face_dolfinx.cli.main import main

if __name__ == "__main__":
    sys.exit(main())
