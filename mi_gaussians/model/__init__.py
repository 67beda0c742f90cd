"""The Gaussian model: raw parameters, activations, spherical harmonics, PLY I/O and initialization."""
