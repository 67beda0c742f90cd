"""The differentiable tile-sorted rasterizer: projection -> binning -> blending (one CustomOp)."""
