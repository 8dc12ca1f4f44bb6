"""The external magnet: its poses, mounts (stage, arm), guard and drivers."""
