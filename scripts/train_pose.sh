#!/usr/bin/env bash
# Trains and ships the served pose models, then the comparison runs (MLflow only), one after the other on the CPU.
# Wall times on 2 cores are the configs' time budgets plus about a minute each (docs/pose.md has the results).
set -euo pipefail
cd "$(dirname "$0")/.."
. .venv/bin/activate
: "${WEARMOCAP_DATA_DIR:?set WEARMOCAP_DATA_DIR to the data folder (the one with index.csv)}"
for name in pose_full6 pose_full6_stream pose_lower3 pose_lower3_stream; do
  python -m training.cli pose-train "training/configs/$name.yaml" --ship --version "${POSE_VERSION:-1.0.0}"
done
# Comparisons (not shipped), each for at most the epochs its reference ran (13 for pose_lower3, 18 for pose_full6)
# and no time budget, so that a slower or busier machine compares the same training: axis-angle against 6D at the
# lower-body size; Vlutters 2016's FFNN against the Bi-LSTM of Zheng et al. 2021 with six sensors (its unidirectional LSTM is
# pose_full6_stream, which sees 5 frames ahead).
python -m training.cli pose-train training/configs/pose_lower3.yaml -s name=pose_lower3_axisangle \
  -s model.representation=axis_angle -s train.max_epochs=13 -s train.time_budget_s=1e9
python -m training.cli pose-train training/configs/pose_full6.yaml -s name=pose_full6_ffn -s model.kind=ffn \
  -s train.max_epochs=18 -s train.time_budget_s=1e9
