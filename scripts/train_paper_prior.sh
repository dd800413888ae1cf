#!/usr/bin/env bash
# The prior for the paper preset, trained from scratch on paper-like scenes, from a clean clone:
#
#   1. chunks of planner demonstrations (rtv3 generate, CHUNK_SCENES: the scenes of each, seed blocks 31,
#      32, ...; 31 is also the pilot's): the paper preset's packed layout with objects from the YCB-sized,
#      procedural and pybullet sets (OBJECTS; the validation and test scenes hold only the 12 YCB objects), starts drawn
#      around the ready pose as the authors do, free-space clearance CLEARANCE (chosen by
#      the pilot in docs/RESULTS.md); after each chunk the prior trains on every chunk so far through the
#      compact cache (chunk 1: from scratch, STEPS0 steps; then STEPS more from the previous stage);
#   2. a DAgger round after each chunk named in DAGGER_AFTER (rounds 1, 2, ... in seed blocks 51, 52, ...),
#      from the stage before: that prior rolls out alone and under RT-V3 (the preset's fusion) with the
#      noisy and single-DoF users, the planner re-plans from the visited states (most from the second after
#      a failed rollout's closest approach to the pre-grasp: from scratch the prior's failures are mostly
#      runaways, whose last second lies far out of reach), and the prior trains STEPS more steps on every
#      demonstration and relabel so far
#      (rounds between the chunks: more demonstrations alone left the validation SR flat, docs/RESULTS.md);
#   3. a last stage, LONG_STEPS more steps on every demonstration and relabel;
#   4. every stage is evaluated on the validation block (seed 8, never the test block 9): planning
#      (rtv3 evaluate planning --preset paper, EVAL_SCENES scenes) and RT-V3 with the noisy and single-DoF
#      users (rtv3 benchmark-shared --preset paper, SHARED_SCENES scenes, 8 goals each), as is the shipped
#      prior once (OUT/reference, with Direct beside it); rtv3 learning-curve adds each stage to
#      OUT/curve.csv and OUT/curve.png (validation SRs against trajectories seen, wins / losses against
#      the shipped prior on the same trials); the stage with the best mean validation SR is copied to
#      OUT/final.
# Every step resumes when rerun (generation and DAgger skip finished scenes, training goes on from its
# last checkpoint, a finished evaluation is kept) and is skipped when its output is complete. Run it
# from a git worktree at a fixed commit so that work on main cannot change a running job:
#   git worktree add ../rtv3-paper-prior HEAD && cd ../rtv3-paper-prior && nohup bash scripts/train_paper_prior.sh &
# Started in a session of its own (setsid), `nice` does not make it yield to other work on Linux's
# per-session scheduling (autogroups); lower its whole session instead: echo 19 > /proc/PID/autogroup.
# Environment: CHUNK_SCENES, DAGGER_AFTER, DAGGER_SCENES, STEPS0, STEPS, LONG_STEPS, BATCH, WORKERS, EVAL_SCENES,
# SHARED_SCENES, CLEARANCE, DEVICE (cpu or cuda), OUT trade time for quality; MIN_FREE_GB (20) stops it before the disk fills
# (each stage's compact cache is removed once the stage is trained).
set -euo pipefail
cd "$(dirname "$0")/.."
CHUNK_SCENES=${CHUNK_SCENES:-200 300 500 1000 1000}
DAGGER_AFTER=${DAGGER_AFTER:-2 3 4}
DAGGER_SCENES=${DAGGER_SCENES:-300}
STEPS0=${STEPS0:-6000}
STEPS=${STEPS:-4000}
LONG_STEPS=${LONG_STEPS:-24000}
MIN_FREE_GB=${MIN_FREE_GB:-20}
BATCH=${BATCH:-64}
WORKERS=${WORKERS:-2}
EVAL_SCENES=${EVAL_SCENES:-100}
SHARED_SCENES=${SHARED_SCENES:-20}
CLEARANCE=${CLEARANCE:-0.03}
DEVICE=${DEVICE:-cpu}
OUT=${OUT:-outputs/paper_prior}
OBJECTS=ycb+procedural+random_urdfs
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
mkdir -p data/paper_prior "$OUT"
rtv3=.venv/bin/rtv3
# A fresh RTV3Config in the shipped prior's architecture, with its closed-loop regularisers.
fresh=(--set point_stem_poolings=0 --set num_points=512 --set rotation_conditioning='"sampled"'
       --set twist_noise_linear=0.05 --set twist_noise_angular=0.25 --set history_rotation_resample_prob=0.5)

stage() {  # NAME INIT(fresh|checkpoint) STEPS LR DATASETS... -> OUT/NAME/run/checkpoints/last, evaluated
  local name=$1 init=$2 steps=$3 lr=$4; shift 4
  local dir=$OUT/$name roots=() start=()
  for d in "$@"; do roots+=(--dataset.root "$d"); done
  if [[ $init == fresh ]]; then start=("${fresh[@]}"); else start=(--policy.path "$init"); fi
  mkdir -p "$dir"
  if [[ ! -f $dir/finished ]]; then
    enough_disk
    [[ -f $dir/cache/summary.json ]] || $rtv3 compact-cache build "${roots[@]}" --output "$dir/cache" \
        --max-mib 8000 "${start[@]}"
    $rtv3 compact-cache train --cache "$dir/cache" --output "$dir/run" --steps "$steps" --batch-size "$BATCH" \
        --save-freq 500 --log-freq 250 --device "$DEVICE" --lr "$lr" --lr-decay 0.9995 --min-lr 1e-5
    $rtv3 compact-cache finish "$dir/run/checkpoints/last"
    touch "$dir/finished"
  fi
  # Each stage builds its own cache of every dataset so far: once trained, only its summary is kept.
  for f in "$dir"/cache/*; do [[ $f == */summary.json ]] || rm -rf "$f"; done
  validate "$dir/run/checkpoints/last" "$dir" rtv3
  $rtv3 learning-curve "$OUT"
}

validate() {  # CHECKPOINT DIR METHODS: the validation block's planning trials and shared-control rows
  local checkpoint=$1 dir=$2 methods=$3
  # (a summary from before the arm-reach check gains it: the rerun checks the targets, runs no trial again)
  grep -qs '"arm_reachable"' "$dir/planning/planning_summary.json" || $rtv3 evaluate planning --preset paper --seed 8 \
      --scenes "$EVAL_SCENES" --policy.path "$checkpoint" --output "$dir/planning"
  [[ -f $dir/shared/summary.csv ]] || $rtv3 benchmark-shared --preset paper --seed 8 --scenes "$SHARED_SCENES" \
      --goals-per-scene 8 --users noisy,single_dof --methods "$methods" --policy.path "$checkpoint" \
      --workers "$WORKERS" --output "$dir/shared"
}

enough_disk() {  # stop (resumably) before the disk fills: MIN_FREE_GB must stay free for everything else
  local free_gb=$(( $(df -Pk . | awk 'NR==2 {print $4}') / 1048576 ))
  if (( free_gb < MIN_FREE_GB )); then
    echo "train_paper_prior: only ${free_gb} GB free on $(pwd), below MIN_FREE_GB=${MIN_FREE_GB}: stopping; free some and rerun" >&2
    exit 1
  fi
}

generated() {  # FOLDER SCENES: whether rtv3 generate has finished SCENES scenes there
  [[ -f $1/rtv3_summary.json ]] && (( $(.venv/bin/python -c \
      'import json, sys; print(json.load(open(sys.argv[1]))["scenes"])' "$1/rtv3_summary.json") >= $2 ))
}

dagger_round() {  # R: relabels from the current prior's rollouts, then a stage on everything so far
  local r=$1 relabels=data/paper_prior/dagger_$1
  if [[ ! -f $relabels/rtv3_summary.json ]]; then
    enough_disk
    $rtv3 dagger --preset paper --objects "$OBJECTS" --clearance "$CLEARANCE" \
        --policy.path "$prior" --output "$relabels" --num-scenes "$DAGGER_SCENES" --seed $((50 + r)) \
        --drivers prior,rtv3:noisy,rtv3:single_dof,prior --targets-per-scene 8 --relabels-per-rollout 1 \
        --failure-relabels 4 --failure-window drift --workers "$WORKERS"
  fi
  datasets+=("$relabels")
  stage "dagger_$r" "$prior" "$STEPS" 3e-4 "${datasets[@]}"
  prior=$OUT/dagger_$r/run/checkpoints/last
}

# The prior to beat: the shipped checkpoint on the same validation trials, with Direct beside RT-V3.
validate rtv3_maniskill/checkpoints/rtv3_grasp_clutter "$OUT/reference" direct,rtv3
datasets=()
prior=fresh
c=0
r=0
for scenes in $CHUNK_SCENES; do
  c=$((c + 1))
  chunk=data/paper_prior/demos_$c
  if ! generated "$chunk" "$scenes"; then
    enough_disk
    $rtv3 generate --preset paper --objects "$OBJECTS" --clearance "$CLEARANCE" \
        --num-scenes "$scenes" --seed $((30 + c)) --output "$chunk" --end-at pregrasp --grasps-per-scene 16 \
        --num-points 512 --workers "$WORKERS"
  fi
  datasets+=("$chunk")
  if [[ $prior == fresh ]]; then
    stage "demos_$c" fresh "$STEPS0" 1e-3 "${datasets[@]}"
  else
    stage "demos_$c" "$prior" "$STEPS" 3e-4 "${datasets[@]}"
  fi
  prior=$OUT/demos_$c/run/checkpoints/last
  for after in $DAGGER_AFTER; do
    if (( after == c )); then r=$((r + 1)); dagger_round "$r"; fi
  done
done
# Then LONG_STEPS more on everything: the stages above add STEPS each, which may leave the prior short of
# steps rather than of data (the curve flattened while the data grew tenfold).
if (( LONG_STEPS > 0 )); then
  stage long "$prior" "$LONG_STEPS" 3e-4 "${datasets[@]}"
fi
best=$($rtv3 learning-curve "$OUT" --best)
mkdir -p "$OUT/final"
cp "$best/"{config.json,model.safetensors} "$OUT/final/"
echo "paper prior: $OUT/final (from $best)"
