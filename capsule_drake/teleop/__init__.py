"""Teleoperation: bridges between the simulator and real input devices (udp: a haptic stylus)."""
