"""Optimization: photometric losses, learning-rate and SH-degree schedules, Adam set-up, adaptive density control and
the training loop (``losses``, ``schedules``, ``optimizer``, ``densify``, ``trainer``)."""
