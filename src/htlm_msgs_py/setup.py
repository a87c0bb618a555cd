"""Packaging of htlm_msgs_py: an ament_python package that also installs with plain pip."""

from setuptools import find_packages, setup

PACKAGE = "htlm_msgs_py"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={PACKAGE: ["fastdds.xml", "fastdds_loopback.xml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml", f"{PACKAGE}/fastdds.xml", f"{PACKAGE}/fastdds_loopback.xml"]),
    ],
    install_requires=["msgspec>=0.18", "numpy>=1.26,<3"],  # numpy: the binary arrays of the bulk records
    python_requires=">=3.11",
    zip_safe=False,
    maintainer="HTLM maintainers",
    maintainer_email="htlm@example.com",
    description="HTLM wire contract: topic names, QoS profiles, validated message schemas on standard interfaces.",
    license="Apache-2.0",
)
