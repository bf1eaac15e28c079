#!/usr/bin/env bash
# Reproduces the bundled default model (d3lvo_deploy/default_model) and its rgb-only ablation.
# Data: synthetic sequences from `d3lvo synth`, motion replayed from the real KITTI GT 00-08
# (training) and 09-10 (held-out validation, other seeds). Takes about 55 min on 2 CPU cores
# (data 10 min, default model 25 min, rgb ablation 15 min); sequences already in $OUT/data are reused.
#   GT=path/to/kitti_gt_poses OUT=runs/default STEPS=1000 bash scripts/train_default.sh
set -euo pipefail
cd "$(dirname "$0")/.."
GT=${GT:-../shared/data/kitti_gt_poses}
OUT=${OUT:-runs/default}
STEPS=${STEPS:-1000}
FRAMES=${FRAMES:-200}
SIZE=${SIZE:-620x188}
D3LVO=${D3LVO:-.venv/bin/d3lvo}

train=()
i=0
for s in 00 01 02 03 04 05 06 07 08; do
  n=$(wc -l < "$GT/$s.txt")
  start=$((50 + 37 * i))
  [ $((start + FRAMES)) -le "$n" ] || start=$((n - FRAMES))
  [ -f "$OUT/data/train_$s/poses.txt" ] || "$D3LVO" synth --out "$OUT/data/train_$s" --frames "$FRAMES" \
    --seed $((10 + i)) --size "$SIZE" --motion-from "$GT/$s.txt" --motion-start "$start"
  train+=(--data "$OUT/data/train_$s")
  i=$((i + 1))
done
for s in 09 10; do
  [ -f "$OUT/data/heldout_$s/poses.txt" ] || "$D3LVO" synth --out "$OUT/data/heldout_$s" --frames "$FRAMES" \
    --seed $((100 + 10#$s)) --size "$SIZE" --motion-from "$GT/$s.txt" --motion-start 0
done
val=(--val "$OUT/data/heldout_09")

"$D3LVO" train "${train[@]}" "${val[@]}" --out "$OUT/default.pt" --steps "$STEPS" --preset small \
  --batch-size 4 --lr 5e-4 --val-every 250 --ckpt-every 50 --seed 0 --workers 1
# ship the weights that scored best on the validation sequence (heldout_09; heldout_10 stays unseen),
# weights + config only (no optimizer state), and export from exactly that file
.venv/bin/python -c "from models.checkpoint import slim_checkpoint; slim_checkpoint('$OUT/default.best.pt', 'd3lvo_deploy/default_model/default.pt')"
"$D3LVO" export --ckpt d3lvo_deploy/default_model/default.pt --out d3lvo_deploy/default_model

if [ "${ABLATION:-1}" = 1 ]; then
  "$D3LVO" train "${train[@]}" "${val[@]}" --out "$OUT/rgb.pt" --steps "$STEPS" --preset small --mode rgb \
    --batch-size 4 --lr 5e-4 --val-every 250 --ckpt-every 50 --seed 0 --workers 1
  "$D3LVO" export --ckpt "$OUT/rgb.best.pt" --out "$OUT/rgb_onnx"
fi
