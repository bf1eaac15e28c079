#!/usr/bin/env bash
# Reproduces the bundled default model (d3lvo_deploy/default_model): first the network with the
# Gauss-Newton solver on its cells (whose encoder, completion and flow the bundled model starts
# from), the paper's MLP pose head on the same data and the rgb ablation; then the bundled point
# head on drives with traffic; then the evaluation beside the no-learning direct tracker.
# Data: synthetic sequences from `d3lvo synth`, motion replayed from the real KITTI GT 00-08
# (training) and 09-10 (held-out, other seeds). On 2 CPU cores: data ~16 min, then the trainings
# below side by side, ~100 min in all, then ~40 min for the bundled point head's three trainings;
# sequences already in $OUT/data are reused; then ~70 min for its confidence net's two trainings.
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
# a training that starts from other weights: --init those, or --resume its own checkpoint with RESUME=1
init_or_resume() { [ "${RESUME:-0}" = 1 ] && [ -f "$2" ] && echo --resume "$2" || echo --init "$1"; }

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

# The cell-solver network then continues from step 1,000 on a schedule of 2,500 steps, validated every 300.
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

# The bundled model: the point pose head (the direct tracker's solver on the LiDAR points, each
# weighted by a learned confidence that it does not move), started from the step-2,500 weights
# above (encoder, completion and flow; checkpoints/default_step2500.pt) and trained 2,000 steps on
# drives with traffic and sensor effects (true flow, motion masks) and two static ones, one
# thread, ~1.2 s per step; validated on a traffic drive of its own (val_traffic).
INIT=${INIT:-checkpoints/default_step2500.pt}
S=(--size "$SIZE" --sensor-effects)
# (a traffic drive without shadow_2/ is rendered again: synth resumes, adds it, and writes every
# other file byte for byte as before)
drive() {
  [ -f "$OUT/data/$1/poses.txt" ] && { [[ " ${*:2} " != *" --traffic "* ]] || [ -d "$OUT/data/$1/shadow_2" ]; } && return
  "$D3LVO" synth --out "$OUT/data/$1" "${@:2}" "${S[@]}"
}
# the training and validation drives with traffic as the bundled model saw them: vehicles whose
# schedule runs into the camera's own car kept (`d3lvo synth --ego-collisions`; val_traffic_4 and
# val_traffic_612 have some: `python scripts/ego_collisions.py DRIVE...` lists them)
seen() { drive "$@" --ego-collisions; }
# a static drive of 200 frames, no sensor effects: static_drive NAME SEED KITTI_SEQ START
static_drive() {
  [ -f "$OUT/data/$1/poses.txt" ] || "$D3LVO" synth --out "$OUT/data/$1" --frames 200 --seed "$2" --size "$SIZE" \
    --motion-from "$GT/$3.txt" --motion-start "$4"
}
seen tr_00 --frames 120 --seed 500 --motion-from "$GT/00.txt" --motion-start 100 --traffic 4
seen tr_02 --frames 120 --seed 501 --motion-from "$GT/02.txt" --motion-start 300 --traffic 6
seen tr_05 --frames 120 --seed 502 --motion-from "$GT/05.txt" --motion-start 500 --traffic 3
seen tr_08 --frames 120 --seed 503 --motion-from "$GT/08.txt" --motion-start 700 --traffic 8
drive st_03 --frames 120 --seed 504 --motion-from "$GT/03.txt" --motion-start 100
drive st_07 --frames 120 --seed 505 --motion-from "$GT/07.txt" --motion-start 200
seen tr_04 --frames 120 --seed 506 --motion-from "$GT/04.txt" --motion-start 50 --traffic 5
seen tr_06 --frames 120 --seed 507 --motion-from "$GT/06.txt" --motion-start 400 --traffic 7
seen tr_01 --frames 120 --seed 508 --motion-from "$GT/01.txt" --motion-start 300 --traffic 4
seen tr_00b --frames 120 --seed 509 --motion-from "$GT/00.txt" --motion-start 2000 --traffic 10
seen val_traffic --frames 100 --seed 600 --motion-from "$GT/08.txt" --motion-start 2000 --traffic 6
points=()
for s in tr_00 tr_00b tr_01 tr_02 tr_04 tr_05 tr_06 tr_08 st_03 st_07; do points+=(--data "$OUT/data/$s"); done
OMP_NUM_THREADS=1 "$D3LVO" train "${points[@]}" --val "$OUT/data/val_traffic" --out "$OUT/points.pt" \
  $(init_or_resume "$INIT" "$OUT/points.pt") --preset small --pose-head points --batch-size 4 --lr 5e-4 --steps 2000 --val-every 400 \
  --ckpt-every 50 --seed 0

# Then the pose loss through the solver (--solver-loss 1: eq. 11 on the solver's own poses,
# backpropagated into the confidence; flips and rotations off), in two parts: 600 steps on the same
# ten drives, then 400 more with four more static drives (two with the synthesizer's own motion),
# one thread, ~1.5 s per step. checkpoints/points_solver_step400.pt is the second part's full state.
plain() { [ -f "$OUT/data/$1/poses.txt" ] || "$D3LVO" synth --out "$OUT/data/$1" "${@:2}" --size "$SIZE"; }
plain st_d1 --frames 120 --seed 520
drive st_d2 --frames 120 --seed 521
plain st_02 --frames 120 --seed 522 --motion-from "$GT/02.txt" --motion-start 900
drive st_08 --frames 120 --seed 523 --motion-from "$GT/08.txt" --motion-start 1500
OMP_NUM_THREADS=1 "$D3LVO" train "${points[@]}" --val "$OUT/data/val_traffic" --out "$OUT/solver.pt" \
  $(init_or_resume "$OUT/points.pt" "$OUT/solver.pt") --preset small --pose-head points --batch-size 4 --lr 2e-4 --steps 600 --val-every 200 \
  --ckpt-every 50 --seed 0 --solver-loss 1
more=("${points[@]}")
for s in st_d1 st_d2 st_02 st_08; do more+=(--data "$OUT/data/$s"); done
OMP_NUM_THREADS=1 "$D3LVO" train "${more[@]}" --val "$OUT/data/val_traffic" --out "$OUT/solver2.pt" \
  $(init_or_resume "$OUT/solver.pt" "$OUT/solver2.pt") --preset small --pose-head points --batch-size 4 --lr 1.5e-4 --steps 400 --val-every 200 \
  --ckpt-every 50 --seed 1 --solver-loss 1

# Last, the confidence net alone, trained anew on the evidence of motion only (scripts/confidence.toml:
# pt_conf_inputs = "evidence", train_only = ["point_pose.moving"]; everything else keeps the weights
# above): cross-entropy against the motion masks, 1,500 steps and then continued to 3,000 (the
# cosine schedule restarts from where 3,000 steps would be), then 1,000 steps of the pose loss
# through the solver, one thread, ~0.8 and ~1.2 s per step. checkpoints/confidence_step3000.pt and
# checkpoints/confidence_solver_step1000.pt are their full states.
OMP_NUM_THREADS=1 "$D3LVO" train --config scripts/confidence.toml "${more[@]}" --val "$OUT/data/val_traffic" \
  --out "$OUT/confidence.pt" $(init_or_resume "$OUT/solver2.pt" "$OUT/confidence.pt")
OMP_NUM_THREADS=1 "$D3LVO" train --config scripts/confidence.toml "${more[@]}" --val "$OUT/data/val_traffic" \
  --out "$OUT/confidence.pt" --resume "$OUT/confidence.pt" --steps 3000
OMP_NUM_THREADS=1 "$D3LVO" train --config scripts/confidence.toml "${more[@]}" --val "$OUT/data/val_traffic" \
  --out "$OUT/confidence_solver.pt" $(init_or_resume "$OUT/confidence.pt" "$OUT/confidence_solver.pt") \
  --steps 1000 --lr 3e-4 --solver-loss 1

# ship the final weights, weights + config only (no optimizer state), with the solver settings
# measured for the direct tracker (docs/evaluation.md) and the classical pose kept unless the
# weighted one explains the trusted points better by 0.005 and its rotation differs by more than
# 0.05 degrees (pt_select, pt_select_rotation: chosen on the validation drives with
# scripts/selection_rules.py below, docs/model-card.md), each point weighted by its confidence to
# the fourth power (pt_conf_power, chosen on the validation drives at the end of this script),
# frame t's grey matched to frame t-1's mean and spread at every step (pt_affine, chosen on the
# validation drives at the end of this script), the finest level also solved alone from the start
# and kept where it explains the points better by 0.001 (pt_fine_restart, chosen on the validation
# drives at the end of this script) or where its depth error against frame t's own LiDAR scan is
# below half the coarse-to-fine pose's (pt_restart_depth, chosen last, at the very end), and
# export from exactly that file
.venv/bin/python -c "from models.checkpoint import slim_checkpoint; slim_checkpoint('$OUT/confidence_solver.pt', \
  'd3lvo_deploy/default_model/default.pt', dict(pt_iters=(15, 15, 15), pt_capacity=2048, pt_scale_every=3, pt_select=0.005, \
  pt_select_rotation=0.05, pt_conf_power=4.0, pt_affine=True, pt_fine_restart=0.001, pt_restart_depth=0.5))"
"$D3LVO" export --ckpt d3lvo_deploy/default_model/default.pt --out d3lvo_deploy/default_model --overwrite
"$D3LVO" export --ckpt "$OUT/mlp.best.pt" --out "$OUT/mlp_onnx" --overwrite
"$D3LVO" export --ckpt "$OUT/rgb.best.pt" --out "$OUT/rgb_onnx" --overwrite
"$D3LVO" export --ckpt "$OUT/default.best.pt" --out "$OUT/cells_onnx" --overwrite

# held-out drives (seeds never trained on), static and with traffic, for docs/evaluation.md
# static ones (seed, KITTI sequence, start); those from 221 on were rendered after the solver's
# settings were fixed
# static_drives "SEED KITTI_SEQ START"...: each into static_SEED
static_drives() {
  for spec in "$@"; do
    read -r seed sq start <<< "$spec"
    static_drive "static_$seed" "$seed" "$sq" "$start"
  done
}
static_drives "219 09 800" "220 10 600" "221 09 400" "222 10 0" "223 09 1300" "224 10 900" "225 09 100" \
  "226 10 200" "227 09 500" "228 10 400" "229 09 1000" "230 10 700" "231 09 1200"
drive traffic_309 --frames 200 --seed 309 --motion-from "$GT/09.txt" --motion-start 200 --traffic 3
drive traffic_310 --frames 200 --seed 310 --motion-from "$GT/10.txt" --motion-start 300 --traffic 5
drive traffic_311 --frames 200 --seed 311 --motion-from "$GT/09.txt" --motion-start 900 --traffic 8
drive traffic_312 --frames 200 --seed 312 --motion-from "$GT/09.txt" --motion-start 400 --traffic 2
drive traffic_313 --frames 200 --seed 313 --motion-from "$GT/10.txt" --motion-start 0 --traffic 4
drive traffic_314 --frames 200 --seed 314 --motion-from "$GT/09.txt" --motion-start 1350 --traffic 6
drive traffic_315 --frames 200 --seed 315 --motion-from "$GT/10.txt" --motion-start 800 --traffic 10
# validation drives of where each pair starts (docs/model-card.md: the kept pose or the weighted one)
seen val_traffic_3 --frames 200 --seed 606 --motion-from "$GT/05.txt" --motion-start 600 --traffic 4
seen val_traffic_4 --frames 200 --seed 607 --motion-from "$GT/00.txt" --motion-start 3000 --traffic 8
for v in kept-start:0.01 pt_select:0.01; do
  .venv/bin/python scripts/confidence_variants.py "$v" "$OUT/data/val_traffic_3" "$OUT/data/val_traffic_4"
done

# the tables of docs/evaluation.md: the bundled network beside its classical mode (--method
# direct), the cell-solver network, the MLP head and the rgb ablation; `d3lvo run` scores each run
# against the poses.txt beside the sequence
for s in heldout_09 heldout_10 static_219 static_220 traffic_309 traffic_310 traffic_311; do
  "$D3LVO" run --seq-dir "$OUT/data/$s" --out "$OUT/eval/default_$s.txt" --overwrite
  "$D3LVO" run --seq-dir "$OUT/data/$s" --method direct --out "$OUT/eval/direct_$s.txt" --overwrite
  "$D3LVO" run --seq-dir "$OUT/data/$s" --onnx "$OUT/cells_onnx" --out "$OUT/eval/cells_$s.txt" --overwrite
done
for s in traffic_312 traffic_313 traffic_314 traffic_315; do
  "$D3LVO" run --seq-dir "$OUT/data/$s" --out "$OUT/eval/default_$s.txt" --overwrite
  "$D3LVO" run --seq-dir "$OUT/data/$s" --method direct --out "$OUT/eval/direct_$s.txt" --overwrite
done
for s in $(seq 221 231); do
  "$D3LVO" run --seq-dir "$OUT/data/static_$s" --out "$OUT/eval/default_static_$s.txt" --overwrite
  "$D3LVO" run --seq-dir "$OUT/data/static_$s" --method direct --out "$OUT/eval/direct_static_$s.txt" --overwrite
done
for s in heldout_09 heldout_10; do
  "$D3LVO" run --seq-dir "$OUT/data/$s" --onnx "$OUT/mlp_onnx" --out "$OUT/eval/mlp_$s.txt" --overwrite
  "$D3LVO" run --seq-dir "$OUT/data/$s" --onnx "$OUT/rgb_onnx" --out "$OUT/eval/rgb_$s.txt" --overwrite
done

# the sweeps below were measured before pt_affine was chosen (at the end of this script), so they
# start from the shipped file with it off (and without the restart's scan check, chosen after them)
.venv/bin/python -c "from models.checkpoint import slim_checkpoint; slim_checkpoint('d3lvo_deploy/default_model/default.pt', \
  '$OUT/affine_off.pt', dict(pt_affine=False, pt_restart_depth=0.0))"
"$D3LVO" export --ckpt "$OUT/affine_off.pt" --out "$OUT/affine_off" --overwrite
# the sweeps below select as the model card's tables of them: pt_select 0.01, no rotation gate
SEL01="--set pt_select=0.01 --set pt_select_rotation=0"
# the static prior pt_conf_full (a point weighs 1 once its confidence reaches it), measured on the
# validation drives with and without traffic (docs/model-card.md): it stays off
[ -f "$OUT/data/val_static/poses.txt" ] || "$D3LVO" synth --out "$OUT/data/val_static" --frames 100 --seed 601 \
  --size "$SIZE" --motion-from "$GT/05.txt" --motion-start 1800
for s in val_traffic val_static; do
  "$D3LVO" run "$OUT/data/$s" --method direct --onnx "$OUT/affine_off" --out "$OUT/eval/direct_$s.txt" --overwrite
done
for c in 1 0.5 0.7 0.85; do
  "$D3LVO" export --ckpt "$OUT/affine_off.pt" --out "$OUT/conf_full_$c" --overwrite --set pt_conf_full=$c $SEL01
  for s in val_traffic val_static; do
    "$D3LVO" run "$OUT/data/$s" --onnx "$OUT/conf_full_$c" --backend onnxruntime --out "$OUT/eval/conf_full_${c}_$s.txt" \
      --overwrite
  done
done

# the power that turns a confidence into a weight (pt_conf_power), on the validation drives with
# and without traffic (docs/model-card.md#solver-settings): 4 ships
seen val_traffic_2 --frames 200 --seed 605 --motion-from "$GT/02.txt" --motion-start 1500 --traffic 6
for spec in "602 03 300" "603 07 500" "604 06 200"; do
  read -r seed sq start <<< "$spec"
  static_drive "val_static_$((seed - 600))" "$seed" "$sq" "$start"
done
for p in 1 2 4 8; do
  "$D3LVO" export --ckpt "$OUT/affine_off.pt" --out "$OUT/power_$p" --overwrite --set pt_conf_power=$p $SEL01
  for s in val_traffic val_traffic_2 val_traffic_3 val_traffic_4 val_static val_static_2 val_static_3 val_static_4; do
    "$D3LVO" run "$OUT/data/$s" --onnx "$OUT/power_$p" --backend onnxruntime --threads 1 \
      --out "$OUT/eval/power_${p}_$s.txt" --overwrite
  done
done

# at power 4, the static prior and a higher selection threshold, on those validation drives and six
# more (docs/model-card.md#solver-settings): neither ships
seen val_traffic_612 --frames 200 --seed 612 --motion-from "$GT/08.txt" --motion-start 1500 --traffic 5
seen val_traffic_613 --frames 200 --seed 613 --motion-from "$GT/00.txt" --motion-start 1500 --traffic 3
for spec in "608 00 1000" "609 02 2000" "610 05 1200" "611 08 3000"; do
  read -r seed sq start <<< "$spec"
  static_drive "val_static_$seed" "$seed" "$sq" "$start"
done
NEW=(val_traffic_612 val_traffic_613 val_static_608 val_static_609 val_static_610 val_static_611)
VAL=(val_traffic val_traffic_2 val_traffic_3 val_traffic_4 val_static val_static_2 val_static_3 val_static_4 "${NEW[@]}")
# the classical mode where the static prior's runs above have not scored it, power 4 (power_4)
# where the power sweep has not
for s in val_traffic_2 val_traffic_3 val_traffic_4 val_static_2 val_static_3 val_static_4 "${NEW[@]}"; do
  "$D3LVO" run "$OUT/data/$s" --method direct --onnx "$OUT/affine_off" --out "$OUT/eval/direct_$s.txt" --overwrite
done
for s in "${NEW[@]}"; do
  "$D3LVO" run "$OUT/data/$s" --onnx "$OUT/power_4" --backend onnxruntime --threads 1 \
    --out "$OUT/eval/power_4_$s.txt" --overwrite
done
for set in pt_conf_full=0.85 pt_select=0.02 pt_select=0.04; do
  "$D3LVO" export --ckpt "$OUT/affine_off.pt" --out "$OUT/$set" --overwrite $SEL01 --set "$set"
  for s in "${VAL[@]}"; do
    "$D3LVO" run "$OUT/data/$s" --onnx "$OUT/$set" --backend onnxruntime --threads 1 --out "$OUT/eval/${set}_$s.txt" \
      --overwrite
  done
done
# the selection's two thresholds, on those fourteen validation drives and ten more static ones
# (docs/model-card.md)
for spec in "614 01 300" "615 03 500" "616 04 50" "617 06 600" "618 07 800" "619 02 3500" "620 00 4000" \
            "621 05 2400" "622 08 1200" "623 00 200"; do
  read -r seed sq start <<< "$spec"
  static_drive "val_static_$seed" "$seed" "$sq" "$start"
done
.venv/bin/python scripts/selection_rules.py --ckpt "$OUT/affine_off.pt" "$OUT"/data/val_static* "$OUT"/data/val_traffic*
# the same rules on the two held-out drives where the network loses to its classical mode (not used
# for the choice): the demo's drive and seed 228
[ -f "$OUT/data/demo_909/poses.txt" ] || "$D3LVO" synth --out "$OUT/data/demo_909" --frames 220 --seed 909 --size "$SIZE"
.venv/bin/python scripts/selection_rules.py --ckpt "$OUT/affine_off.pt" "$OUT/data/demo_909" "$OUT/data/static_228"
# each drive's first pair from rest and from the cold start's guesses (docs/evaluation.md, the first pair)
.venv/bin/python scripts/first_pairs.py "$OUT"/data/val_* "$OUT"/data/tr_00 "$OUT"/data/heldout_* "$OUT"/data/static_219 \
  "$OUT"/data/static_22[0-9] "$OUT"/data/traffic_3* "$OUT"/data/demo_909
# the confidence read against the classical pose, as a gate in the graph (pt_select_unexplained;
# docs/model-card.md), on the held-out drives: it does not ship
"$D3LVO" export --ckpt "$OUT/affine_off.pt" --out "$OUT/unexplained_0.15" --overwrite --set pt_select_unexplained=0.15
for d in "$OUT"/data/heldout_?? "$OUT"/data/static_2[12]? "$OUT"/data/static_23[01] "$OUT"/data/traffic_31[0-5] \
         "$OUT"/data/traffic_309 "$OUT"/data/demo_909; do
  "$D3LVO" run "$d" --onnx "$OUT/unexplained_0.15" --backend onnxruntime --threads 1 \
    --out "$OUT/eval/unexplained_0.15_$(basename "$d").txt" --overwrite
done
# ten more static held-out drives and four with traffic, rendered after every setting of the bundled
# model was fixed (docs/evaluation.md, fresh held-out drives)
static_drives "232 09 50" "233 10 100" "234 09 650" "235 10 300" "236 09 900" "237 10 500" "238 09 1100" \
  "239 10 800" "240 09 250" "241 10 1000"
drive traffic_316 --frames 200 --seed 316 --motion-from "$GT/09.txt" --motion-start 600 --traffic 4
drive traffic_317 --frames 200 --seed 317 --motion-from "$GT/10.txt" --motion-start 500 --traffic 6
drive traffic_318 --frames 200 --seed 318 --motion-from "$GT/09.txt" --motion-start 1100 --traffic 3
drive traffic_319 --frames 200 --seed 319 --motion-from "$GT/10.txt" --motion-start 150 --traffic 8
FRESH=(static_232 static_233 static_234 static_235 static_236 static_237 static_238 static_239 static_240 static_241
       traffic_316 traffic_317 traffic_318 traffic_319)
for s in "${FRESH[@]}"; do
  "$D3LVO" run "$OUT/data/$s" --backend onnxruntime --threads 1 --out "$OUT/eval/default_$s.txt" --overwrite
  "$D3LVO" run "$OUT/data/$s" --method direct --out "$OUT/eval/direct_$s.txt" --overwrite
  "$D3LVO" run "$OUT/data/$s" --onnx "$OUT/affine_off" --backend onnxruntime --threads 1 \
    --out "$OUT/eval/affine_off_$s.txt" --overwrite
  "$D3LVO" run "$OUT/data/$s" --method direct --onnx "$OUT/affine_off" --out "$OUT/eval/affine_off_direct_$s.txt" \
    --overwrite
done
# frame t's grey matched to frame t-1's at every step (pt_affine), on the twenty-four validation
# drives, the network and its classical mode with and without it (docs/evaluation.md): it ships
for d in "$OUT"/data/val_traffic* "$OUT"/data/val_static*; do
  s=$(basename "$d")
  "$D3LVO" run "$d" --onnx "$OUT/affine_off" --backend onnxruntime --threads 1 --out "$OUT/eval/affine_off_$s.txt" --overwrite
  "$D3LVO" run "$d" --onnx "$OUT/affine_off" --method direct --out "$OUT/eval/affine_off_direct_$s.txt" --overwrite
  "$D3LVO" run "$d" --backend onnxruntime --threads 1 --out "$OUT/eval/default_$s.txt" --overwrite
  "$D3LVO" run "$d" --method direct --out "$OUT/eval/direct_$s.txt" --overwrite
done
# the selection's thresholds again with pt_affine on, on the shipped checkpoint (docs/model-card.md)
.venv/bin/python scripts/selection_rules.py "$OUT"/data/val_static* "$OUT"/data/val_traffic*
# the finest level also solved alone from the start, kept where it explains the points better by
# more than the threshold (pt_fine_restart; docs/evaluation.md), on the twenty-four validation
# drives: the classical mode at 0.005, 0.02 and 0.001, the network at 0.005 and 0.001; 0.001 ships
.venv/bin/python -c "from models.checkpoint import slim_checkpoint; slim_checkpoint('d3lvo_deploy/default_model/default.pt', \
  '$OUT/restart_off.pt', dict(pt_fine_restart=0.0, pt_restart_depth=0.0))"
# both modes of the model folder $2 on the twenty-four validation drives, written as
# eval/$1_direct_DRIVE.txt and eval/$1_DRIVE.txt; a third argument "classical": that mode only
on_validation() {
  for d in "$OUT"/data/val_traffic* "$OUT"/data/val_static*; do
    s=$(basename "$d")
    "$D3LVO" run "$d" --onnx "$2" --method direct --out "$OUT/eval/$1_direct_$s.txt" --overwrite
    [ "${3:-}" = classical ] || "$D3LVO" run "$d" --onnx "$2" --backend onnxruntime --threads 1 \
      --out "$OUT/eval/$1_$s.txt" --overwrite
  done
}
for t in 0.005 0.02 0.001; do
  "$D3LVO" export --ckpt "$OUT/restart_off.pt" --out "$OUT/restart_$t" --overwrite --set pt_fine_restart=$t
  on_validation "restart_$t" "$OUT/restart_$t" $([ "$t" = 0.02 ] && echo classical)
done
# then the held-out drives again, the shipped model and its classical mode (docs/evaluation.md)
for d in "$OUT"/data/heldout_?? "$OUT"/data/static_2?? "$OUT"/data/traffic_3?? "$OUT"/data/demo_909; do
  s=$(basename "$d")
  "$D3LVO" run "$d" --backend onnxruntime --threads 1 --out "$OUT/eval/default_$s.txt" --overwrite
  "$D3LVO" run "$d" --method direct --out "$OUT/eval/direct_$s.txt" --overwrite
done
# up to 9 Gauss-Newton steps per level instead of 15 (pt_iters; docs/evaluation.md), both modes, on
# the twenty-four validation drives and then the held-out ones; it costs accuracy with traffic and
# does not ship. Then 40 steps at the finest level, the classical mode on eight static ones (both
# measured before the restart's scan check was chosen)
"$D3LVO" export --ckpt d3lvo_deploy/default_model/default.pt --out "$OUT/steps_9" --overwrite --set pt_iters=9,9,9 --set pt_restart_depth=0
for d in "$OUT"/data/val_traffic* "$OUT"/data/val_static* "$OUT"/data/heldout_?? "$OUT"/data/static_2?? \
         "$OUT"/data/traffic_3?? "$OUT"/data/demo_909; do
  s=$(basename "$d")
  "$D3LVO" run "$d" --onnx "$OUT/steps_9" --backend onnxruntime --threads 1 --out "$OUT/eval/steps_9_$s.txt" --overwrite
  "$D3LVO" run "$d" --onnx "$OUT/steps_9" --method direct --out "$OUT/eval/steps_9_direct_$s.txt" --overwrite
done
"$D3LVO" export --ckpt d3lvo_deploy/default_model/default.pt --out "$OUT/steps_40" --overwrite --set pt_iters=15,15,40 --set pt_restart_depth=0
for s in val_static_2 val_static_3 val_static_4 val_static_608 val_static_609 val_static_610 val_static_611 \
         val_static_614; do
  "$D3LVO" run "$OUT/data/$s" --onnx "$OUT/steps_40" --method direct --out "$OUT/eval/steps_40_direct_$s.txt" --overwrite
done
# the finest level's restart also kept where its depth error against frame t's own LiDAR scan is
# below R times the coarse-to-fine pose's (pt_restart_depth; docs/evaluation.md), on the
# twenty-four validation drives: the classical mode at 0.5 and 0.7, the network at 0.5; 0.5 ships
# (set in the slimmed default.pt above; the held-out runs of the shipped model above have it).
# Then the held-out drives without it
.venv/bin/python -c "from models.checkpoint import slim_checkpoint; slim_checkpoint('d3lvo_deploy/default_model/default.pt', \
  '$OUT/scan_off.pt', dict(pt_restart_depth=0.0))"
"$D3LVO" export --ckpt "$OUT/scan_off.pt" --out "$OUT/scan_off" --overwrite
for r in 0.5 0.7; do
  "$D3LVO" export --ckpt "$OUT/scan_off.pt" --out "$OUT/scan_$r" --overwrite --set pt_restart_depth=$r
  on_validation "scan_$r" "$OUT/scan_$r" $([ "$r" = 0.7 ] && echo classical)
done
for d in "$OUT"/data/heldout_?? "$OUT"/data/static_2?? "$OUT"/data/traffic_3?? "$OUT"/data/demo_909; do
  s=$(basename "$d")
  "$D3LVO" run "$d" --onnx "$OUT/scan_off" --backend onnxruntime --threads 1 --out "$OUT/eval/scan_off_$s.txt" --overwrite
  "$D3LVO" run "$d" --onnx "$OUT/scan_off" --method direct --out "$OUT/eval/scan_off_direct_$s.txt" --overwrite
done

# four more traffic drives, rendered after every setting of the bundled model was fixed and scored
# once (docs/evaluation.md, four traffic drives rendered last): the shipped model and its classical mode
drive traffic_320 --frames 200 --seed 320 --motion-from "$GT/09.txt" --motion-start 50 --traffic 5
drive traffic_321 --frames 200 --seed 321 --motion-from "$GT/10.txt" --motion-start 100 --traffic 7
drive traffic_322 --frames 200 --seed 322 --motion-from "$GT/09.txt" --motion-start 700 --traffic 4
drive traffic_323 --frames 200 --seed 323 --motion-from "$GT/10.txt" --motion-start 1000 --traffic 9
for s in traffic_320 traffic_321 traffic_322 traffic_323; do
  "$D3LVO" run "$OUT/data/$s" --backend onnxruntime --threads 1 --out "$OUT/eval/default_$s.txt" --overwrite
  "$D3LVO" run "$OUT/data/$s" --method direct --out "$OUT/eval/direct_$s.txt" --overwrite
done
# moving shadows (shadow_2/) in the confidence's target, measured, not shipped (docs/model-card.md).
# First the classical mode with an oracle's points dropped: those on movers, then also those in
# moving shadows
# (all fifteen held-out traffic drives: docs/model-card.md, how much of the 30 % cut a confidence can reach)
for s in val_traffic val_traffic_2 val_traffic_3 val_traffic_4 val_traffic_612 val_traffic_613 traffic_309 \
         traffic_310 traffic_311 traffic_312 traffic_313 traffic_314 traffic_315 traffic_316 traffic_317 traffic_318 \
         traffic_319 traffic_320 traffic_321 traffic_322 traffic_323; do
  .venv/bin/python scripts/masked_tracker.py "$OUT/data/$s" "$OUT/eval/movers_dropped_$s.txt"
  .venv/bin/python scripts/masked_tracker.py "$OUT/data/$s" "$OUT/eval/shadows_dropped_$s.txt" --shadows
done
# then the shipped confidence trained on with them (1,000 steps against the masks, 500 through the
# solver, one thread, ~0.9 and ~1.1 s per step) and, as the control, the same without them
sed 's/moving_shadows = true/moving_shadows = false/' scripts/confidence_shadows.toml > "$OUT/shadows_control.toml"
for v in shadows shadows_control; do
  toml=scripts/confidence_shadows.toml
  [ "$v" = shadows_control ] && toml="$OUT/shadows_control.toml"
  OMP_NUM_THREADS=1 "$D3LVO" train --config "$toml" "${more[@]}" --val "$OUT/data/val_traffic" --out "$OUT/$v.pt" \
    $(init_or_resume checkpoints/confidence_solver_step1000.pt "$OUT/$v.pt")
  OMP_NUM_THREADS=1 "$D3LVO" train --config "$toml" "${more[@]}" --val "$OUT/data/val_traffic" --out "$OUT/${v}_solver.pt" \
    $(init_or_resume "$OUT/$v.pt" "$OUT/${v}_solver.pt") --steps 500 --lr 2e-4 --solver-loss 1 --val-every 250
  .venv/bin/python -c "from models.checkpoint import slim_checkpoint; slim_checkpoint('$OUT/${v}_solver.pt', \
    '$OUT/${v}_slim.pt', dict(pt_iters=(15, 15, 15), pt_capacity=2048, pt_scale_every=3, pt_select=0.005, \
    pt_select_rotation=0.05, pt_conf_power=4.0, pt_affine=True, pt_fine_restart=0.001, pt_restart_depth=0.5))"
  "$D3LVO" export --ckpt "$OUT/${v}_slim.pt" --out "$OUT/$v" --overwrite
  for d in "$OUT"/data/val_traffic* "$OUT"/data/traffic_3??; do
    "$D3LVO" run "$d" --onnx "$OUT/$v" --backend onnxruntime --threads 1 --out "$OUT/eval/${v}_$(basename "$d").txt" --overwrite
  done
  .venv/bin/python -m models.pair_eval "$OUT/${v}_slim.pt" "$OUT/data/val_traffic" "$OUT"/data/traffic_32[0-3]
done
for d in "$OUT"/data/val_static* "$OUT"/data/static_2?? "$OUT"/data/heldout_?? "$OUT"/data/demo_909; do
  "$D3LVO" run "$d" --onnx "$OUT/shadows" --backend onnxruntime --threads 1 --out "$OUT/eval/shadows_$(basename "$d").txt" --overwrite
done
# cheaper solver steps, measured and not shipped (docs/evaluation.md, docs/performance.md): the
# Huber threshold's median over every fourth point, and that with 6 steps at the coarse levels
for v in "stride_4:--set pt_median_stride=4" "stride_4_coarse_6:--set pt_median_stride=4 --set pt_iters=6,6,15"; do
  name=${v%%:*}
  # shellcheck disable=SC2086
  "$D3LVO" export --ckpt d3lvo_deploy/default_model/default.pt --out "$OUT/$name" --overwrite ${v#*:}
  for d in "$OUT"/data/val_traffic* "$OUT"/data/val_static* "$OUT"/data/traffic_3?? "$OUT"/data/static_2?? \
           "$OUT"/data/heldout_?? "$OUT"/data/demo_909; do
    "$D3LVO" run "$d" --onnx "$OUT/$name" --backend onnxruntime --threads 1 --out "$OUT/eval/${name}_$(basename "$d").txt" --overwrite
  done
done
.venv/bin/python -m export.solver_bench --height 375 --width 1242
.venv/bin/python -m export.solver_bench --height 375 --width 1242 --median-stride 4
# frame t's scan as a second judge between the weighted and the classical pose (pt_select_scan,
# pt_select_scan_pass; docs/model-card.md), chosen on the twenty-four validation drives after
# every run above: the pass at 0.7 ships, set in default.pt and exported into the bundled folder;
# then the held-out drives and the validation traffic drives with it
.venv/bin/python scripts/selection_rules.py --quick "$OUT"/data/val_static* "$OUT"/data/val_traffic*
.venv/bin/python -c "from models.checkpoint import slim_checkpoint; slim_checkpoint('d3lvo_deploy/default_model/default.pt', \
  'd3lvo_deploy/default_model/default.pt', dict(pt_select_scan_pass=0.7))"
"$D3LVO" export --ckpt d3lvo_deploy/default_model/default.pt --out d3lvo_deploy/default_model --overwrite
for d in "$OUT"/data/heldout_?? "$OUT"/data/static_2?? "$OUT"/data/traffic_3?? "$OUT"/data/demo_909 "$OUT"/data/val_traffic*; do
  "$D3LVO" run "$d" --backend onnxruntime --threads 1 --out "$OUT/eval/scan_pass_$(basename "$d").txt" --overwrite
done

# Last, the confidence net continued on denser traffic (docs/model-card.md): six more drives of 120
# frames at 9-12 vehicles per 100 m (seeds 540-545, KITTI 00-08 motion at starts no training or
# held-out drive uses; three replay validation drives' motion in other worlds: seeds 601, 603 and
# 617), then, everything else kept as above (scripts/confidence.toml), 1,200 steps of cross-entropy
# against the motion masks at lr 3e-4 on the twenty drives from the weights shipped above
# (checkpoints/confidence_solver_step1000.pt) and 600 steps of the pose loss through the solver at
# lr 3e-4, one thread, ~0.9 and ~1.8 s per step; checkpoints/dense_step1200.pt and
# checkpoints/dense_solver_step600.pt are their full states. Chosen on the validation drives (the
# confidence's AUROC and t_rel), shipped with the settings default.pt holds, and scored once on
# the held-out drives.
seen trd_00 --frames 120 --seed 540 --motion-from "$GT/00.txt" --motion-start 700 --traffic 12
seen trd_02 --frames 120 --seed 541 --motion-from "$GT/02.txt" --motion-start 2500 --traffic 9
seen trd_05 --frames 120 --seed 542 --motion-from "$GT/05.txt" --motion-start 1800 --traffic 10
seen trd_06 --frames 120 --seed 543 --motion-from "$GT/06.txt" --motion-start 700 --traffic 11
seen trd_07 --frames 120 --seed 544 --motion-from "$GT/07.txt" --motion-start 500 --traffic 9
seen trd_08 --frames 120 --seed 545 --motion-from "$GT/08.txt" --motion-start 3200 --traffic 12
dense=("${more[@]}")
for s in trd_00 trd_02 trd_05 trd_06 trd_07 trd_08; do dense+=(--data "$OUT/data/$s"); done
OMP_NUM_THREADS=1 "$D3LVO" train --config scripts/confidence.toml "${dense[@]}" --val "$OUT/data/val_traffic" \
  --out "$OUT/dense.pt" $(init_or_resume checkpoints/confidence_solver_step1000.pt "$OUT/dense.pt") \
  --steps 1200 --lr 3e-4 --val-every 300
OMP_NUM_THREADS=1 "$D3LVO" train --config scripts/confidence.toml "${dense[@]}" --val "$OUT/data/val_traffic" \
  --out "$OUT/dense_solver.pt" $(init_or_resume "$OUT/dense.pt" "$OUT/dense_solver.pt") \
  --steps 600 --lr 3e-4 --val-every 200 --solver-loss 1
for v in val_traffic val_traffic_2 val_traffic_3 val_traffic_4 val_traffic_612 val_traffic_613; do
  .venv/bin/python -m models.pair_eval "$OUT/dense_solver.pt" "$OUT/data/$v"
done
.venv/bin/python -c "from models.checkpoint import load_checkpoint, slim_checkpoint; from models.config import SOLVER_KEYS; \
  c = load_checkpoint('d3lvo_deploy/default_model/default.pt')['config']; \
  slim_checkpoint('$OUT/dense_solver.pt', 'd3lvo_deploy/default_model/default.pt', {k: getattr(c, k) for k in SOLVER_KEYS})"
"$D3LVO" export --ckpt d3lvo_deploy/default_model/default.pt --out d3lvo_deploy/default_model --overwrite
for d in "$OUT"/data/val_traffic_* "$OUT"/data/val_static_2 "$OUT"/data/val_static_3 "$OUT"/data/heldout_?? \
         "$OUT"/data/static_2?? "$OUT"/data/traffic_3?? "$OUT"/data/demo_909; do
  "$D3LVO" run "$d" --backend onnxruntime --threads 1 --out "$OUT/eval/dense_$(basename "$d").txt" --overwrite
done
.venv/bin/python -m models.pair_eval d3lvo_deploy/default_model/default.pt "$OUT"/data/traffic_3?? --pairs 199

# Then the static drives' gap to the classical mode (docs/model-card.md). Measured, not shipped: the
# confidence net's pose-loss training continued from the shipped weights with the six static training
# drives given twice (400 steps, lr 1.5e-4, seed 2), scored on the twenty-four validation drives beside
# the shipped weights and the classical mode. Shipped: a cap on the share of frame t-1's points the
# network distrusts for the photometric test (pt_select_share), chosen on the same drives (0.7), set
# in default.pt and exported into the bundled folder; then every held-out drive with it.
static2=("${dense[@]}")
for s in st_03 st_07 st_d1 st_d2 st_02 st_08; do static2+=(--data "$OUT/data/$s"); done
OMP_NUM_THREADS=1 "$D3LVO" train --config scripts/confidence.toml "${static2[@]}" --val "$OUT/data/val_traffic" \
  --out "$OUT/static2.pt" $(init_or_resume "$OUT/dense_solver.pt" "$OUT/static2.pt") \
  --steps 400 --lr 1.5e-4 --val-every 200 --solver-loss 1 --seed 2
# (both without the cap: the shipped weights exported with pt_select_share 1 beside it)
.venv/bin/python -c "from models.checkpoint import load_checkpoint, slim_checkpoint; from models.config import SOLVER_KEYS; \
  c = load_checkpoint('d3lvo_deploy/default_model/default.pt')['config']; \
  slim_checkpoint('$OUT/static2.pt', '$OUT/static2_slim.pt', {**{k: getattr(c, k) for k in SOLVER_KEYS}, 'pt_select_share': 1.0})"
"$D3LVO" export --ckpt "$OUT/static2_slim.pt" --out "$OUT/static2_onnx" --overwrite
"$D3LVO" export --ckpt d3lvo_deploy/default_model/default.pt --out "$OUT/no_cap" --overwrite --set pt_select_share=1
for d in "$OUT"/data/val_traffic* "$OUT"/data/val_static*; do
  "$D3LVO" run "$d" --onnx "$OUT/static2_onnx" --backend onnxruntime --threads 1 --out "$OUT/eval/static2_$(basename "$d").txt" --overwrite
  "$D3LVO" run "$d" --onnx "$OUT/no_cap" --backend onnxruntime --threads 1 --out "$OUT/eval/shipped_$(basename "$d").txt" --overwrite
  "$D3LVO" run "$d" --method direct --out "$OUT/eval/direct_$(basename "$d").txt" --overwrite
done
.venv/bin/python scripts/selection_rules.py --quick "$OUT"/data/val_static* "$OUT"/data/val_traffic*
.venv/bin/python -c "from models.checkpoint import slim_checkpoint; slim_checkpoint('d3lvo_deploy/default_model/default.pt', \
  'd3lvo_deploy/default_model/default.pt', dict(pt_select_share=0.7))"
"$D3LVO" export --ckpt d3lvo_deploy/default_model/default.pt --out d3lvo_deploy/default_model --overwrite
for d in "$OUT"/data/val_static_4 "$OUT"/data/val_traffic_3; do  # the graph against the script's scores
  "$D3LVO" run "$d" --backend onnxruntime --threads 1 --out "$OUT/eval/capval_$(basename "$d").txt" --overwrite
done
for d in "$OUT"/data/static_2?? "$OUT"/data/heldout_?? "$OUT"/data/traffic_3?? "$OUT"/data/demo_909; do
  "$D3LVO" run "$d" --backend onnxruntime --threads 1 --out "$OUT/eval/cap_$(basename "$d").txt" --overwrite
  "$D3LVO" run "$d" --method direct --out "$OUT/eval/direct_$(basename "$d").txt" --overwrite
done
# The classical solve from its own previous pose (pt_classical_chain), on the validation drives
# beside the shipped model without it, then on every held-out drive (docs/model-card.md): not shipped
"$D3LVO" export --ckpt d3lvo_deploy/default_model/default.pt --out "$OUT/chain" --overwrite --set pt_classical_chain=true
for d in "$OUT"/data/val_traffic* "$OUT"/data/val_static* "$OUT"/data/static_2?? "$OUT"/data/heldout_?? \
         "$OUT"/data/traffic_3??; do
  "$D3LVO" run "$d" --backend onnxruntime --threads 2 --out "$OUT/eval/cap2_$(basename "$d").txt" --overwrite
  "$D3LVO" run "$d" --onnx "$OUT/chain" --backend onnxruntime --threads 2 --out "$OUT/eval/chain_$(basename "$d").txt" \
    --overwrite
done
# Sixteen more static held-out drives and eight with traffic, rendered last, after every setting was
# fixed, and scored once (docs/evaluation.md, "Twenty-four more held-out drives")
static_drives "242 09 150" "243 10 50" "244 09 300" "245 10 250" "246 09 450" "247 10 350" "248 09 600" \
  "249 10 450" "250 09 750" "251 10 550" "252 09 950" "253 10 650" "254 09 1150" "255 10 750" "256 09 1350" \
  "257 10 850"
# traffic_drives "SEED KITTI_SEQ START DENSITY"...: each into traffic_SEED, 200 frames, sensor effects
traffic_drives() {
  for spec in "$@"; do
    read -r seed sq start density <<< "$spec"
    drive "traffic_$seed" --frames 200 --seed "$seed" --motion-from "$GT/$sq.txt" --motion-start "$start" \
      --traffic "$density"
  done
}
traffic_drives "324 09 450 3" "325 10 250 5" "326 09 750 7" "327 10 450 9" "328 09 1000 4" "329 10 650 6" \
  "330 09 1250 8" "331 10 850 10"
for d in "$OUT"/data/static_24[2-9] "$OUT"/data/static_25[0-7] "$OUT"/data/traffic_32[4-9] "$OUT"/data/traffic_33[01]; do
  "$D3LVO" run "$d" --backend onnxruntime --threads 2 --out "$OUT/eval/more_default_$(basename "$d").txt" --overwrite
  "$D3LVO" run "$d" --method direct --out "$OUT/eval/more_direct_$(basename "$d").txt" --overwrite
done
.venv/bin/python -m models.pair_eval d3lvo_deploy/default_model/default.pt "$OUT"/data/traffic_32[4-9] \
  "$OUT"/data/traffic_33[01] --pairs 199
# The selection read over several pairs, or by how far its gain stands out from its spread, on the
# twenty-four validation drives (docs/model-card.md): none ships
.venv/bin/python scripts/selection_rules.py --quick "$OUT"/data/val_static* "$OUT"/data/val_traffic*
# The demo's second drive (`d3lvo demo`: seed 910, 5 moving vehicles per 100 m; the same files the
# demo renders) and four more on the synthesizer's own path with traffic and sensor effects (seed,
# vehicles per 100 m), held out like the others and scored as the README's table is, with the
# AUROC of the confidence (docs/evaluation.md, "The demo")
for spec in "910 5" "911 3" "912 7" "913 9" "914 4"; do
  read -r seed density <<< "$spec"
  drive "own_$seed" --frames 220 --seed "$seed" --traffic "$density"
  "$D3LVO" run "$OUT/data/own_$seed" --backend onnxruntime --threads 1 --out "$OUT/eval/net_$seed.txt" --overwrite
  "$D3LVO" run "$OUT/data/own_$seed" --method direct --out "$OUT/eval/dir_$seed.txt" --overwrite
  for e in net dir; do "$D3LVO" eval --gt "$OUT/data/own_$seed/poses.txt" --est "$OUT/eval/${e}_$seed.txt"; done
  OMP_NUM_THREADS=1 .venv/bin/python -m models.pair_eval d3lvo_deploy/default_model/default.pt "$OUT/data/own_$seed" \
    --pairs 219
done
# The motion guard (`d3lvo run --max-accel A`: the previous motion kept where a solved speed jumps by
# more than A m/s^2), chosen for the classical mode on the six validation traffic drives, then
# scored once on the held-out traffic drives and the five on the synthesizer's own path, both
# methods; it ships off (docs/evaluation.md, "The motion guard")
for d in "$OUT"/data/val_traffic*; do
  for a in 0 20 25 30 40; do
    "$D3LVO" run "$d" --method direct --max-accel "$a" --out "$OUT/eval/guard_direct_${a}_$(basename "$d").txt" --overwrite
  done
  for a in 0 30; do
    "$D3LVO" run "$d" --backend onnxruntime --threads 1 --max-accel "$a" \
      --out "$OUT/eval/guard_net_${a}_$(basename "$d").txt" --overwrite
  done
done
for d in "$OUT"/data/traffic_3?? "$OUT"/data/own_91? "$OUT"/data/static_2?? "$OUT"/data/heldout_?? "$OUT"/data/demo_909; do
  "$D3LVO" run "$d" --backend onnxruntime --threads 1 --max-accel 30 --out "$OUT/eval/guard_net_$(basename "$d").txt" --overwrite
  "$D3LVO" run "$d" --method direct --max-accel 30 --out "$OUT/eval/guard_direct_$(basename "$d").txt" --overwrite
done
.venv/bin/python scripts/pair_steps.py "$OUT/data/traffic_323" 62 82
# three other ways of guarding the classical mode, on the validation drives, and the ground truth's
# largest change of step (docs/evaluation.md, "The motion guard")
V=("$OUT"/data/val_traffic_2 "$OUT"/data/val_traffic_3 "$OUT"/data/val_traffic_4)
.venv/bin/python scripts/guard_variants.py clamp 20 "${V[@]}"
for k in 3 5 10; do .venv/bin/python scripts/guard_variants.py "release:$k" 30 "$OUT/data/val_traffic_2"; done
.venv/bin/python scripts/guard_variants.py scan 30 "${V[@]}" "$OUT"/data/val_traffic_612 "$OUT"/data/val_traffic_613
.venv/bin/python scripts/guard_variants.py truth "$OUT"/data/*
# dropped frames: four held-out drives with one frame in ten left out, with their own times and with
# times 0.1 s apart (docs/evaluation.md, "Dropped frames")
for s in heldout_09 heldout_10 traffic_312 traffic_313; do
  for v in own uniform; do
    d="$OUT/data/dropped_${s}_$v"
    [ -d "$d" ] || .venv/bin/python scripts/drop_frames.py "$OUT/data/$s" "$d" $([ $v = uniform ] && echo --uniform-times)
    "$D3LVO" run "$d" --backend onnxruntime --threads 1 --out "$OUT/eval/dropped_net_${s}_$v.txt" --overwrite
    "$D3LVO" run "$d" --method direct --out "$OUT/eval/dropped_direct_${s}_$v.txt" --overwrite
  done
done
# frame t's scan as a gate before the solve (pt_scan_gate; docs/evaluation.md, "Frame t's scan as a
# gate before the solve"): other robust weights and the gate on the classical mode, on the
# validation drives (each variant also on the static ones alone, for their mean); the network
# without and with the gate on them; then 0.05 set in default.pt and exported into the bundled
# folder, and every held-out drive and the demo's scored with both methods
for v in huber tukey cauchy t scangate:0.05 scangate:0.1 gate:0.03 gate:0.05 gate:0.1; do
  .venv/bin/python scripts/robust_weights.py "$v" "$OUT"/data/val_traffic* "$OUT"/data/val_static*
  .venv/bin/python scripts/robust_weights.py "$v" "$OUT"/data/val_static*
done
for g in 0 0.05; do
  "$D3LVO" export --ckpt d3lvo_deploy/default_model/default.pt --out "$OUT/scan_gate_$g" --overwrite --set pt_scan_gate=$g
  for d in "$OUT"/data/val_traffic* "$OUT"/data/val_static*; do
    "$D3LVO" run "$d" --onnx "$OUT/scan_gate_$g" --backend onnxruntime --threads 1 \
      --out "$OUT/eval/scan_gate_${g}_$(basename "$d").txt" --overwrite
  done
done
.venv/bin/python -c "from models.checkpoint import slim_checkpoint; slim_checkpoint('d3lvo_deploy/default_model/default.pt', \
  'd3lvo_deploy/default_model/default.pt', dict(pt_scan_gate=0.05))"
"$D3LVO" export --ckpt d3lvo_deploy/default_model/default.pt --out d3lvo_deploy/default_model --overwrite
for d in "$OUT"/data/heldout_?? "$OUT"/data/static_2?? "$OUT"/data/traffic_3?? "$OUT"/data/own_91? "$OUT"/data/demo_909; do
  "$D3LVO" run "$d" --backend onnxruntime --threads 1 --out "$OUT/eval/gated_net_$(basename "$d").txt" --overwrite
  "$D3LVO" run "$d" --method direct --out "$OUT/eval/gated_direct_$(basename "$d").txt" --overwrite
done
# what a confidence that knew every moving point (and shadow) would give on seeds 318 and 322, with
# the gate (docs/evaluation.md, "The shipped model on every held-out drive")
for s in 318 322; do
  .venv/bin/python scripts/masked_tracker.py "$OUT/data/traffic_$s" "$OUT/eval/gated_movers_$s.txt"
  .venv/bin/python scripts/masked_tracker.py "$OUT/data/traffic_$s" "$OUT/eval/gated_shadows_$s.txt" --shadows
  for e in movers shadows; do "$D3LVO" eval --gt "$OUT/data/traffic_$s/poses.txt" --est "$OUT/eval/gated_${e}_$s.txt"; done
done
.venv/bin/python scripts/selection_rules.py --quick "$OUT/data/traffic_322"
# the pose choice's rules again with the gate, on the validation drives (docs/model-card.md, "With
# the scan gate"; run as two halves on two cores and the sums added)
.venv/bin/python scripts/selection_rules.py --quick "$OUT"/data/val_static* "$OUT"/data/val_traffic*
# the motion guard at 30 with the gate, both methods, on every held-out traffic drive
# (docs/evaluation.md, "The motion guard")
for d in "$OUT"/data/traffic_3?? "$OUT"/data/own_91?; do
  "$D3LVO" run "$d" --method direct --max-accel 30 --out "$OUT/eval/gated_guard_direct_$(basename "$d").txt" --overwrite
  "$D3LVO" run "$d" --backend onnxruntime --threads 1 --max-accel 30 \
    --out "$OUT/eval/gated_guard_net_$(basename "$d").txt" --overwrite
done
# the pose choice's thresholds chosen again with the gate on, on the validation drives (the cap and
# the scan's pass beside the photometric test; docs/model-card.md, "The pose choice's thresholds
# with the scan gate"), then scored once on every held-out drive from the same records; pt_select
# 0.003 set in default.pt and exported into the bundled folder, every held-out drive run with the
# network again (the classical mode does not read it), and the demo
.venv/bin/python scripts/selection_rules.py --quick --cache "$OUT/selcache" "$OUT"/data/val_static* "$OUT"/data/val_traffic*
.venv/bin/python scripts/selection_rules.py --quick --cache "$OUT/selcache" "$OUT"/data/heldout_?? "$OUT"/data/static_2?? \
  "$OUT"/data/demo_909 "$OUT"/data/traffic_3?? "$OUT"/data/own_91?
.venv/bin/python -c "from models.checkpoint import slim_checkpoint; slim_checkpoint('d3lvo_deploy/default_model/default.pt', \
  'd3lvo_deploy/default_model/default.pt', dict(pt_select=0.003))"
"$D3LVO" export --ckpt d3lvo_deploy/default_model/default.pt --out d3lvo_deploy/default_model --overwrite
for d in "$OUT"/data/heldout_?? "$OUT"/data/static_2?? "$OUT"/data/traffic_3?? "$OUT"/data/own_91? "$OUT"/data/demo_909; do
  "$D3LVO" run "$d" --backend onnxruntime --threads 1 --out "$OUT/eval/select_net_$(basename "$d").txt" --overwrite
done
"$D3LVO" export --ckpt d3lvo_deploy/default_model/default.pt --out "$OUT/select_0.005" --overwrite --set pt_select=0.005
"$D3LVO" run "$OUT/data/traffic_322" --onnx "$OUT/select_0.005" --backend onnxruntime --threads 1 \
  --out "$OUT/eval/select_0.005_traffic_322.txt" --overwrite
"$D3LVO" demo --out "$OUT/demo"
# a learned choice between the weighted and the classical pose (a logistic regression on the
# records above), fitted on the validation drives and scored on the held-out ones
# (docs/model-card.md, "A learned choice between the two poses"; pip install -e '.[analysis]')
.venv/bin/python scripts/learned_choice.py --cache "$OUT/selcache" --fit "$OUT"/data/val_static* "$OUT"/data/val_traffic* \
  --score "$OUT"/data/heldout_?? "$OUT"/data/static_2?? "$OUT"/data/demo_909 "$OUT"/data/traffic_3?? "$OUT"/data/own_91?
# the choice with a memory (the weighted pose held for a few pairs after each pair it is kept on,
# or while frame t's scan or the network's distrust still speaks for it), chosen on the validation
# drives from the same records (docs/model-card.md, "The choice held for a few pairs"), and each
# static held-out drive's replay: not shipped
.venv/bin/python scripts/selection_rules.py --quick --cache "$OUT/selcache" "$OUT"/data/val_static* "$OUT"/data/val_traffic*
.venv/bin/python scripts/selection_rules.py --quick --cache "$OUT/selcache" "$OUT"/data/traffic_3?? "$OUT"/data/own_91?
for d in "$OUT"/data/static_2?? "$OUT"/data/traffic_318; do
  .venv/bin/python scripts/selection_rules.py --quick --cache "$OUT/selcache" "$d"
done
# the same hold in the graph and the runtime (`pt_select_hold` 2), every held-out drive run with it
# and, on the same CPU, with the bundled model as it ships: not shipped (static mean above the
# classical mode's; docs/model-card.md, "The choice held for a few pairs")
"$D3LVO" export --ckpt d3lvo_deploy/default_model/default.pt --out "$OUT/hold_2" --overwrite --set pt_select_hold=2
for d in "$OUT"/data/heldout_?? "$OUT"/data/static_2?? "$OUT"/data/traffic_3?? "$OUT"/data/own_91? "$OUT"/data/demo_909; do
  "$D3LVO" run "$d" --onnx "$OUT/hold_2" --backend onnxruntime --threads 1 --out "$OUT/eval/hold_2_$(basename "$d").txt" \
    --overwrite
  "$D3LVO" run "$d" --backend onnxruntime --threads 1 --out "$OUT/eval/hold_0_$(basename "$d").txt" --overwrite
  for h in hold_2 hold_0; do
    "$D3LVO" eval --gt "$d/poses.txt" --est "$OUT/eval/${h}_$(basename "$d").txt" --json
  done
done
"$D3LVO" run ../shared/data/kitti_raw_snippet/sequences/r0926 --onnx "$OUT/hold_2" --backend onnxruntime \
  --out "$OUT/eval/hold_2_real.txt" --overwrite
