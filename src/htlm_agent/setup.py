"""Packaging of htlm_agent: an ament_python package that also installs with plain pip."""

from setuptools import find_packages, setup

PACKAGE = "htlm_agent"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
    ],
    # torch is deliberately absent: an unpinned torch pulls a multi-GB CUDA build. setup.sh (or the Dockerfile)
    # installs the pinned CPU build torch==2.13.0 first.
    install_requires=[
        "numpy>=1.26",
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
            "trainer_node = htlm_agent.ros.trainer_node:main",
            "htlm = htlm_agent.cli:main",
        ],
    },
)
