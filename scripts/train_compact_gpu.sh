#!/usr/bin/env bash
# The GPU recipe's one command, run on the GPU machine (PyTorch with CUDA is all it needs: no LeRobot,
# ManiSkill or network). Copy the repository and a cache folder made here with
#   rtv3 compact-cache build --dataset.root DATA --output CACHE [--policy.path CKPT] [--max-mib 60]
# to that machine, then there:
#   bash scripts/train_compact_gpu.sh CACHE RUN [compact-cache train flags, e.g. --steps 5000 --batch-size 2048]
# It prints the machine, times $THROUGHPUT_STEPS (150) training steps at each batch size of
# $THROUGHPUT_BATCHES (default "64 512"; none with THROUGHPUT_BATCHES=""), then trains into RUN
# (resumable: rerun the same command) and, with $OUT set, copies config.json, each checkpoint's
# weights (model_NNNNNN.safetensors) and the logs there. Bring RUN/checkpoints/last back (or
# config.json with one model_NNNNNN.safetensors renamed model.safetensors) and run
# `rtv3 compact-cache finish FOLDER` to make it a LeRobot pretrained_model folder.
# DEVICE (default cuda) picks another torch device, PYTHON another interpreter.
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ $# -lt 2 ]]; then
  echo "usage: bash scripts/train_compact_gpu.sh CACHE RUN [train flags]" >&2
  exit 2
fi
cache=$1 run=$2
shift 2
PY=${PYTHON:-python3}
DEVICE=${DEVICE:-cuda}
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
train() { "$PY" -m rtv3_maniskill.cli.compact_cache train --cache "$cache" --device "$DEVICE" "$@"; }
"$PY" - "$DEVICE" <<'PYEOF'
import sys, torch
device = torch.device(sys.argv[1])
name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
print(f"torch {torch.__version__}, device {device}: {name}")
if device.type == "cuda" and not torch.cuda.is_available():
    sys.exit("error: DEVICE=cuda but torch sees no CUDA device")
PYEOF
logs=$(mktemp -d)
for batch in ${THROUGHPUT_BATCHES-64 512}; do
  train --output "$logs/throughput_$batch" --steps "${THROUGHPUT_STEPS:-150}" --batch-size "$batch" --log-freq 25 --save-freq 1000000 \
    | tee "$logs/throughput_b$batch.json"
  rm -rf "$logs/throughput_$batch"
done
train --output "$run" "$@" | tee "$logs/train.json"
if [[ -n ${OUT:-} ]]; then  # every saved checkpoint's weights (choose --save-freq accordingly) and the logs
  cp "$run/checkpoints/last/config.json" "$OUT/"
  for ckpt in "$run"/checkpoints/[0-9]*; do
    cp "$ckpt/model.safetensors" "$OUT/model_$(basename "$ckpt").safetensors"
  done
  cat "$logs"/*.json > "$OUT/logs.json"
fi
