"""The physically grounded sensor simulator: the sensor model, the virtual board on a pty, scenes and datasets."""
