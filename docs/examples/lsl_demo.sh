#!/bin/sh
# unshare -rn sh docs/examples/lsl_demo.sh [FOLDER]: simulated fingertip -> daemon -> tactiled lsl -> an inlet, all in FOLDER
set -e
PIDS=
DIR=${1:-$(mktemp -d)}
mkdir -p "$DIR"
ip link set lo up   # a private network namespace: LSL discovery stays on this machine
tactiled simulate serial --link "$DIR/tty" --speed 2 --seconds 60 --drop 0.002 & PIDS="$PIDS $!"
tactiled run --port "$DIR/tty" --publish "ipc://$DIR/pub" --samples & PIDS="$PIDS $!"
tactiled lsl --connect "ipc://$DIR/pub" & PIDS="$PIDS $!"
timeout 60 python "$(dirname "$0")/lsl_inlet.py"
kill $PIDS
wait
