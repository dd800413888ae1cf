#!/usr/bin/env bash
# The prior for the paper preset (YCB-sized packed scenes, every floating-hand goal), from a clean clone:
#
#   1. planner demonstrations on paper-preset scenes (rtv3 generate --preset paper, seed block 21:
#      scenes 2100000..; starts drawn around the ready pose as the authors do);
#   2. a fine-tune of the shipped prior on them through the compact cache (rtv3 compact-cache build /
#      train / finish; CPU or, with DEVICE=cuda, a GPU), checkpoints every SAVE_FREQ steps;
#   3. a DAgger round on paper-preset scenes (seed block 22) with the planner as the expert, driven by
#      that prior alone and by the noisy and single-DoF users through RT-V3 (aimed at their failures);
#   4. a second fine-tune on both datasets; its last checkpoint is the paper prior (OUT/final).
# Validation uses seed block 8 (rtv3 benchmark-shared --preset paper --seed 8), never the test block 9.
# Every step resumes when rerun (generation and DAgger skip finished scenes, training goes on from
# its last checkpoint) and is skipped when its output is complete. Run it from a git worktree at a
# fixed commit so that work on main cannot change a running job:
#   git worktree add ../rtv3-paper-prior HEAD && cd ../rtv3-paper-prior && nohup bash scripts/train_paper_prior.sh &
# Environment: GEN_SCENES, DAGGER_SCENES, STEPS1, STEPS2, BATCH, SAVE_FREQ, WORKERS, DEVICE, OUT trade time for quality.
set -euo pipefail
cd "$(dirname "$0")/.."
GEN_SCENES=${GEN_SCENES:-400}
DAGGER_SCENES=${DAGGER_SCENES:-100}
STEPS1=${STEPS1:-1500}
STEPS2=${STEPS2:-1500}
BATCH=${BATCH:-64}
SAVE_FREQ=${SAVE_FREQ:-250}
WORKERS=${WORKERS:-1}
DEVICE=${DEVICE:-cpu}
OUT=${OUT:-outputs/paper_prior}
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
bash scripts/setup.sh
# LeRobot reads datasets through Hugging Face `datasets`, which keeps an uncompressed copy of each one
# (0.8 to 12 GB per training set here) in ~/.cache/huggingface/datasets for good. Unless HF_DATASETS_CACHE
# is set, this recipe keeps its copies in outputs/hf_datasets_cache and removes them when it ends.
if [[ -z ${HF_DATASETS_CACHE:-} ]]; then
  export HF_DATASETS_CACHE="$PWD/outputs/hf_datasets_cache"
  mkdir -p "$HF_DATASETS_CACHE"
  trap 'rm -rf "$HF_DATASETS_CACHE"' EXIT
fi
mkdir -p data "$OUT"
rtv3=.venv/bin/rtv3

$rtv3 generate --preset paper --num-scenes "$GEN_SCENES" --output data/paper_demos --end-at pregrasp \
    --grasps-per-scene 16 --num-points 512 --seed 21 --workers "$WORKERS"

fine_tune() {  # INIT DATASETS... -> OUT/NAME (cache, run, final)
  local name=$1 init=$2 steps=$3; shift 3
  local roots=()
  for d in "$@"; do roots+=(--dataset.root "$d"); done
  [[ -f $OUT/$name/cache/summary.json ]] || $rtv3 compact-cache build "${roots[@]}" --output "$OUT/$name/cache" \
      --policy.path "$init" --set optimizer_lr=3e-4
  $rtv3 compact-cache train --cache "$OUT/$name/cache" --output "$OUT/$name/run" --steps "$steps" \
      --batch-size "$BATCH" --save-freq "$SAVE_FREQ" --device "$DEVICE" --lr 3e-4 --lr-decay 0.999 --min-lr 3e-5
  $rtv3 compact-cache finish "$OUT/$name/run/checkpoints/last"
}

fine_tune round1 rtv3_maniskill/checkpoints/rtv3_grasp_clutter "$STEPS1" data/paper_demos
$rtv3 dagger --preset paper --policy.path "$OUT/round1/run/checkpoints/last" --output data/paper_dagger \
    --num-scenes "$DAGGER_SCENES" --seed 22 --drivers prior,rtv3:noisy,rtv3:single_dof,prior \
    --targets-per-scene 4 --relabels-per-rollout 1 --failure-relabels 4 --workers "$WORKERS"
fine_tune round2 "$OUT/round1/run/checkpoints/last" "$STEPS2" data/paper_demos data/paper_dagger
mkdir -p "$OUT/final"
cp "$OUT/round2/run/checkpoints/last/"{config.json,model.safetensors} "$OUT/final/"
echo "paper prior: $OUT/final"
