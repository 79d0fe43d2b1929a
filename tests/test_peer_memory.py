"""Bounded memory from any peer: thousands of distinct subscriptions cost little, and a peer sending longer ones than any topic is dropped."""

from __future__ import annotations

import contextlib
import subprocess
from collections.abc import Iterator
from pathlib import Path

import zmq
from tactiled_client import BlockingSubscriber, Status

from tests.conftest import tactiled_cmd, wait_for


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as fh:
        return int(next(line for line in fh if line.startswith("VmRSS:")).split()[1]) / 1024


@contextlib.contextmanager
def boardless_daemon(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[bytes], BlockingSubscriber, str]]:
    """``tactiled run`` waiting for a port that does not exist yet (it publishes status), a status subscriber that has seen
    its first status, and its endpoint."""
    endpoint = f"ipc://{tmp_path}/pub"
    proc = subprocess.Popen(tactiled_cmd("run", "--port", str(tmp_path / "no-board-yet"), "--publish", endpoint),
                            stderr=subprocess.DEVNULL)
    try:
        with BlockingSubscriber(endpoint, topics=["status"], timeout=20) as watch:
            wait_for(lambda: isinstance(watch.receive(), Status), timeout=30, what="the daemon's first status")
            yield proc, watch, endpoint
    finally:
        proc.terminate()
        proc.wait(15)


def subscribe_all(endpoint: str, topics: list[bytes]) -> zmq.Socket[bytes]:
    """A peer holding every subscription of ``topics``, returned once the daemon has taken them all (a status came back)."""
    greedy = zmq.Context.instance().socket(zmq.SUB)
    greedy.setsockopt(zmq.LINGER, 0)
    greedy.setsockopt(zmq.RCVTIMEO, 1000)
    greedy.setsockopt(zmq.SNDHWM, 0)  # every subscription reaches the daemon (the default high-water mark drops past 1 000)
    greedy.connect(endpoint)
    for topic in topics:
        greedy.setsockopt(zmq.SUBSCRIBE, topic)
    greedy.setsockopt(zmq.SUBSCRIBE, b"status/")  # subscriptions are taken in order: a status here means all were

    def answered() -> bool:
        try:
            greedy.recv_multipart()
        except zmq.Again:
            return False
        return True

    wait_for(answered, timeout=30, what="a status on the greedy peer")
    return greedy


def test_ten_thousand_subscriptions_stay_small_and_longer_ones_are_dropped(tmp_path: Path) -> None:
    with boardless_daemon(tmp_path) as (proc, watch, endpoint):
        base = rss_mb(proc.pid)
        greedy = subscribe_all(endpoint, [f"roughness/{i:064d}".encode() for i in range(10_000)])  # distinct, each as long as the longest real topic
        held = rss_mb(proc.pid)
        greedy.close()
        bulky = zmq.Context.instance().socket(zmq.SUB)  # subscriptions longer than any topic (4 000 bytes each): the peer is dropped at the first
        bulky.setsockopt(zmq.LINGER, 0)
        bulky.setsockopt(zmq.SNDHWM, 0)
        bulky.connect(endpoint)
        for i in range(1000):
            bulky.setsockopt(zmq.SUBSCRIBE, f"{i:04d}".encode() * 1000)
        wait_for(lambda: isinstance(watch.receive(), Status) and isinstance(watch.receive(), Status), timeout=30, what="two status periods")
        bulky.close()
        after = rss_mb(proc.pid)
        assert held <= base + 10 and after <= base + 10, f"resident {base:.0f} MB, {held:.0f} with 10 000 subscriptions, {after:.0f} after 4 kB ones"
        assert proc.poll() is None


def test_memory_held_by_the_longest_allowed_subscriptions_is_given_back_when_their_peer_leaves(tmp_path: Path) -> None:
    """10 000 distinct subscriptions just under the length that drops a peer (110 bytes; 45 MB of them stayed resident after
    the peer left, glibc keeping the freed pages): <= 150 MB while held, back within 10 MB of the start once it has gone."""
    with boardless_daemon(tmp_path) as (proc, watch, endpoint):
        base = rss_mb(proc.pid)
        greedy = subscribe_all(endpoint, [f"roughness/{i:08d}".ljust(110, "x").encode() for i in range(10_000)])  # distinct from the start
        held = rss_mb(proc.pid)
        greedy.close()
        wait_for(lambda: isinstance(watch.receive(), Status) and rss_mb(proc.pid) <= base + 10, timeout=30,
                 what=f"resident memory back within 10 MB of {base:.0f} MB (held {held:.0f} MB)")
        assert held <= 150 and proc.poll() is None
