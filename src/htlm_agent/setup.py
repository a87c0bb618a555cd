"""Packaging of htlm_agent: an ament_python package that also installs with plain pip."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "htlm_agent"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={"htlm_agent.people": ["*.html"]},  # the pages of a person in the team and of the commander
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/launch", sorted(glob("launch/*.launch.py"))),  # ros2 launch htlm_agent team.launch.py
    ],
    # What htlm_agent imports at run time, beyond the standard library:
    # - torch (learning/, the Q-networks) is deliberately absent: an unpinned torch pulls a multi-GB CUDA build.
    #   setup.sh (or the Dockerfile) installs the pinned CPU build torch==2.13.0 first.
    # - rclpy (ros/ only) comes from the ROS 2 Jazzy wheels or a ROS install, like every ROS interface (package.xml).
    # - htlm_world and htlm_msgs_py are the sibling packages of this repository (not on PyPI): install the three
    #   together, as setup.sh does (`pip install src/htlm_msgs_py src/htlm_world src/htlm_agent`).
    install_requires=[
        "numpy>=1.26,<3",  # everywhere
        "pyyaml>=6",  # learner settings files, run files (scenario.yaml), evaluation reports
        "matplotlib>=3.8",  # evaluation histograms, reproduction figures, episode pictures
        "rich>=13",  # progress displays, `htlm watch`
        "tensorboard>=2.15",  # torch.utils.tensorboard in `htlm train`
        "pettingzoo>=1.24",  # runtime/pz_env.py, the PettingZoo ParallelEnv
        "gymnasium>=0.29",  # its observation and action spaces
        "rosbags>=0.11",  # experiments/recording.py: `htlm launch --record` writes and reads ROS 2 bags (MCAP)
        "starlette>=0.40",  # people/web.py: the API and pages of the people in the team and of the commander
        "uvicorn>=0.30",  # ... served in a thread of the agent's process
    ],
    python_requires=">=3.11",
    zip_safe=False,
    maintainer="HTLM maintainers",
    maintainer_email="htlm@example.com",
    description="HTLM agent mind: belief filter, reward, DQN learner, baselines, agent/trainer nodes, htlm CLI.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "agent_node = htlm_agent.ros.agent_node:main",
            "agents_node = htlm_agent.ros.agents_node:main",
            "trainer_node = htlm_agent.ros.trainer_node:main",
            "record_node = htlm_agent.ros.record_node:main",
            "htlm = htlm_agent.cli:main",
        ],
    },
)
