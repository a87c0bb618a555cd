"""The agent process's core without ROS (`core.AgentSession`): its side of the protocol around its `AgentMind`, with
its parts each in a module (the trainer's weights, the outbox, the deployed team's step clock, the clock offsets,
the robot's arrival, the records it writes), above the baselines and the learning it chooses its policy from; its
node (htlm_agent.ros.agent_node) only moves messages."""
