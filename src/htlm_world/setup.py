"""Packaging of htlm_world: an ament_python package that also installs with plain pip."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "htlm_world"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={PACKAGE: ["scenarios/*.yaml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/scenarios", sorted(glob(f"{PACKAGE}/scenarios/*.yaml"))),
    ],
    # What htlm_world imports at run time, beyond the standard library. rclpy (ros/world_node only) comes from the
    # ROS 2 Jazzy wheels or a ROS install (package.xml); htlm_msgs_py is the sibling package of this repository
    # (not on PyPI): install the three together, as setup.sh does.
    install_requires=[
        "numpy>=1.26,<3",  # the model's tables, the simulator, the metrics
        "pyyaml>=6",  # scenario files
    ],
    python_requires=">=3.11",
    zip_safe=False,
    maintainer="HTLM maintainers",
    maintainer_email="htlm@example.com",
    description="HTLM operation model: scenarios, transition/observation/channel models, simulator, world node.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "world_node = htlm_world.ros.world_node:main",
            "robot_node = htlm_world.ros.robot_node:main",
            "robots_node = htlm_world.ros.robots_node:main",
            "operation_node = htlm_world.ros.operation_node:main",
        ],
    },
)
