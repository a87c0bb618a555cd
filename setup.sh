#!/usr/bin/env bash
# Create .venv and install everything HTLM needs. Safe to run twice: a second run with nothing changed returns at
# once (the stamp .venv/.setup-stamp is newer than every file that decides what gets installed).
# Environment: PYTHON (interpreter for the venv, default python3), HTLM_SETUP_FORCE=1 (reinstall anyway).
set -euo pipefail
cd "$(dirname "$0")"
PY=${PYTHON:-python3}
STAMP=.venv/.setup-stamp
# What gets installed, in this order (tests/test_packaging.py reads TORCH, ROS_WHEELS and PACKAGES from here to build
# a fresh venv of the packages alone). Each package declares its own run-time dependencies (setup.py
# install_requires); requirements-dev.txt adds the development tools only.
# torch is pinned: a CPU build of 2.13.0 is on this machine's disk; an unpinned torch pulls a multi-GB CUDA build.
TORCH="torch==2.13.0"
ROS_WHEELS=("ros-jazzy-rclpy[fastrtps]" ros-jazzy-common-interfaces)
PACKAGES=(src/htlm_msgs_py src/htlm_world src/htlm_agent)
INPUTS=(setup.sh requirements-dev.txt src/*/setup.py src/*/setup.cfg)

up_to_date() {
  [ -x .venv/bin/python ] && [ -f "$STAMP" ] || return 1
  local f
  for f in "${INPUTS[@]}"; do
    [ "$f" -nt "$STAMP" ] && return 1
  done
  return 0
}

if [ "${HTLM_SETUP_FORCE:-0}" != 1 ] && up_to_date; then
  echo "setup: up to date (.venv; HTLM_SETUP_FORCE=1 to reinstall)"
  exit 0
fi

if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
rm -f "$STAMP"
. .venv/bin/activate
export PIP_DISABLE_PIP_VERSION_CHECK=1
python -m pip install -q --upgrade pip
python -m pip install -q "$TORCH"
python -m pip install -q "${ROS_WHEELS[@]}"
python -m pip install -q -r requirements-dev.txt
editable=()
for p in "${PACKAGES[@]}"; do editable+=(-e "$p"); done
python -m pip install -q "${editable[@]}"
touch "$STAMP"
echo "setup: done (.venv ready; activate with: . .venv/bin/activate)"
