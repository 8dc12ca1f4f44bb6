"""The run's live outputs (Foxglove, ROS 2) beside its MCAP file, from the scenario's
`outputs` (app/channels.py: one table of channels; app/mcap_log.py: the streams that read the
station)."""
