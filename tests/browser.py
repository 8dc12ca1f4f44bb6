"""What the browser tests share: the headless Chromium they drive."""

import os

import pytest

from capsule_drake.io.headless import chromium_executable


def chromium() -> str:
    """The Chromium executable; skips without one, except on CI, which must have it."""
    exe = chromium_executable()
    if exe is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is not on PATH (the CI set-up must install it)")
        pytest.skip("chromium is not on PATH")
    return exe
