"""The agent process's core without ROS (`core.AgentSession`): its side of the protocol around its `AgentMind`, above
the baselines and the learning it chooses its policy from; its node (htlm_agent.ros.agent_node) only moves
messages."""
