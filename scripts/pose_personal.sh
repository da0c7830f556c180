#!/usr/bin/env bash
# The personal-mocap figures of docs/pose.md ("A person's first takes, then their later ones"): two held-out people of
# the data directory split by takes into folders of links to its files, the six-sensor networks fine-tuned on their
# first takes (data.own, train.init_from_onnx), and every model scored on their later takes. Nothing is shipped to
# onnx_models/: the files go to $WORK/models. About 35 minutes on two cores.
set -euo pipefail
cd "$(dirname "$0")/.."
. .venv/bin/activate
: "${WEARMOCAP_DATA_DIR:?set WEARMOCAP_DATA_DIR to the data folder (the one with index.csv)}"
WORK=${1:-/tmp/pose_personal}
ICLONE="$WEARMOCAP_DATA_DIR/mocap/cmu_iclone"
rm -rf "$WORK/own_cmu" "$WORK/own_one"

takes() {  # takes FOLDER CLIP...: links to the iClone clips in FOLDER
  mkdir -p "$1"
  local folder=$1
  shift
  for clip in "$@"; do ln -s "$(ls "$ICLONE/$clip".bvh* | head -1)" "$folder/"; done
}
# CMU 07's walks and CMU 06's basketball (07_01 left out: the data directory excludes it, its pelvis height is constant)
for set in own_cmu own_one; do
  takes "$WORK/$set/cmu07_val/walk" 07_07 07_08
  takes "$WORK/$set/cmu07_test/walk" 07_09 07_10 07_11 07_12
  takes "$WORK/$set/cmu06_val/basketball" 06_08 06_09
  takes "$WORK/$set/cmu06_test/basketball" 06_10 06_11 06_12 06_14 06_15
done
takes "$WORK/own_cmu/cmu07/walk" 07_02 07_03 07_04 07_05 07_06
takes "$WORK/own_cmu/cmu06/basketball" 06_02 06_03 06_04 06_05 06_06 06_07
takes "$WORK/own_one/cmu07/walk" 07_02  # one take each
takes "$WORK/own_one/cmu06/basketball" 06_02

python -m training.cli restore-model pose_full6 4.0.0 --models-dir "$WORK/models"  # one network of the served 4.1.0
FINE_TUNE=(-s train.lr=0.0003 -s train.lr_schedule=constant -s train.max_epochs=8 -s train.patience=3)
SPLIT=(-s "data.own.val_people=[cmu07_val,cmu06_val]" -s "data.own.test_people=[cmu07_test,cmu06_test]")
OWN_CMU=(-s "data.own.path=$WORK/own_cmu" "${SPLIT[@]}")
OWN_ONE=(-s "data.own.path=$WORK/own_one" "${SPLIT[@]}")
ship=(--ship --version 0.1.0 --models-dir "$WORK/models")
python -m training.cli pose-train training/configs/pose_full6.yaml -s name=pose_full6_own_cmu "${OWN_CMU[@]}" \
  -s train.init_from_onnx="$WORK/models/pose_full6/4.0.0" "${FINE_TUNE[@]}" "${ship[@]}"
python -m training.cli pose-train training/configs/pose_full6.yaml -s name=pose_full6_own_one_take "${OWN_ONE[@]}" \
  -s train.init_from_onnx="$WORK/models/pose_full6/4.0.0" "${FINE_TUNE[@]}" "${ship[@]}"
# the control: the same epochs on the data directory alone
python -m training.cli pose-train training/configs/pose_full6.yaml -s name=pose_full6_more_epochs \
  -s train.init_from_onnx="$WORK/models/pose_full6/4.0.0" "${FINE_TUNE[@]}" "${ship[@]}"
python -m training.cli pose-train training/configs/pose_full6_stream.yaml -s name=pose_full6_stream_own_cmu \
  "${OWN_CMU[@]}" -s train.init_from_onnx=onnx_models/pose_full6_stream/4.0.0 "${FINE_TUNE[@]}" "${ship[@]}"

for model in "$WORK/models/pose_full6/4.0.0" "$WORK/models/pose_full6_own_cmu/0.1.0" \
  "$WORK/models/pose_full6_own_one_take/0.1.0" onnx_models/pose_full6_stream/4.0.0 \
  "$WORK/models/pose_full6_stream_own_cmu/0.1.0"; do
  echo "== $model"
  python -m training.cli evaluate-pose "$WORK/own_cmu/cmu07_test" "$WORK/own_cmu/cmu06_test" --model "$model" |
    grep "^activity\|^overall"
done
