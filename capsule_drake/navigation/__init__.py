"""Autonomous navigation of the magnetic capsule (the EPM moved by a controller, no hand)."""
