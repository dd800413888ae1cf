#!/usr/bin/env bash
# Idempotent set-up for a fresh Debian 12 / Python 3.11 machine, with or without a GPU.
#   1. a virtual environment in ./.venv with the project and its LeRobot plugin
#      (plugins/lerobot_policy_rtv3: outside the repository root, so that Python started
#      there cannot mistake the folder for the installed package);
#   2. only when SAPIEN finds no usable Vulkan device: Mesa's software Vulkan driver
#      (lavapipe >= 24.3, from Debian's bookworm-backports suite), which ManiSkill needs
#      to render point clouds on a machine without a GPU.
# Usage: bash scripts/setup.sh [--dev]
set -euo pipefail
cd "$(dirname "$0")/.."
extras=""
[[ "${1:-}" == "--dev" ]] && extras="[dev]"

log() { printf '\033[1m[setup]\033[0m %s\n' "$*" >&2; }

PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null || PY=python3
if [[ ! -x .venv/bin/python ]]; then
  log "creating virtual environment .venv ($($PY --version))"
  "$PY" -m venv .venv
fi
stamp=.venv/.rtv3-installed
plugin=plugins/lerobot_policy_rtv3
# The stamp covers both pyprojects and the plugin's path (an install from an old path is redone).
want="$( (cat pyproject.toml $plugin/pyproject.toml; echo $plugin) | sha1sum | cut -c1-16)${extras}"
have="$(cat $stamp 2>/dev/null || true)"
# An install with the test extras also serves a plain set-up (the demo after the tests).
if [[ "$have" != "$want" && ! ( -z "$extras" && "$have" == "${want}[dev]" ) ]]; then
  # torch 2.10 from PyPI brings its CUDA libraries: the finished .venv is ~10 GB. Fail early
  # with the numbers rather than halfway through pip with "No space left on device".
  free_mb=$(( $(df -Pk . | awk 'NR==2 {print $4}') / 1024 ))
  venv_mb=$(du -sm .venv | cut -f1)
  if (( free_mb + venv_mb < 10500 )); then
    log "ERROR: not enough disk space for .venv: it needs ~10.5 GB, and $(pwd) has ${free_mb} MB free (+ ${venv_mb} MB already in .venv)"
    exit 1
  fi
  log "installing rtv3-maniskill${extras} and its pinned dependencies into .venv (first time: several minutes, ~5 GB of wheels, ~10 GB installed)"
  # pip's errors reach the terminal; its notes about index locations this machine's pip configuration names
  # but lacks do not, nor the build backend's Python warnings about editable installs (they read like failures).
  pip_quiet() {
    PYTHONWARNINGS=ignore .venv/bin/pip install --quiet "$@" 2>&1 \
      | { grep -v "^WARNING: Location '.*' is ignored" || true; } >&2
    return "${PIPESTATUS[0]}"
  }
  pip_quiet --upgrade "pip>=24"
  pip_quiet -e ".${extras}"
  pip_quiet --no-deps -e "./$plugin"
  echo "$want" > $stamp
fi

vulkan_ok() {
  .venv/bin/python - <<'PY' >/dev/null 2>&1
import sapien
sapien.render.RenderSystem()   # raises "failed to find a rendering device" without Vulkan
PY
}

if ! vulkan_ok; then
  log "no usable Vulkan device: installing Mesa's software Vulkan driver (lavapipe) from bookworm-backports;"
  log "ManiSkill renders point clouds through Vulkan, and Debian 12's own Mesa 22.3 is too old for SAPIEN."
  SUDO=""; [[ $(id -u) -ne 0 ]] && SUDO="sudo"
  src=/etc/apt/sources.list.d/rtv3-bookworm-backports.sources
  if [[ ! -f $src ]]; then
    # Reuse the machine's own Debian mirror: copy its first Debian URI, change the suite.
    uri=$(grep -h '^URIs:' /etc/apt/sources.list.d/*.sources 2>/dev/null | grep -v security | head -1 | awk '{print $2}')
    if [[ -z "$uri" ]]; then
      uri=$(grep -hE '^deb ' /etc/apt/sources.list 2>/dev/null | grep -v security | head -1 | awk '{print $2}')
    fi
    [[ -n "$uri" ]] || { log "ERROR: found no Debian apt source to derive bookworm-backports from"; exit 1; }
    printf 'Types: deb\nURIs: %s\nSuites: bookworm-backports\nComponents: main\nSigned-By: /usr/share/keyrings/debian-archive-keyring.gpg\n' "$uri" | $SUDO tee $src >/dev/null
  fi
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq -t bookworm-backports mesa-vulkan-drivers libvulkan1 >/dev/null
  if ! vulkan_ok; then
    log "ERROR: SAPIEN still finds no Vulkan device after installing lavapipe"; exit 1
  fi
  log "software Vulkan (lavapipe) is working"
fi

# --dev: the keyboard-session test drives the `rtv3 teleop` window under a virtual X server.
if [[ -n "$extras" ]]; then
  missing=""
  for tool in Xvfb:xvfb xdotool:xdotool; do
    command -v "${tool%%:*}" >/dev/null || missing="$missing ${tool##*:}"
  done
  if [[ -n "$missing" ]]; then
    log "installing$missing (the teleop test sends key presses to a window on a virtual display)"
    SUDO=""; [[ $(id -u) -ne 0 ]] && SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $missing >/dev/null
  fi
fi
