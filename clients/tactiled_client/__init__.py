"""Client library for tactiled (pyzmq + msgpack only)."""
