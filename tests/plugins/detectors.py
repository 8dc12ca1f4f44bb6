"""Lumen detectors a user might plug into `capsule-sim eval-lumen` that break
(tests/test_bad_inputs.py): one raises, one returns None, one NaN, one a NaN pixel it calls
visible, one a pixel of the wrong shape, one ends the program, and two write into what they
are given (the frame, the field mask)."""

import sys

import numpy as np

from capsule_drake.perception.lumen import LumenDetection


def raises(rgb, field_mask):
    raise ZeroDivisionError("the detector divided by zero")


def returns_none(rgb, field_mask):
    return None


def returns_nan(rgb, field_mask):
    return float("nan")


def nan_pixel(rgb, field_mask):
    return LumenDetection(True, np.array([np.nan, np.nan]), 0.9,
                          np.zeros(rgb.shape[:2], dtype=np.uint8))


def wrong_shape(rgb, field_mask):
    return LumenDetection(True, np.array([10.0, 20.0, 1.0]), 0.9,
                          np.zeros(rgb.shape[:2], dtype=np.uint8))


def exits(rgb, field_mask):
    sys.exit(0)


def scribbles(rgb, field_mask):
    """Writes into the frame it is given (white), then sees no lumen."""
    rgb[...] = 255
    return LumenDetection.nothing(rgb.shape)


def clears_the_mask(rgb, field_mask):
    """Writes into the field mask it is given (nothing in the field), then sees no lumen."""
    field_mask[...] = False
    return LumenDetection.nothing(rgb.shape)
