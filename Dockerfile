# HTLM on the official ROS 2 Jazzy image (Ubuntu 24.04): the same packages, built with colcon.
#   docker build -t htlm .
#   docker run --rm -it htlm            # ./launch_scripts/team.sh train
#   docker run --rm -it htlm <args>     # ./launch_scripts/team.sh <args>
FROM ros:jazzy

SHELL ["/bin/bash", "-o", "pipefail", "-c"]

RUN apt-get update \
    && apt-get install -y --no-install-recommends \
        python3-pip \
        python3-numpy \
        python3-yaml \
        python3-venv \
        ros-jazzy-diagnostic-msgs \
        ros-jazzy-geometry-msgs \
    && rm -rf /var/lib/apt/lists/*

# The packages' run-time dependencies that colcon does not install (setup.py install_requires; rosdep has no key
# for msgspec, tensorboard, pettingzoo or gymnasium; rosbags, for recordings, comes from PyPI too). torch has no apt package: the pinned CPU build from PyTorch's CPU index (an unpinned torch pulls a CUDA build).
# Ubuntu 24.04 marks the system Python as externally managed (PEP 668), hence --break-system-packages.
RUN pip3 install --no-cache-dir --break-system-packages \
        --index-url https://download.pytorch.org/whl/cpu "torch==2.13.0" \
    && pip3 install --no-cache-dir --break-system-packages \
        "msgspec>=0.18" "matplotlib>=3.8" "tensorboard>=2.15" "pettingzoo>=1.24" "gymnasium>=0.29" "rosbags>=0.11"

COPY . /htlm
WORKDIR /htlm/ros_ws
RUN source /opt/ros/jazzy/setup.bash && colcon build

WORKDIR /htlm
ENTRYPOINT ["/htlm/docker/entrypoint.sh"]
CMD ["train"]
