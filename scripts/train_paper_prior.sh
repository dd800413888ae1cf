#!/usr/bin/env bash
# The prior for the paper preset (YCB-sized packed scenes, every floating-hand goal), from a clean clone:
#
#   1. planner demonstrations on paper-preset scenes (rtv3 generate --preset paper, seed block 21:
#      scenes 2100000..; starts drawn around the ready pose as the authors do);
#   2. ROUNDS DAgger rounds, each started from the prior before it (round 1: the shipped prior):
#      roll that prior out on fresh paper-preset scenes (seed block 22 + r) alone and under RT-V3
#      (the preset's fusion) with the noisy and single-DoF users, re-plan with the motion planner
#      from visited states (most of them from the last second of failed rollouts), then fine-tune
#      that prior on the demonstrations and every round's relabels so far, through the compact cache
#      (rtv3 compact-cache build / train / finish; CPU or, with DEVICE=cuda, a GPU), checkpoints
#      every SAVE_FREQ steps. The demonstrations alone push the arm into the table (docs/RESULTS.md,
#      "A prior for these scenes"); the relabels show it the recoveries from its own states;
#   3. the last round's last checkpoint is the paper prior (OUT/final).
# Validation uses seed block 8 (rtv3 evaluate planning --preset paper --seed 8; rtv3 benchmark-shared
# --preset paper --seed 8), never the test block 9.
# Every step resumes when rerun (generation and DAgger skip finished scenes, training goes on from
# its last checkpoint) and is skipped when its output is complete. Run it from a git worktree at a
# fixed commit so that work on main cannot change a running job:
#   git worktree add ../rtv3-paper-prior HEAD && cd ../rtv3-paper-prior && nohup bash scripts/train_paper_prior.sh &
# Environment: GEN_SCENES, DAGGER_SCENES, ROUNDS, STEPS, LR, BATCH, SAVE_FREQ, WORKERS, DEVICE, OUT trade
# time for quality.
set -euo pipefail
cd "$(dirname "$0")/.."
GEN_SCENES=${GEN_SCENES:-250}
DAGGER_SCENES=${DAGGER_SCENES:-150}
ROUNDS=${ROUNDS:-2}
STEPS=${STEPS:-1500}
LR=${LR:-1e-4}
BATCH=${BATCH:-64}
SAVE_FREQ=${SAVE_FREQ:-250}
WORKERS=${WORKERS:-1}
DEVICE=${DEVICE:-cpu}
OUT=${OUT:-outputs/paper_prior}
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
bash scripts/setup.sh
# LeRobot reads datasets through Hugging Face `datasets`, which keeps an uncompressed copy of each one in
# ~/.cache/huggingface/datasets for good; unless HF_DATASETS_CACHE is set, this recipe keeps its copies in
# outputs/hf_datasets_cache and removes them when it ends.
if [[ -z ${HF_DATASETS_CACHE:-} ]]; then
  export HF_DATASETS_CACHE="$PWD/outputs/hf_datasets_cache"
  mkdir -p "$HF_DATASETS_CACHE"
  trap 'rm -rf "$HF_DATASETS_CACHE"' EXIT
fi
mkdir -p data "$OUT"
rtv3=.venv/bin/rtv3

$rtv3 generate --preset paper --num-scenes "$GEN_SCENES" --output data/paper_demos --end-at pregrasp \
    --grasps-per-scene 16 --num-points 512 --seed 21 --workers "$WORKERS"

fine_tune() {  # NAME INIT STEPS DATASETS... -> OUT/NAME (cache, run)
  local name=$1 init=$2 steps=$3; shift 3
  local roots=()
  for d in "$@"; do roots+=(--dataset.root "$d"); done
  [[ -f $OUT/$name/cache/summary.json ]] || $rtv3 compact-cache build "${roots[@]}" --output "$OUT/$name/cache" \
      --policy.path "$init"
  $rtv3 compact-cache train --cache "$OUT/$name/cache" --output "$OUT/$name/run" --steps "$steps" \
      --batch-size "$BATCH" --save-freq "$SAVE_FREQ" --device "$DEVICE" --lr "$LR" --lr-decay 0.998 --min-lr 1e-5
  $rtv3 compact-cache finish "$OUT/$name/run/checkpoints/last"
}

prior=rtv3_maniskill/checkpoints/rtv3_grasp_clutter
datasets=(data/paper_demos)
for ((r = 1; r <= ROUNDS; r++)); do
  $rtv3 dagger --preset paper --policy.path "$prior" --output "data/paper_dagger_r$r" \
      --num-scenes "$DAGGER_SCENES" --seed $((22 + r)) --drivers prior,rtv3:noisy,rtv3:single_dof,prior \
      --targets-per-scene 4 --relabels-per-rollout 1 --failure-relabels 4 --workers "$WORKERS"
  datasets+=("data/paper_dagger_r$r")
  fine_tune "round$r" "$prior" "$STEPS" "${datasets[@]}"
  prior="$OUT/round$r/run/checkpoints/last"
done
mkdir -p "$OUT/final"
cp "$prior/"{config.json,model.safetensors} "$OUT/final/"
echo "paper prior: $OUT/final"
