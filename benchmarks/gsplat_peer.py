"""gsplat (the peer CUDA rasterizer, ``pip install gsplat``, PyTorch) on our scenes and cameras, for the GPU benchmarks.

Only the benchmarks import this, and only on a machine with PyTorch, gsplat and a CUDA device (``available()``
says why not otherwise). gsplat compiles its CUDA code on first import (about 90 s on 16 cores).

Conventions mapped one to one: our parameters are raw 3DGS ones (log scales, unnormalized (w, x, y, z) rotations,
opacity logits, SH DC + rest), and gsplat's ``rasterization`` takes activated scales and opacities, (w, x, y, z)
quaternions (it normalizes them), the SH coefficients as one (N, K, 3) tensor, OpenCV world-to-camera matrices and
pixel intrinsics, as our :class:`Camera` holds them. The near plane defaults to ours (0.2; gsplat's own is 0.01).
"""

from __future__ import annotations

import numpy as np


def available() -> tuple[bool, str]:
    """(True, version) when torch, gsplat and a CUDA device are there, else (False, why not)."""
    try:
        import torch
    except ImportError:
        return False, "PyTorch is not installed"
    if not torch.cuda.is_available():
        return False, "PyTorch sees no CUDA device"
    try:
        import gsplat
    except ImportError:
        return False, "gsplat is not installed"
    return True, f"gsplat {gsplat.__version__}, torch {torch.__version__}"


def to_torch(params: dict, requires_grad: bool = False) -> dict:
    """Our raw parameter arrays (``benchmarks/render.py``'s scene dict, or a model's numpy export) as CUDA tensors."""
    import torch

    def t(a):
        x = torch.tensor(np.ascontiguousarray(a, dtype=np.float32), device="cuda")
        return x.requires_grad_(requires_grad)

    sh = np.concatenate([np.asarray(params["sh_dc"], np.float32).reshape(-1, 1, 3),
                         np.asarray(params["sh_rest"], np.float32).reshape(len(params["means"]), -1, 3)], axis=1)
    return {"means": t(params["means"]), "scales": t(params["scales"]), "quats": t(params["rotations"]),
            "opacities": t(np.asarray(params["opacities"]).reshape(-1)), "sh": t(sh)}


def camera_tensors(cam) -> tuple:
    """(viewmats (1, 4, 4), Ks (1, 3, 3)) of one of our cameras."""
    import torch

    k = np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]], np.float32)
    w2c = np.asarray(cam.world_to_camera, np.float32)
    return (torch.tensor(w2c, device="cuda")[None], torch.tensor(k, device="cuda")[None])


def sh_degree_of(n_coeffs: int) -> int:
    return int(round(np.sqrt(n_coeffs))) - 1


def rasterize(p: dict, cam, background=None, near_plane: float = 0.2, packed: bool = False,
              sh_degree: int | None = None, **kwargs):
    """gsplat's ``rasterization`` of raw parameters ``p`` (:func:`to_torch`) through one of our cameras:
    (rgb (H, W, 3), alpha (H, W, 1), info)."""
    import torch
    from gsplat import rasterization

    viewmats, ks = camera_tensors(cam)
    bg = None if background is None else torch.as_tensor(background, dtype=torch.float32, device="cuda")[None]
    deg = sh_degree_of(p["sh"].shape[1]) if sh_degree is None else sh_degree
    rgb, alpha, info = rasterization(
        means=p["means"], quats=p["quats"], scales=torch.exp(p["scales"]), opacities=torch.sigmoid(p["opacities"]),
        colors=p["sh"], viewmats=viewmats, Ks=ks, width=cam.width, height=cam.height, near_plane=near_plane,
        sh_degree=deg, packed=packed, backgrounds=bg, **kwargs)
    return rgb[0], alpha[0], info


def cuda_kernel_profile(fn, rows: int = 8) -> str:
    """torch.profiler's table of the CUDA kernels of one call of ``fn`` (after it ran once), by total device time."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    fn()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        fn()
        torch.cuda.synchronize()
    try:
        return prof.key_averages().table(sort_by="device_time_total", row_limit=rows)
    except (AttributeError, KeyError, ValueError):  # older PyTorch names the column after CUDA
        return prof.key_averages().table(sort_by="cuda_time_total", row_limit=rows)
