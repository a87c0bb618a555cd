"""The trainer process's core without ROS (`core.TrainerCore`): above the learners it feeds (`htlm_agent.learning`);
its node (htlm_agent.ros.trainer_node) only moves messages."""
