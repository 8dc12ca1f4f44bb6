"""Polyp detectors a user might plug into the benchmark (tests/test_lesions_seen.py):
trivial ones, for the scoring, not for finding polyps."""

import cv2
import numpy as np


def brightest_spot(rgb):
    """The brightest spot of the blurred frame, as a 9-pixel box: polyps stand out of the
    wall toward the light, so they are often the brightest thing in view."""
    grey = cv2.GaussianBlur(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), (0, 0), 3.0)
    v, u = np.unravel_index(np.argmax(grey), grey.shape)
    return [(u - 4, v - 4, 9, 9)]


def broken(rgb):
    raise RuntimeError("this detector always fails")
