#!/bin/bash
# The model ladder of docs/ladder.md, stage by stage (cheapest first), one process at a time,
# every stage appending to one JSON-lines file in benchmarks/results/ladder/ (emptied first; each
# stage adds its entry to the folder's manifest.json); then the tables and charts. Each stage
# reuses the cached takes (runs/ladder_takes). Touch runs/STOP to end it after the current stage.
#   nice -n 19 benchmarks/run_ladder.sh            # then see runs/ladder_table.md, docs/img/ladder_*.png
set -u
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-.venv/bin/python}
OUT=${OUT:-benchmarks/results/ladder/ladder_truth20k.jsonl}
COMMON="--truth-tets ${TRUTH_TETS:-20000} --variant-tets ${VARIANT_TETS:-10000} --scenarios speech jaw smile --frames 12 --out $OUT"
run() { [ -e runs/STOP ] && exit 0; echo "== $*"; $PYTHON benchmarks/model_ladder.py $COMMON "$@"; }
mkdir -p runs
$PYTHON benchmarks/provenance.py start $OUT
run --tets 5000 --rungs fe --variants
run --tets 5000 --rungs linear --variants --training-levels ${TRAINING_LEVELS:-2}
run --tets 10000 --rungs fe --variants
for variant in reuse gn1 fast paper; do run --tets 10000 --rungs --variants $variant; done
run --tets 20000 --rungs fe --variants
for variant in newton-1e-4 ls2 newton-1e-6 gn6 fresh-jacobian; do run --tets 10000 --rungs --variants $variant; done
$PYTHON benchmarks/model_ladder.py --collect $OUT --plot docs/img/ladder > runs/ladder_table.md

# At the paper's scale: a truth at 404K tets, the FE rungs on 2 ranks, `fit --fast` at every size
# (about 80 minutes, most of it the 404K truth and the 404K rung).
OUT404=${OUT404:-benchmarks/results/ladder/ladder_truth404k_np2.jsonl}
[ -e runs/STOP ] && exit 0
$PYTHON benchmarks/provenance.py start $OUT404
mpirun -n 2 $PYTHON benchmarks/model_ladder.py --truth-tets 400000 --tets 10000 50000 --rungs fe \
  --variants fit-fast --variant-tets 10000 50000 150000 400000 --scenarios speech jaw smile --frames 12 --out $OUT404
$PYTHON benchmarks/model_ladder.py --collect $OUT404 --plot docs/img/ladder_404k > runs/ladder_404k_table.md
