"""Session hooks: the 50-reset memory test's processes start with the session (they run at
the lowest priority beside the other tests; tests/test_memory.py)."""

import test_memory


def pytest_collection_finish(session):   # the items selected to run
    if any(item.name == test_memory.FIFTY_RESETS_TEST for item in session.items):
        test_memory.start_fifty_resets()


def pytest_sessionfinish(session, exitstatus):
    test_memory.stop_fifty_resets()
