#!/usr/bin/env bash
# Entry point of the HTLM image: source ROS 2 Jazzy and the HTLM workspace, then start a team (default: train).
# No `set -u`: the ROS setup scripts read unset variables.
set -eo pipefail
source /opt/ros/jazzy/setup.bash
source /htlm/ros_ws/install/setup.bash
cd /htlm
if [ "$#" -eq 0 ]; then
  set -- train
fi
exec ./launch_scripts/team.sh "$@"
