"""What runs a station: the one run loop (guard, signals, outputs), record, the benchmark,
the Gymnasium environment, the MCAP and dataset writers, and the command line. Nothing
below this package imports it."""
