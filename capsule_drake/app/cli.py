"""capsule-sim: the command line. Parses the arguments (app/cli_parser.py) and hands them to
the verb's command (app/commands/); the errors a user can make end here in one line."""

from __future__ import annotations

import os
import signal
import sys
import tempfile
import threading
import traceback

from capsule_drake.anatomy.cache import CacheError, cache_base
from capsule_drake.app.cli_parser import _parser
from capsule_drake.app.commands import (benchmark, docs, eval_lumen, import_colon, notebooks,
                                        record, run, teleop)

from capsule_drake.app.commands.common import (COLON_VERBS, _check_flag_combinations,
                                               _created_folders, _remove_unused_folders)
from capsule_drake.app.outputs import OutputError, release_claims
from capsule_drake.app.run import Interrupted
from capsule_drake.app.run_outputs import WriteError
from capsule_drake.scenario import ScenarioError


# Each verb's command (app/commands/): it returns the exit status.
VERBS = {"run": run._run, "record": record._record, "eval-lumen": eval_lumen._eval_lumen,
         "teleop": teleop._teleop, "benchmark": benchmark._benchmark,
         "import-colon": import_colon._import_colon, "notebooks": notebooks._notebooks,
         "docs": docs._docs}


def _raise_interrupted(signal_number, frame):
    raise Interrupted(signal_number)


def main(argv=None, noted=None) -> int:
    """The command. `noted`: signals that arrived before it (app/entry.py notes them while
    the libraries are imported); the first ends the command at once, as it would have."""
    noted = noted if noted is not None else []
    # A termination signal (kill, timeout, a closed terminal) ends a run as Ctrl-C does:
    # what was logged is written, then the exit status says which signal it was. SIGINT
    # too: a process started in the background (nohup, `&` in a script) inherits it ignored,
    # and Python then installs no Ctrl-C handler of its own.
    if threading.current_thread() is threading.main_thread():
        for number in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(number, _raise_interrupted)
    try:
        if noted:  # before anything ran
            raise Interrupted(noted[0])
        args = _parser().parse_args(argv)
        _created_folders.clear()
        _check_flag_combinations(args)
        if args.verb in COLON_VERBS:
            cache_base()  # a cache variable naming a file: one line, before anything is made
        return VERBS[args.verb](args)
    except (ScenarioError, WriteError, CacheError) as e:  # WriteError: after the run
        _remove_unused_folders()
        print(f"capsule-sim: error: {e}", file=sys.stderr)
        return 1 if isinstance(e, WriteError) else 2
    except OutputError as e:
        _remove_unused_folders()
        print(f"capsule-sim: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        name = getattr(e, "signal_name", "SIGINT")
        print(f"capsule-sim: interrupted ({name})", file=sys.stderr)
        return 128 + signal.Signals[name].value
    except BrokenPipeError:  # the output piped into a command that stopped reading
        sys.stderr.close()
        return 1
    except Exception as e:  # a defect, not the user's mistake: one line, the details on disk
        return _internal_error(e)
    finally:
        release_claims()  # the output folders this command held (the system would, at exit)
    return 0


def _internal_error(e: Exception) -> int:
    """An unexpected error: one line, and the traceback in a file for a bug report."""
    details = "".join(traceback.format_exception(e))
    try:
        handle, path = tempfile.mkstemp(prefix="capsule-sim-error-", suffix=".txt")
        with os.fdopen(handle, "w") as f:
            f.write(details)
        where = f"the traceback is in {path}"
    except OSError:
        where = "no file could be written for the traceback"
    text = str(e).strip().splitlines()[0] if str(e).strip() else ""
    print(f"capsule-sim: internal error: {type(e).__name__}: {text} ({where}; please report "
          "it with the command that caused it)", file=sys.stderr)
    return 70


if __name__ == "__main__":
    sys.exit(main())
