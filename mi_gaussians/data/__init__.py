"""Cameras, datasets and initial point clouds (numpy; no Dr.Jit state)."""
