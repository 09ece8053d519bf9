"""Helpers with no knowledge of the task: atomic files and folder locks, YAML as users write it, and worker processes
with shared arrays (standard library, numpy and PyYAML only)."""
