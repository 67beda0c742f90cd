"""Training data: cameras, dataset folders (COLMAP / Blender / instant-ngp, NumPy), structure from motion, and Mitsuba
scene files as datasets (loading the scene, its camera rig, path-traced references cached as EXR, initial points)."""
