#!/bin/bash
# Every benchmark of docs/performance.md, docs/ladder.md and docs/stability.md, one after the other
# (they time themselves: run nothing else meanwhile), raw results in runs/, then the tables and
# figures. About 6 hours on the 2-core machine; each stage can be run on its own (see each script).
#   benchmarks/run_all.sh            # then runs/forward_table.md, runs/ladder_table.md, docs/img/*
set -eu
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-.venv/bin/python}
MPI2="mpirun -n 2"
export OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1
mkdir -p runs

# Forward solves: 5K..400K tets, 1 and 2 ranks; at 400K also from the 50K face's equilibrium.
FORWARD="benchmarks/forward_scaling.py --expressions smile jaw_open pucker"
for ranks in 1 2; do
  mpirun -n $ranks $PYTHON $FORWARD --tets 5000 20000 50000 150000 400000 > runs/forward_np$ranks.jsonl
  mpirun -n $ranks $PYTHON $FORWARD --tets 400000 --coarse 50000 > runs/forward_np${ranks}_coarse.jsonl
done
$PYTHON $FORWARD --collect runs/forward_table.md runs/forward_np*.jsonl

# Tracking: solver variants at the paper's scale and against the naive loop; layouts of a whole take.
$MPI2 $PYTHON benchmarks/tracking_speed.py --tets 400000 --frames 4 --variants fast reuse-1j-loose-gn2 naive > runs/tracking_400k.log
$MPI2 $PYTHON benchmarks/tracking_speed.py --tets 50000 --frames 4 --variants naive fresh reuse-1j > runs/tracking_50k.log
$PYTHON benchmarks/ranks_and_chunks.py --tets 20000 --frames 120 \
  --fit-options="--reuse-factorization --fresh-jacobians 1" > runs/ranks_and_chunks.log
$PYTHON benchmarks/ranks_and_chunks.py --tets 400000 --frames 16 --take-frames 240 --first-frame 80 \
  --fit-options=--fast > runs/ranks_and_chunks_404k.log
# The fastest speech stretch (frames 114-125) of two takes at 400K, fit --fast with one and with three
# line-search iterations (docs/performance.md, session 8): per-frame seconds in each timings.csv.
for seed in 0 3; do
  take=runs/speech114_seed$seed.trc
  $MPI2 $PYTHON run.py synth --tets 400000 --frames 12 --take-frames 240 --first-frame 114 --noise 0.5 \
    --seed $seed --out $take --overwrite
  for iterations in 1 3; do
    $MPI2 $PYTHON run.py fit $take --tets 400000 --fast --line-search-iterations $iterations \
      --out runs/speech114_seed${seed}_ls$iterations --overwrite
  done
done

# Where methods fail, and the model ladder (each writes its own tables and figures).
$PYTHON benchmarks/stability.py --out runs/stability.jsonl
$PYTHON benchmarks/stability.py --collect runs/stability.jsonl --plot docs/img/stability > runs/stability_tables.md
benchmarks/run_ladder.sh
