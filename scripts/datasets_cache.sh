# Sourced by the training scripts. LeRobot reads a dataset through Hugging Face `datasets`, which
# keeps an uncompressed Arrow copy of every dataset it loads (0.8 to 12 GB per training set here,
# point clouds included), by default in ~/.cache/huggingface/datasets, where it stays. Unless
# HF_DATASETS_CACHE is set, a training script keeps these copies in outputs/hf_datasets_cache
# and removes them when it ends.
if [[ -z ${HF_DATASETS_CACHE:-} ]]; then
  HF_DATASETS_CACHE="$PWD/outputs/hf_datasets_cache"
  mkdir -p "$HF_DATASETS_CACHE"
  trap 'rm -rf "$HF_DATASETS_CACHE"' EXIT
fi
export HF_DATASETS_CACHE
