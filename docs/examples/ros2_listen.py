"""A controller-side subscriber: two final labels and one samples message (its own stamp and first index)."""
import numpy as np
import rclpy
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String

rclpy.init()
node = rclpy.create_node("listener")
labels, batches = [], []
node.create_subscription(String, "/robot1/tactiled/fingertip0/roughness", lambda m: labels.append(m.data), 10)
node.create_subscription(PointCloud2, "/robot1/tactiled/fingertip0/samples", batches.append, qos_profile_sensor_data)
while len(labels) < 2 or not batches:
    rclpy.spin_once(node, timeout_sec=1.0)
rows = np.frombuffer(bytes(batches[-1].data), dtype=[("film1", "<f4"), ("film2", "<f4"), ("t", "<f4"), ("index", "<f8")])
stamp = batches[-1].header.stamp
print(f"labels: {labels}; a batch of {len(rows)} samples from index {int(rows['index'][0])} at {stamp.sec}.{stamp.nanosec:09d}")
