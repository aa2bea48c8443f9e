#!/bin/bash
# The real-capture measurements of docs/accuracy.md ("The AnimFace take from its typical frame"),
# one after the other: subject models built on the take's most typical frame, the whole take fitted
# on them, what the controls and the markers allow, and the studies of settings and controls on every
# 8th frame. The capture is not in this repository (AnimFace, CC BY-SA 4.0): give its path.
# Results go to benchmarks/results/real_capture/ under the names the docs cite, each run recorded
# in the manifest (benchmarks/provenance.py); models and fit folders go to runs/. About 1 hour on
# the 2-core machine.
#   benchmarks/run_real_capture.sh PATH/NoseMoCap_cm.csv
set -eu
CAPTURE=$(realpath "$1")
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-.venv/bin/python}
RESULTS=benchmarks/results/real_capture
CORRESPONDENCE=benchmarks/real_capture/animface_correspondence.toml
SETUP=benchmarks/real_capture/animface_markers.toml
export OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1
mkdir -p runs

for tets in 5000 20000; do
  $PYTHON run.py build --subject "$CAPTURE" --units cm --correspondence $CORRESPONDENCE --tets $tets \
    --neutral-frame typical --out runs/animface_${tets} --overwrite
done
for name in real_capture_5k_adapted_typical_neutral control_span_5k_adapted_typical_neutral \
            real_capture_20k_adapted_typical_neutral_np2_every8th; do
  $PYTHON benchmarks/provenance.py start $RESULTS/$name.jsonl
done
fit="benchmarks/real_capture.py $CAPTURE --correspondence $CORRESPONDENCE --marker-setup $SETUP --neutral-frame typical --overwrite"
$PYTHON $fit --model runs/animface_5000 --out runs/animface_5k_fit \
  --results $RESULTS/real_capture_5k_adapted_typical_neutral.jsonl
$PYTHON benchmarks/control_span.py runs/animface_5k_fit --units cm --pressure \
  --results $RESULTS/control_span_5k_adapted_typical_neutral.jsonl
mpirun -n 2 $PYTHON $fit --model runs/animface_20000 --out runs/animface_20k_fit --frames 0:962:8 \
  --results $RESULTS/real_capture_20k_adapted_typical_neutral_np2_every8th.jsonl

# Settings and controls, every 8th frame of the take.
studies=$RESULTS/studies_5k_adapted_typical_neutral_every8th.jsonl
$PYTHON benchmarks/provenance.py start $studies
every8th="$fit --model runs/animface_5000 --frames 0:962:8 --results $studies"
$PYTHON $every8th --out runs/animface_study_default
for effort in 10 30 100; do
  $PYTHON $every8th --out runs/animface_study_effort$effort --effort $effort
done
$PYTHON $every8th --out runs/animface_study_pressure --intraoral-pressure
sed 's/^eyelids = 0$/eyelids = 0\neye_corners = 0/' $SETUP > runs/animface_markers_eye_corners_out.toml
$PYTHON benchmarks/real_capture.py "$CAPTURE" --correspondence $CORRESPONDENCE --neutral-frame typical --overwrite \
  --model runs/animface_5000 --frames 0:962:8 --results $studies \
  --marker-setup runs/animface_markers_eye_corners_out.toml --out runs/animface_study_eye_corners_out
