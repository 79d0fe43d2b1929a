#!/bin/sh
# unshare -rn sh docs/examples/ros2_demo.sh [FOLDER]: simulated fingertip -> daemon -> tactiled ros2 -> a subscriber, all in FOLDER
set -e
PIDS=
DIR=${1:-$(mktemp -d)}
mkdir -p "$DIR"
ip link set lo up   # a private network namespace: DDS discovery stays on this machine
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
tactiled simulate serial --link "$DIR/tty" --speed 2 --seconds 60 & PIDS="$PIDS $!"
tactiled run --port "$DIR/tty" --publish "ipc://$DIR/pub" --samples & PIDS="$PIDS $!"
tactiled ros2 --connect "ipc://$DIR/pub" --ros-args -r __ns:=/robot1 & PIDS="$PIDS $!"
timeout 60 python "$(dirname "$0")/ros2_listen.py"
kill $PIDS
wait
