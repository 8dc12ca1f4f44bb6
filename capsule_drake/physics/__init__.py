"""Magnet fields, forces and torques; the magnet force system; contact."""
