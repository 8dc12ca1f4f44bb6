"""Running a station and what a run leaves: run loop, metrics, datasets."""
