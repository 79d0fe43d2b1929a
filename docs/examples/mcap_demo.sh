#!/bin/sh
# sh docs/examples/mcap_demo.sh [FOLDER]: a simulated recording -> MCAP (JSON, and a ROS 2 bag) -> its final labels, all in FOLDER
set -e
HERE=$(cd "$(dirname "$0")" && pwd)
DIR=${1:-$(mktemp -d)}
mkdir -p "$DIR"
cd "$DIR"
tactiled simulate dataset --out data --surfaces Ra2.29 --files-per-surface 1 --slides-per-file 3
tactiled export data/hand_Ra2.29_00.npz -o slides.mcap
tactiled export data/hand_Ra2.29_00.npz -o slides_ros2.mcap --profile ros2
python "$HERE/mcap_read.py"
