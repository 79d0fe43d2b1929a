"""Programs built on the client library only: the terminal monitor and the ROS 2 / LSL bridges."""
