#!/usr/bin/env bash
# Reproduces the bundled default model (d3lvo_deploy/default_model), the paper's MLP pose head
# on the same data (the head comparison in docs/evaluation.md), the rgb ablation, and their
# evaluation beside the no-learning direct tracker on the held-out drives.
# Data: synthetic sequences from `d3lvo synth`, motion replayed from the real KITTI GT 00-08
# (training) and 09-10 (held-out, other seeds). On 2 CPU cores: data ~16 min, then the trainings
# below side by side, ~100 min in all; sequences already in $OUT/data are reused.
# A run cut short resumes: RESUME=1 continues the trainings from their last checkpoints.
#   GT=path/to/kitti_gt_poses OUT=runs/default bash scripts/train_default.sh
set -euo pipefail
cd "$(dirname "$0")/.."
GT=${GT:-../shared/data/kitti_gt_poses}
OUT=${OUT:-runs/default}
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
common=(--preset small --batch-size 4 --lr 5e-4 --ckpt-every 50 --seed 0 --workers 0)
resume() { [ "${RESUME:-0}" = 1 ] && [ -f "$1" ] && echo --resume "$1" || true; }

# Side by side, as they were run for the bundled model (the budgets differ; the comparison
# favours the MLP head, which has more steps than the default's first 1,000):
# - the paper's MLP head, 1,600 steps validated every 400, then the rgb ablation (no depth, so
#   the MLP head), 1,500 steps validated every 300, one thread each (the rgb run that produced
#   the figures in docs/evaluation.md was stopped at step 1,050 to give the default's training
#   both cores; its best validated step was 600);
# - the default, the Gauss-Newton head with the solver on LiDAR cells, 1,000 steps validated
#   every 250, two threads.
( export OMP_NUM_THREADS=1
  "$D3LVO" train "${train[@]}" "${val[@]}" --out "$OUT/mlp.pt" --pose-head mlp "${common[@]}" --steps 1600 \
    --val-every 400 $(resume "$OUT/mlp.pt")
  "$D3LVO" train "${train[@]}" "${val[@]}" --out "$OUT/rgb.pt" --mode rgb "${common[@]}" --steps 1500 \
    --val-every 300 $(resume "$OUT/rgb.pt") ) &
OMP_NUM_THREADS=2 "$D3LVO" train "${train[@]}" "${val[@]}" --out "$OUT/default.pt" "${common[@]}" --steps 1000 \
  --val-every 250 --set gn_lidar_pool=stride $(resume "$OUT/default.pt") &
wait

# The default then continues from step 1,000 on a schedule of 2,500 steps, validated every 300.
# Steps 1,000-2,050 keep the solver's LiDAR cells on the cell pixel (gn_lidar_pool=stride); the
# step-1,800 weights score better on 09-motion with the closest return within half a cell
# (gn_lidar_pool=nearest, docs/model-card.md), so steps 2,050-2,500 train with that, which is what
# ships. Two threads, nothing else running: ~1 s per step. checkpoints/default_step2500.pt is the
# full training state at step 2,500, to continue from.
if [ ! -f "$OUT/default.pt" ] || [ "$(.venv/bin/python -c "import torch; print(torch.load('$OUT/default.pt', weights_only=False)['step'])")" -lt 2050 ]; then
  OMP_NUM_THREADS=2 "$D3LVO" train "${train[@]}" "${val[@]}" --out "$OUT/default.pt" "${common[@]}" --steps 2500 \
    --stop-at 2050 --val-every 300 --set gn_lidar_pool=stride --resume "$OUT/default.pt"
fi
OMP_NUM_THREADS=2 "$D3LVO" train "${train[@]}" "${val[@]}" --out "$OUT/default.pt" "${common[@]}" --steps 2500 \
  --val-every 300 --set gn_lidar_pool=nearest --resume "$OUT/default.pt"

# ship the weights that scored best on the validation sequence (heldout_09; heldout_10 stays unseen),
# weights + config only (no optimizer state), and export from exactly that file
.venv/bin/python -c "from models.checkpoint import slim_checkpoint; slim_checkpoint('$OUT/default.best.pt', 'd3lvo_deploy/default_model/default.pt')"
"$D3LVO" export --ckpt d3lvo_deploy/default_model/default.pt --out d3lvo_deploy/default_model
"$D3LVO" export --ckpt "$OUT/mlp.best.pt" --out "$OUT/mlp_onnx"
"$D3LVO" export --ckpt "$OUT/rgb.best.pt" --out "$OUT/rgb_onnx"

# the held-out table of docs/evaluation.md: network, MLP head, rgb ablation and the direct tracker,
# through `d3lvo run` (which scores each run against the poses.txt beside the sequence)
for s in 09 10; do
  "$D3LVO" run --seq-dir "$OUT/data/heldout_$s" --out "$OUT/eval/default_$s.txt"
  "$D3LVO" run --seq-dir "$OUT/data/heldout_$s" --onnx "$OUT/mlp_onnx" --out "$OUT/eval/mlp_$s.txt"
  "$D3LVO" run --seq-dir "$OUT/data/heldout_$s" --onnx "$OUT/rgb_onnx" --out "$OUT/eval/rgb_$s.txt"
  "$D3LVO" run --seq-dir "$OUT/data/heldout_$s" --method direct --out "$OUT/eval/direct_$s.txt"
done
