#!/usr/bin/env bash
# Start a team over ROS 2: the world, one process per agent and the trainer, each with its own log file (with
# --robots sim also a simulated robot per agent and their stand-in operation).
#
#   launch_scripts/team.sh train                       # train a few episodes over ROS, then evaluate the result
#   launch_scripts/team.sh evaluate --checkpoint DIR   # evaluate a checkpoint of `htlm train`
#   launch_scripts/team.sh deploy --checkpoint DIR     # run until Ctrl-C
#   launch_scripts/team.sh deploy --checkpoint DIR --robots sim   # external world + a simulated robot per agent
#   launch_scripts/team.sh --help                      # every option (domain id, discovery, other hosts, keys)
#
# Discovery stays on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) on ROS_DOMAIN_ID 42 unless told
# otherwise. Ctrl-C stops every process; the exit code says how the run ended (0 finished, 1 a process failed,
# 2 bad arguments, 124 timeout, 130 Ctrl-C, 143 SIGTERM). All options are those of `htlm launch`.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ -x .venv/bin/htlm ]; then
  exec .venv/bin/htlm launch "$@"
elif [ -x .venv/bin/python ]; then
  exec .venv/bin/python -m htlm_agent.cli launch "$@"
else
  exec python3 -m htlm_agent.cli launch "$@"
fi
