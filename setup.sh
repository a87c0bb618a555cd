#!/usr/bin/env bash
# Create .venv and install everything HTLM needs. Safe to run twice.
set -euo pipefail
cd "$(dirname "$0")"
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
. .venv/bin/activate
export PIP_DISABLE_PIP_VERSION_CHECK=1
python -m pip install -q --upgrade pip
# torch is pinned: a CPU build of 2.13.0 is on this machine's disk; an unpinned torch pulls a multi-GB CUDA build.
python -m pip install -q "torch==2.13.0"
python -m pip install -q "ros-jazzy-rclpy[fastrtps]" ros-jazzy-common-interfaces
python -m pip install -q -r requirements-dev.txt
python -m pip install -q -e src/htlm_msgs_py -e src/htlm_world -e src/htlm_agent
echo "setup: done (.venv ready; activate with: . .venv/bin/activate)"
