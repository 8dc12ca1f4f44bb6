"""The command line's verbs, one module each (app/cli.py dispatches to them)."""
