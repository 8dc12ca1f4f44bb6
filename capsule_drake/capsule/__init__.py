"""The capsule: its model (frames, size, magnet) and its on-board sensors."""
