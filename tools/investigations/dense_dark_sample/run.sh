#!/bin/bash
# Every run behind README.md's figures, in the order they were made (about 2.5 h of one core at the priority
# below; the renders dominate). Output: $DENSE_DIR (default out/dense-dark-sample). Then: python final.py.
set -euo pipefail
cd "$(dirname "$0")/../../.."
export PYTHONPATH=host DENSE_DIR=${DENSE_DIR:-out/dense-dark-sample}
mkdir -p "$DENSE_DIR"
here=tools/investigations/dense_dark_sample
R="taskset -c ${CORE:-1} nice -n 10 .venv/bin/python"
D=$DENSE_DIR
dense="0.72283 36.6378 0.0254"   # α, σt [1/mm], g: the check's exact material (device, n 1.5, ℓ 0.4 mm)
control="0.9 5.0 0.0254"
M=8388608
# the shift series (same seeds at every shift) and the tracer
$R $here/series.py $D/series_dense_b.json $dense 0.02 $M 101,102,103,104,105,106,107,108 0,2.5,5,10,20,40
$R $here/tracer.py $D/tracer_dense.json $dense $M 201,202,203,204
# the near-zero-offset scene (zero_eps.py's variants S:dz:spot) beside the shipped one, same seeds
$R $here/zero_eps.py $D/zero_dense.json $dense 0.02 $M 101,102,103,104,105,106,107,108 \
  "1:0:0;1000:-0.55:0.02;1000:-0.55:0;1:0:0.02"
$R $here/tracer_spot.py $D/tracer_dense_spot.json $dense $M 301,302 0.02
# the control sample
$R $here/tracer.py $D/tracer_ctrl.json $control 4194304 211,212,213,214
$R $here/series.py $D/series_ctrl.json $control 0.02 $M 111,112,113,114 0,5,10,20,40
$R $here/zero_eps.py $D/zero_ctrl.json $control 0.02 $M 111,112,113,114 "1000:-0.55:0.02"
# more seeds of each
$R $here/zero_eps.py $D/zero_dense2.json $dense 0.02 $M 101,102,103,104,105,106,107,108 "1000:-0.55:0.02;1000:-0.55:0"
$R $here/tracer.py $D/tracer_dense2.json $dense $M 205,206,207,208,209,210,211,212
$R $here/zero_eps.py $D/zero_dense3.json $dense 0.02 $M "$(seq -s, 121 144)" "1000:-0.55:0.02;1:0:0"
$R $here/zero_eps.py $D/zero_dense4.json $dense 0.02 $M "$(seq -s, 145 224)" "1000:-0.55:0.02"
$R $here/tracer.py $D/tracer_dense3.json $dense $M 221,222,223,224,225,226,227,228
# the independent float64 Monte Carlo, the white reference, ρ 0.9
$R $here/indep.py $D/indep_dense.json $dense 2000000 16 11
$R $here/indep.py $D/indep_dense2.json $dense 2000000 16 12
$R $here/white.py
$R $here/zero_eps.py $D/zero_dense_rho09.json $dense 0.9 $M 145,146 "1000:-0.55:0.02"
# the figures
$R $here/analyse.py $D/series_dense_b.json $D/tracer_dense.json
$R $here/analyse.py $D/series_ctrl.json $D/tracer_ctrl.json
$R $here/analyse_zero.py $D/zero_dense.json -- $D/tracer_dense.json
$R $here/analyse_zero.py $D/zero_dense3.json -- $D/tracer_dense.json
$R $here/final.py
