"""A plug-in module that ends the program as it is imported, as a user's script with a
`sys.exit()` at module level would (tests/test_bad_inputs.py). Its navigator and detector are
never reached."""

import sys

sys.exit(0)


def make(context):  # pragma: no cover (never imported that far)
    raise AssertionError("unreachable")


def detect(rgb, field_mask):  # pragma: no cover
    raise AssertionError("unreachable")
