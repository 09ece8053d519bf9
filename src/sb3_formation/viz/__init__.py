"""Figures (matplotlib) and videos (ffmpeg, Pillow) of evaluations and training runs."""
