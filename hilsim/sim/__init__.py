"""The world and its physics: pure, deterministic, no I/O beyond reading data files."""
