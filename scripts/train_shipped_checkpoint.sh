#!/usr/bin/env bash
# How the shipped checkpoint (rtv3_maniskill/checkpoints/rtv3_grasp_clutter) is made:
# planner demonstrations -> LeRobot dataset -> lerobot-train -> copy of the last checkpoint.
# CPU only; STEPS and BATCH trade time for quality (defaults: what the shipped one used).
set -euo pipefail
cd "$(dirname "$0")/.."
SCENES=${SCENES:-104}   # the shipped checkpoint: scenes 100000..100103, 688 trajectories
STEPS=${STEPS:-2000}
BATCH=${BATCH:-64}
bash scripts/setup.sh
.venv/bin/rtv3 generate --num-scenes "$SCENES" --output data/train --seed 1 --grasps-per-scene 16 --num-points 512
rm -rf outputs/train_shipped
OMP_NUM_THREADS=${OMP_NUM_THREADS:-2} .venv/bin/lerobot-train --policy.type=rtv3 \
    --dataset.repo_id=local/rtv3_grasp_clutter --dataset.root=data/train \
    --policy.push_to_hub=false --policy.device=cpu --wandb.enable=false \
    --steps="$STEPS" --batch_size="$BATCH" --num_workers=1 --save_freq=500 --log_freq=50 \
    --output_dir=outputs/train_shipped
rm -rf rtv3_maniskill/checkpoints/rtv3_grasp_clutter
mkdir -p rtv3_maniskill/checkpoints
cp -r outputs/train_shipped/checkpoints/last/pretrained_model rtv3_maniskill/checkpoints/rtv3_grasp_clutter
