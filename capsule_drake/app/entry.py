"""The `capsule-sim` command's entry point. Its first statements take Ctrl-C and the
termination signals, before the simulator's libraries (Drake, OpenCV: a second or two) are
imported: a signal at start-up is noted, and the command ends with one line and 128 + the
signal's number, never a traceback and never a run that goes on as if nothing happened."""

import signal
import sys

_NOTED: list[int] = []


def _note(number, frame):
    _NOTED.append(number)


for _name in ("SIGINT", "SIGTERM", "SIGHUP"):
    signal.signal(getattr(signal, _name), _note)

from capsule_drake.app import cli  # noqa: E402  (after the handlers, on purpose)


def main(argv=None) -> int:
    return cli.main(argv, noted=_NOTED)


if __name__ == "__main__":
    sys.exit(main())
