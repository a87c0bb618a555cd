"""The trainer process's core without ROS (`core.TrainerCore`): above the learning loop and the experiments' validation
it uses; its node (htlm_agent.ros.trainer_node) only moves messages."""
