#!/bin/bash
# Every benchmark of docs/performance.md, docs/ladder.md, docs/stability.md and docs/dynamics.md, one after the other
# (they time themselves: run nothing else meanwhile). Each result goes to benchmarks/results/<study>/
# under the name the docs cite, with an entry in that folder's manifest.json (commit, command,
# machine, date, tets, ranks; benchmarks/provenance.py); bulky fit folders and takes go to runs/.
# About 6 hours on the 2-core machine; each stage can be run on its own (see each script).
#   benchmarks/run_all.sh            # then runs/forward_table.md, runs/*_table*.md, docs/img/*
set -eu
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-.venv/bin/python}
RESULTS=benchmarks/results
export OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1
mkdir -p runs
# A command whose standard output (its JSON lines) is the result file $1, recorded in the manifest.
record() { out=$1; shift; $PYTHON benchmarks/provenance.py run --out "$out" --json-lines -- "$@"; }
# The same, adding to the result file $1 (which `provenance.py start` emptied).
add() { out=$1; shift; $PYTHON benchmarks/provenance.py run --out "$out" --json-lines --append -- "$@"; }

# The built-in face at 5K..1M tets: tets, nodes, seconds, peak memory, element quality (docs/builtin_face.md).
record $RESULTS/model/builtin_face_build.jsonl $PYTHON benchmarks/builtin_face_build.py --tets 5000 50000 400000 1000000
# Forward solves: 5K..400K tets, 1 and 2 ranks; at 400K also from the 50K face's equilibrium.
FORWARD="benchmarks/forward_scaling.py --expressions smile jaw_open pucker"
forward=$RESULTS/forward/forward_5k-404k_np1-np2.jsonl
$PYTHON benchmarks/provenance.py start $forward
for ranks in 1 2; do
  add $forward mpirun -n $ranks $PYTHON $FORWARD --tets 5000 20000 50000 150000 400000
  add $forward mpirun -n $ranks $PYTHON $FORWARD --tets 400000 --coarse 50000
done
$PYTHON $FORWARD --collect runs/forward_table.md $forward

# The lips pressed on the teeth by the orbicularis oris at 0.1, with and without the teeth contact.
record $RESULTS/contact/teeth_5k-20k_np1.jsonl $PYTHON benchmarks/contact_teeth.py --tets 5000 20000
# The teeth's gradient, Hessian and step per call on that solve's iterates: sampled search against the centroid search.
record $RESULTS/contact/teeth_terms_5k-20k_np1.jsonl $PYTHON benchmarks/contact_teeth_terms.py --tets 5000 20000
# The lips' terms per Newton iteration, this version against one that built the collision set in every call
# (rounds in turn), and the closing solve's iterates (bit for bit with the IPC Toolkit on one thread).
git show 944f7b8:face_dolfinx/physics/self_contact.py > runs/self_contact_944f7b8.py
lips=$RESULTS/contact/lip_calls_5k-20k_np1.jsonl
$PYTHON benchmarks/provenance.py start $lips
add $lips $PYTHON benchmarks/lip_contact_calls.py --tets 5000 20000 --compare-with runs/self_contact_944f7b8.py
add $lips $PYTHON benchmarks/lip_contact_calls.py --tets 5000 --ipctk-threads 1
# A probe tip and a blade pressed into the cheek, with the instrument's vertices and edges kept off
# the skin and with the skin's nodes alone (each run writes its own JSON and manifest entry).
for tets in 5000 20000; do
  for instrument in tip blade; do
    $PYTHON benchmarks/instrument.py --tets $tets --instrument $instrument \
      --out $RESULTS/contact/instrument_${instrument}_$((tets / 1000))k.json
    $PYTHON benchmarks/instrument.py --tets $tets --instrument $instrument --nodes \
      --out $RESULTS/contact/instrument_${instrument}_$((tets / 1000))k_nodes.json
  done
done
# A warm tracking frame with lip and teeth contact against the same frame without (fit --fast, one run):
# modified Newton and Krylov on the old factor.
record $RESULTS/contact/tracking_5k_np1.jsonl $PYTHON benchmarks/contact_tracking.py --tets 5000 --frames 5 \
  --variants no-contact contact contact-krylov --max-seconds 600 --abort-seconds 2400
record $RESULTS/contact/tracking_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py --tets 400000 \
  --truth-tets 20000 --frames 3 --variants no-contact contact-krylov contact --max-seconds 1200 --abort-seconds 5400
# ... with the nodes in contact relaxed after each Newton correction (fit --fast's --contact-relaxation),
# and without it, at 5K.
record $RESULTS/contact/tracking_5k_np1_relaxation.jsonl $PYTHON benchmarks/contact_tracking.py --tets 5000 \
  --frames 5 --variants no-contact contact+relaxation contact
record $RESULTS/contact/tracking_404k_np2_relaxation_patch_matrix.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --frames 4 --variants no-contact contact+relaxation --max-seconds 2400 \
  --abort-seconds 5400
# ... with the head moving: Newton's factor judged by the residual's energy norm (fit --fast) and by its
# norm alone; how far the energy stop leaves the equilibrium.
record $RESULTS/contact/energy_judged_ablation_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --frames 4 --variants no-contact contact contact+residual-refresh \
  --max-seconds 2400 --abort-seconds 4000
record $RESULTS/contact/energy_judged_20k_np1.jsonl $PYTHON benchmarks/contact_tracking.py --tets 20000 \
  --head-motion --start 5 --frames 20 --variants no-contact contact contact+residual-refresh
$PYTHON benchmarks/energy_stop_accuracy.py --tets 20000 --out $RESULTS/contact/energy_stop_accuracy_20k.json
# ... and the factor refreshed only after a cut slower than 0.75 instead of 0.5.
record $RESULTS/contact/slow_refresh_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --frames 4 --variants no-contact contact contact+slow-refresh \
  --max-seconds 2400 --abort-seconds 4000
# ... and the lips' barrier at 100 kPa instead of 10.
record $RESULTS/contact/stiff_lips_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --frames 4 --variants no-contact contact contact+stiff-lips \
  --max-seconds 2400 --abort-seconds 3600
# The tangent's room for the lips (docs/contact.md, "The tangent's pattern"): the lips' slide over the
# bilabial take, the factor of each pattern, and the tracking with every lip pair within 15 mm.
$PYTHON benchmarks/lip_slide.py --tets 5000 --out $RESULTS/contact/lip_slide_5k.json
$PYTHON benchmarks/lip_slide.py --tets 20000 --out $RESULTS/contact/lip_slide_20k.json
$PYTHON benchmarks/lip_pattern.py --tets 5000 --radii 0 3 --every-pair-within 15 --out $RESULTS/contact/lip_pattern_5k.json
mpirun -n 2 $PYTHON benchmarks/lip_pattern.py --tets 400000 --radii --every-pair-within 15 --no-closure \
  --out $RESULTS/contact/lip_pattern_factor_404k_np2.json
record $RESULTS/contact/lip_pattern_tracking_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --frames 4 --variants no-contact contact contact+wide-pattern \
  --max-seconds 2400 --abort-seconds 4000
record $RESULTS/contact/lip_pattern_tracking_swapped_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --frames 4 --variants no-contact contact+wide-pattern contact \
  --max-seconds 2400 --abort-seconds 4000
# Newton's tangent with the lips' barrier of wider reach (LipContactSettings.newton_reach, the default)
# and without it.
record $RESULTS/contact/newton_reach_default_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --frames 4 --variants no-contact contact contact+narrow-newton-lips \
  --max-seconds 2400 --abort-seconds 4000
record $RESULTS/contact/newton_reach_default_20k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 20000 --head-motion --frames 30 --variants no-contact contact contact+narrow-newton-lips
record $RESULTS/contact/newton_reach_default_5k_np1.jsonl $PYTHON benchmarks/contact_tracking.py \
  --tets 5000 --head-motion --frames 30 --variants no-contact contact contact+narrow-newton-lips
# (push_out_through_lips_5k_np1 is the same 5K command at the commit in its manifest entry, which
# solved from starts whose lips the push-out of the lining had taken through each other.)
# The IPC Toolkit on one thread per MPI rank (face_dolfinx.physics.contact).
record $RESULTS/contact/ipc_one_thread_20k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 20000 --head-motion --frames 30 --variants no-contact contact contact+narrow-newton-lips
record $RESULTS/contact/ipc_one_thread_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --frames 4 --variants no-contact contact \
  --max-seconds 2400 --abort-seconds 4000
# A prediction cut short around a few flattened cells only (FaceProblem.bound_prediction_locally);
# local_prediction_404k_np2_rerun is the same command with --variants no-contact contact.
record $RESULTS/contact/local_prediction_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --frames 4 --variants no-contact contact contact+cut-whole \
  --max-seconds 2400 --abort-seconds 4000
record $RESULTS/contact/local_prediction_20k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 20000 --head-motion --frames 30 --variants no-contact contact contact+cut-whole
# Approximate Jacobians from a factor within 1 mm (fit --fast); then a 30-frame stretch (lips closing,
# opening, the vowel, the second closure).
record $RESULTS/contact/approximate_within_1mm_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --frames 6 --max-seconds 2400 --abort-seconds 4000
record $RESULTS/contact/stretch_30_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --frames 30 --max-seconds 2700 --abort-seconds 5600
record $RESULTS/contact/interleaved_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --frames 6 --interleave --max-seconds 1200 --abort-seconds 1260
# An old factor refreshed after a correction the collision-free bound cut below 0.2 of its length
# (FactorReusePolicy.judged_step_bound), against the variant without (contact+judged-cuts);
# judged_cuts_404k_np2_rerun is the same command with --variants no-contact contact --max-seconds 1200
# --abort-seconds 1500; then frames 5-14 (the closure and the lips' opening).
record $RESULTS/contact/judged_cuts_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --frames 6 --variants no-contact contact contact+judged-cuts \
  --interleave --max-seconds 1500 --abort-seconds 1800
record $RESULTS/contact/judged_cuts_opening_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --frames 10 --variants no-contact contact \
  --interleave --max-seconds 1800 --abort-seconds 2400
record $RESULTS/contact/judged_cuts_20k_np1.jsonl $PYTHON benchmarks/contact_tracking.py \
  --tets 20000 --head-motion --start 5 --frames 20 --variants no-contact contact contact+judged-cuts --interleave
# A fresh approximate Jacobian from a factor of Newton's tangent (FitSettings.fresh_jacobian_from_newton_tangent),
# against the exact tangent's (contact+exact-fresh-jacobians), frames 5-14; newton_jacobians_404k_np2_rerun is
# the same command with --frames 8 --variants no-contact contact --max-seconds 1200 --abort-seconds 1800.
record $RESULTS/contact/newton_jacobians_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --frames 10 --variants no-contact contact contact+exact-fresh-jacobians \
  --interleave --max-seconds 1500 --abort-seconds 3000
# ... and from the open vowel (frame 15, from rest) through the lips' second closure.
record $RESULTS/contact/newton_jacobians_open_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --start 15 --frames 10 --variants no-contact contact \
  --interleave --max-seconds 1500 --abort-seconds 2400
# The same stretch with the lip nodes the teeth overrun moved out before the carry (ContactPotential.carry),
# and the synthetic take's truth with the head moving, solved frame by frame, at 5K and 20K.
record $RESULTS/contact/kept_clear_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --frames 10 --variants no-contact contact \
  --interleave --max-seconds 1500 --abort-seconds 3000
record $RESULTS/contact/kept_clear_open_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --start 15 --frames 10 --variants no-contact contact \
  --interleave --max-seconds 1500 --abort-seconds 2400
for tets in 5000 20000; do
  $PYTHON benchmarks/pressed_lips_newton.py --tets $tets --start 0 --frames 30 --head-motion --variants refuse \
    --out $RESULTS/contact/kept_clear_truth_$((tets / 1000))k_np1.json
done
# The open stretch with the teeth's projection of a prediction's lining judged by true gaps (ContactPotential.projected_end).
record $RESULTS/contact/projection_gaps_open_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --start 15 --frames 10 --variants no-contact contact \
  --interleave --max-seconds 1500 --abort-seconds 3000
# Both stretches with Newton's flesh tangent made definite cell by cell (FaceProblem(definite_tangent=...)).
for stretch in 5: 15:_open; do
  record $RESULTS/contact/definite_tangent${stretch#*:}_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
    --tets 400000 --truth-tets 20000 --head-motion --start ${stretch%%:*} --frames 10 --variants no-contact contact \
    --interleave --max-seconds 1500 --abort-seconds 3000
done
# The lips' opening traced (which term cut each correction; the residual on the contact nodes), then with
# the contact nodes relaxed once Newton crawls on them (QuasistaticSolver(contact_relaxation=None)).
record $RESULTS/contact/opening_trace_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --start 5 --frames 10 --variants contact \
  --max-seconds 1500 --abort-seconds 3000 -v --trace-newton 2> $RESULTS/contact/opening_trace_404k_np2.log
# The same commands at the commits of their manifest entries: the crawl's relaxation, then also the slow
# fall's (relax_on_slow_fall), then a push of the lining through the other lip pushing that lip along
# (LipContact.pushed_along) and its rerun, then a push-out that would flatten cells lifted into the
# flesh (ContactPotential.move_to), the prediction's lining projection judged from the cut prediction,
# and a guard-cut fresh factor kept once in lifting solves, and also in the main solve from a cut prediction;
# then the code of lifting_factor_kept on a face built on another machine (rebuilt_mesh: 404124 tets), and
# on that face the teeth's barrier blocks exact near the solution with a converging phase finishing past the
# iteration limit (exact_teeth_blocks); later the built-in face from the C library's sin, cos, exp and power
# on a CPU with AVX-512 (avx512_machine), contact's checks over the nodes that move (moved_nodes_only), a
# guard's cut counted only where the guard cut a step shorter than the bounds (guard_cuts_only), and a bounded
# step judged by the fraction of its correction the line search took (taken_steps).
for name in crawl_relaxation_404k_np2 slow_fall_relaxation_404k_np2; do
  record $RESULTS/contact/$name.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
    --tets 400000 --truth-tets 20000 --head-motion --start 5 --frames 10 --variants no-contact contact \
    --interleave --max-seconds 1500 --abort-seconds 3000 -v --trace-newton 2> $RESULTS/contact/$name.log
done
for name in crawl_relaxation_open_404k_np2 slow_fall_relaxation_open_404k_np2 lips_pushed_along_open_404k_np2 \
    lips_pushed_along_open_404k_np2_rerun lifted_push_out_open_404k_np2 projection_from_cut_open_404k_np2 \
    lifting_factor_kept_open_404k_np2 cut_prediction_lifting_open_404k_np2 rebuilt_mesh_open_404k_np2 \
    exact_teeth_blocks_open_404k_np2 avx512_machine_open_404k_np2 moved_nodes_only_open_404k_np2 \
    moved_nodes_only_open_404k_np2_rerun guard_cuts_only_open_404k_np2 taken_steps_open_404k_np2 \
    taken_steps_open_404k_np2_rerun; do
  record $RESULTS/contact/$name.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
    --tets 400000 --truth-tets 20000 --head-motion --start 15 --frames 10 --variants no-contact contact \
    --interleave --max-seconds 1500 --abort-seconds 3000 -v 2> $RESULTS/contact/$name.log
done
# At the commits of their manifest entries, whose contact_tracking.py had the variant contact+lips-cut-whole:
# the lips of a prediction held back alone against the prediction cut as a whole at the lips' bound, on
# both stretches, and with the lining's projection spread to the flesh around it in both variants
# (lining_spread_open_404k_np2).
for name in lips_held_404k_np2:5 lips_held_open_404k_np2:15 lining_spread_open_404k_np2:15; do
  record $RESULTS/contact/${name%:*}.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
    --tets 400000 --truth-tets 20000 --head-motion --start ${name#*:} --frames 10 \
    --variants no-contact contact contact+lips-cut-whole --interleave --max-seconds 1500 --abort-seconds 4000 \
    -v 2> $RESULTS/contact/${name%:*}.log
done
# At the commit of its manifest entry, whose contact_tracking.py had the variant contact+whole-steps (a
# Gauss-Newton step shortened where contact cuts its prediction, in the variant contact, against every step whole):
record $RESULTS/contact/shortened_steps_open_404k_np2.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
  --tets 400000 --truth-tets 20000 --head-motion --start 15 --frames 10 \
  --variants no-contact contact contact+whole-steps --interleave --max-seconds 1500 --abort-seconds 3600 \
  -v 2> $RESULTS/contact/shortened_steps_open_404k_np2.log
# An old factor refreshed where bounded steps crawl (contact) against the factor kept (contact+crawl-kept),
# over the open stretch (from frame 15) and the lips' first closure and opening (from frame 5).
for name in crawl_refresh_open_404k_np2:15 crawl_refresh_open_404k_np2_rerun:15 crawl_refresh_404k_np2:5 \
    crawl_refresh_404k_np2_rerun:5; do
  record $RESULTS/contact/${name%:*}.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
    --tets 400000 --truth-tets 20000 --head-motion --start ${name#*:} --frames 10 \
    --variants no-contact contact contact+crawl-kept --interleave --max-seconds 1500 --abort-seconds 3600 \
    -v 2> $RESULTS/contact/${name%:*}.log
done
# The lips' slow fall relaxing the contact nodes and their wider barrier without parting pairs (contact)
# against neither (contact+teeth-slow-fall+parting-reach), over the same two stretches.
for name in lips_slow_fall_404k_np2:5 lips_slow_fall_404k_np2_rerun:5 lips_slow_fall_open_404k_np2:15 \
    lips_slow_fall_open_404k_np2_rerun:15; do
  record $RESULTS/contact/${name%:*}.jsonl mpirun -n 2 $PYTHON benchmarks/contact_tracking.py \
    --tets 400000 --truth-tets 20000 --head-motion --start ${name#*:} --frames 10 \
    --variants no-contact contact contact+teeth-slow-fall+parting-reach --interleave --max-seconds 1500 \
    --abort-seconds 3600 -v 2> $RESULTS/contact/${name%:*}.log
done

# Tracking: fit --fast against the naive loop at the paper's scale, and the solver variants at 50K.
record $RESULTS/tracking/tracking_404k_np2_fast_naive.jsonl \
  mpirun -n 2 $PYTHON benchmarks/tracking_speed.py --tets 400000 --frames 2 --variants fast naive
record $RESULTS/tracking/tracking_50k_np2_naive_fresh_reuse1j.jsonl \
  mpirun -n 2 $PYTHON benchmarks/tracking_speed.py --tets 50000 --frames 4 --variants naive fresh reuse-1j
# A whole take in three layouts (1 rank, 2 ranks, 2 chunks).
record $RESULTS/ranks_and_chunks/ranks_and_chunks_20k_120frames_reuse1j.jsonl \
  $PYTHON benchmarks/ranks_and_chunks.py --tets 20000 --frames 120 \
  --fit-options="--reuse-factorization --fresh-jacobians 1"
record $RESULTS/ranks_and_chunks/ranks_and_chunks_404k_16frames_fast-ls3.jsonl \
  $PYTHON benchmarks/ranks_and_chunks.py --tets 400000 --frames 16 --take-frames 240 --first-frame 80 \
  --fit-options=--fast
# The fastest speech stretch (frames 114-125) of two takes at 400K, fit --fast with one and with three
# line-search iterations: each fit's per-frame seconds (timings.csv) and errors (frames.csv).
for seed in 0 3; do
  take=runs/speech114_seed$seed.trc
  mpirun -n 2 $PYTHON run.py synth --tets 400000 --frames 12 --take-frames 240 --first-frame 114 --noise 0.5 \
    --seed $seed --out $take --overwrite
  for iterations in 1 3; do
    fit="mpirun -n 2 $PYTHON run.py fit $take --tets 400000 --fast --line-search-iterations $iterations"
    $fit --out runs/speech114_seed${seed}_ls$iterations --overwrite
    name=$RESULTS/tracking/stretch_404k_np2_speech114_seed${seed}_ls$iterations
    cp runs/speech114_seed${seed}_ls$iterations/timings.csv ${name}_timings.csv
    cp runs/speech114_seed${seed}_ls$iterations/frames.csv ${name}_frames.csv
    $PYTHON benchmarks/provenance.py record ${name}_timings.csv ${name}_frames.csv --command "$fit"
  done
done

# Retargeted forward frames on a subject adapted from the 20K face, played as simulate --animation plays them.
mpirun -n 2 $PYTHON benchmarks/retarget_speed.py --tets 20000 --frames 20 --work runs/retarget_speed \
  --out $RESULTS/retarget/retarget_20k_np2_idle.jsonl

# Where methods fail, one file per study (each run records itself in the manifest).
declare -A STABILITY=([forward]=forward_5k-20k [ramp]=ramp_1k-20k [remote]=remote_5k [head]=head_5k [damage]=damage_5k)
for study in forward ramp remote head damage; do
  out=$RESULTS/stability/${STABILITY[$study]}.jsonl
  $PYTHON benchmarks/provenance.py start $out
  $PYTHON benchmarks/stability.py --studies $study --out $out
done
$PYTHON benchmarks/stability.py --collect $RESULTS/stability/{forward_5k-20k,ramp_1k-20k,remote_5k,head_5k,damage_5k}.jsonl \
  --plot docs/img/stability > runs/stability_tables.md
# Warm-started frames of an edited animation played back (docs/animation.md).
mpirun -n 2 $PYTHON benchmarks/edit_speed.py --tets 20000 --out $RESULTS/edit/edit_20k_np2_idle.jsonl
# The model ladder (writes its own tables and figures).
benchmarks/run_ladder.sh
# Dynamic against quasistatic re-simulation (docs/dynamics.md): 5K and 20K faces, substeps of 1/240, 1/60 and 1/960 s.
$PYTHON benchmarks/dynamics.py --tets 5000 --out $RESULTS/dynamics/dynamics_5k.jsonl --plot docs/img/dynamics_5k.png
$PYTHON benchmarks/dynamics.py --tets 5000 --time-step 0.016666666666666666 \
  --out $RESULTS/dynamics/dynamics_5k_step60hz.jsonl
$PYTHON benchmarks/dynamics.py --tets 5000 --motions expression --tissues soft --time-step 0.0010416666666666667 \
  --out $RESULTS/dynamics/dynamics_5k_soft_expression_step960hz.jsonl
$PYTHON benchmarks/dynamics.py --tets 20000 --motions expression shake --tissues model \
  --out $RESULTS/dynamics/dynamics_20k.jsonl --plot docs/img/dynamics_20k.png
$PYTHON benchmarks/dynamics.py --tets 20000 --motions expression shake --tissues model --time-step 0.016666666666666666 \
  --out $RESULTS/dynamics/dynamics_20k_step60hz.jsonl
