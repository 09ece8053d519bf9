"""Helpers with no knowledge of the task: atomic files and worker processes (standard library and numpy only)."""
