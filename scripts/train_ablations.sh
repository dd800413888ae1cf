#!/usr/bin/env bash
# Paper Table I at equal compute: the full RT-V3 prior and its three ablations
# (no grasp encoder, no point encoder, joint 6-D Gaussian "6D pred"), each trained from
# scratch through lerobot-train on the same data with the same budget, all four at once
# (one intra-op thread each), so that a wall-clock stop leaves them at comparable steps.
# Every row trains free-running (--policy.teacher_forcing=false): with teacher forcing the
# next twist is predictable from the last one and the full model learns to ignore its
# grasp context (see scripts/train_shipped_checkpoint.sh), which would hide the very
# difference the "no grasp encoder" row measures.
# Then: python scripts/evaluate_ablations.py (prediction on held-out scenes + planning).
# Environment: STEPS (per run), BATCH, DATA (a LeRobot dataset from `rtv3 generate`), STEM (the point
# encoder's stem poolings: 0, the authors' layout, as the README's table was made; 1 is the config default).
set -euo pipefail
cd "$(dirname "$0")/.."
STEPS=${STEPS:-3000}
BATCH=${BATCH:-32}
DATA=${DATA:-data/train}
OUT=${OUT:-outputs/ablations}
STEM=${STEM:-0}
bash scripts/setup.sh
source scripts/datasets_cache.sh
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
mkdir -p "$OUT"
declare -A ROWS=(
    [full]=""
    [no_grasp_encoder]="--policy.use_grasp_encoder=false"
    [no_point_encoder]="--policy.use_point_encoder=false"
    [6d_pred]="--policy.factorized_rotation=false"
)
for row in "${!ROWS[@]}"; do
    # Resume an interrupted run from its last checkpoint; start fresh otherwise.
    if [ -f "$OUT/$row/checkpoints/last/pretrained_model/train_config.json" ]; then
        args=(--config_path="$OUT/$row/checkpoints/last/pretrained_model/train_config.json" --resume=true)
    else
        rm -rf "${OUT:?}/$row"
        # shellcheck disable=SC2206
        args=(--policy.type=rtv3 ${ROWS[$row]} --policy.teacher_forcing=false
              --policy.push_to_hub=false --policy.device=cpu --wandb.enable=false
              --dataset.repo_id=local/rtv3_grasp_clutter --dataset.root="$DATA"
              --batch_size="$BATCH" --steps="$STEPS" --num_workers=1 --save_freq=100 --log_freq=50
              --seed=1 --output_dir="$OUT/$row" --policy.point_stem_poolings="$STEM")
    fi
    .venv/bin/lerobot-train "${args[@]}" >"$OUT/$row.log" 2>&1 &
done
wait
