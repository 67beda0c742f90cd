"""Image operators (image_ops.py) and the training loss (optim/losses.py): SSIM against scikit-image, an independent
SciPy float64 implementation of the reference, a slow pure-AD Dr.Jit reference and finite differences; L1 and the
fused training loss; no recompilation."""

from __future__ import annotations

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi
from scipy.ndimage import correlate, gaussian_filter

from kernel_log import KernelLog
from mi_gaussians.drjit_utils import flat_mean, owned_tensor
from mi_gaussians import image_ops, image_walk
from mi_gaussians.optim import losses

C1, C2 = 0.01 ** 2, 0.03 ** 2


# ----------------------------------------------------------------------------------------------- references (NumPy)
def window_2d(size=11, sigma=1.5) -> np.ndarray:
    """The reference's ``create_window``: outer product of the normalized 1D Gaussian (written out independently)."""
    k = np.arange(size) - size // 2
    g = np.exp(-k ** 2 / (2.0 * sigma ** 2))
    g /= g.sum()
    return np.outer(g, g)


def ssim_map_ref(a: np.ndarray, b: np.ndarray, size=11, sigma=1.5) -> np.ndarray:
    """The reference ``_ssim`` in float64: per-channel 2D correlation with zero padding of size // 2."""
    w = window_2d(size, sigma)[:, :, None]                 # same window for every channel, no mixing
    a = a.reshape(a.shape[0], a.shape[1], -1).astype(np.float64)
    b = b.reshape(a.shape).astype(np.float64)

    def conv(v):
        return correlate(v, w, mode="constant", cval=0.0)

    mu1, mu2 = conv(a), conv(b)
    s11, s22, s12 = conv(a * a) - mu1 ** 2, conv(b * b) - mu2 ** 2, conv(a * b) - mu1 * mu2
    return ((2 * mu1 * mu2 + C1) * (2 * s12 + C2)) / ((mu1 ** 2 + mu2 ** 2 + C1) * (s11 + s22 + C2))


def loss_ref(a, b, lam):
    return (1 - lam) * np.abs(a - b).mean() + lam * (1 - ssim_map_ref(a, b).mean())


def central_fd(f, a: np.ndarray, eps=1e-6) -> np.ndarray:
    g = np.zeros_like(a)
    for i in np.ndindex(a.shape):
        ap, am = a.copy(), a.copy()
        ap[i] += eps
        am[i] -= eps
        g[i] = (f(ap) - f(am)) / (2 * eps)
    return g


def rel_err(got, want) -> float:
    return float(np.abs(np.asarray(got) - want).max() / np.abs(want).max())


# ---------------------------------------------------------------------------------------------- reference (Dr.Jit)
def ssim_ad_reference(x: "mi.TensorXf", y: "mi.TensorXf") -> "mi.Float":
    """A slow, obviously-correct Dr.Jit version: 2 x 11 masked gathers per blur, derivatives by plain AD."""
    H, W, C = x.shape
    w = image_ops.gaussian_window()
    idx = dr.arange(mi.UInt32, H * W * C)
    c = mi.Int32(idx % C)
    px = mi.Int32((idx // C) % W)
    py = mi.Int32(idx // (C * W))

    def blur(v):
        for axis in (1, 0):
            out = dr.zeros(mi.Float, H * W * C)
            for k in range(11):
                qx, qy = (px + k - 5, py) if axis == 1 else (px, py + k - 5)
                ok = (qx >= 0) & (qx < W) & (qy >= 0) & (qy < H)
                out = out + w[k] * dr.gather(mi.Float, v, mi.UInt32((qy * W + qx) * C + c), ok)
            v = out
        return v

    a, b = x.array, y.array
    mu1, mu2 = blur(a), blur(b)
    s11, s22, s12 = blur(a * a) - mu1 * mu1, blur(b * b) - mu2 * mu2, blur(a * b) - mu1 * mu2
    m = ((2 * mu1 * mu2 + C1) * (2 * s12 + C2)) / ((mu1 * mu1 + mu2 * mu2 + C1) * (s11 + s22 + C2))
    return dr.mean(m)


def structured_pair(rng, shape):
    """A smooth image with edges and its blurred, noisy copy (SSIM well inside (0, 1))."""
    H, W, C = shape
    yy, xx = np.mgrid[0:H, 0:W] / max(H, W)
    base = np.stack([0.5 + 0.4 * np.sin(7 * xx + 3 * c) * np.cos(5 * yy) for c in range(C)], axis=2)
    base[H // 3: 2 * H // 3, W // 4: W // 2] = 0.9                       # a sharp-edged block
    copy = np.stack([gaussian_filter(base[..., c], 1.2) for c in range(C)], axis=2)
    copy = np.clip(copy + 0.05 * rng.standard_normal(shape), 0, 1)
    return base, copy


# -------------------------------------------------------------------------------------------------------- values
@pytest.mark.parametrize("kind", ["random", "structured"])
def test_ssim_matches_scikit_image_interior(kind):
    """scikit-image crops (win_size - 1) / 2 = 5 pixels on every side before averaging (its Gaussian filter pads by
    reflection, so only the interior is comparable); in the interior no window reaches past the image, so its map
    equals the reference's zero-padded one: compare the mean of our map over [5:-5, 5:-5] with its value."""
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(1)
    shape = (47, 61, 3)
    if kind == "random":
        a = rng.random(shape)
        b = np.clip(a + 0.3 * rng.standard_normal(shape), 0, 1)
    else:
        a, b = structured_pair(rng, shape)
    want = structural_similarity(a, b, channel_axis=2, gaussian_weights=True, sigma=1.5,
                                 use_sample_covariance=False, data_range=1.0)
    m = np.array(image_ops.ssim_map(owned_tensor(a), owned_tensor(b)))
    assert m.shape == shape
    assert abs(m[5:-5, 5:-5].mean() - want) < 1e-4
    assert 0.05 < want < 0.95


@pytest.mark.parametrize("shape", [(12, 10, 3), (37, 150, 3), (70, 131, 3), (9, 13, 1), (3, 4, 2), (130, 20, 4)])
def test_ssim_matches_zero_padded_reference(shape):
    """Full image, borders included (zero padding), against SciPy in float64; sizes cover partial blocks and tiles,
    images smaller than the window and channel counts other than 3."""
    rng = np.random.default_rng(2)
    a, b = structured_pair(rng, shape) if min(shape[:2]) >= 12 else (rng.random(shape), rng.random(shape))
    want_map = ssim_map_ref(a, b)
    x, y = owned_tensor(a), owned_tensor(b)
    assert abs(image_ops.ssim(x, y)[0] - want_map.mean()) < 1e-5
    # per pixel, float32 cancellation in E[x^2] - mu^2 (as in the reference's float32 torch code) reaches ~1e-4
    # where the local variance is tiny; the mean is far more accurate
    assert np.abs(np.array(image_ops.ssim_map(x, y)) - want_map).max() < 5e-4
    assert abs(image_ops.d_ssim(x, y)[0] - (1 - want_map.mean())) < 1e-5


def test_ssim_of_2d_tensor_and_identical_images():
    rng = np.random.default_rng(3)
    a, b = rng.random((9, 14)), rng.random((9, 14))
    assert abs(image_ops.ssim(owned_tensor(a), owned_tensor(b))[0] - ssim_map_ref(a, b).mean()) < 1e-5
    x = owned_tensor(rng.random((20, 30, 3)))
    assert abs(image_ops.ssim(x, x)[0] - 1.0) < 1e-6


def test_window_and_argument_checks():
    w = image_ops.gaussian_window(11, 1.5)
    assert len(w) == 11 and abs(sum(w) - 1) < 1e-12 and w == w[::-1]
    np.testing.assert_allclose(np.outer(w, w), window_2d(), rtol=1e-12)
    x = owned_tensor(np.zeros((8, 8, 3)))
    with pytest.raises(ValueError):
        image_ops.ssim(x, x, image_ops.SSIMParams(window=10))
    with pytest.raises(ValueError):
        image_ops.ssim(x, owned_tensor(np.zeros((8, 9, 3))))
    with pytest.raises(TypeError):
        image_ops.l1(np.zeros((8, 8, 3)), x)
    with pytest.raises(ValueError):
        losses.photometric_loss(x, x, 1.5)


# ----------------------------------------------------------------------------------------------------- gradients
def test_ssim_gradients_match_finite_differences():
    """Both inputs, against central differences of the float64 reference (12 x 10 x 3)."""
    rng = np.random.default_rng(4)
    a = rng.random((12, 10, 3))
    b = np.clip(a + 0.2 * rng.standard_normal(a.shape), 0, 1)
    x, y = owned_tensor(a), owned_tensor(b)
    dr.enable_grad(x, y)
    dr.backward(image_ops.ssim(x, y))
    assert rel_err(dr.grad(x), central_fd(lambda v: ssim_map_ref(v, b).mean(), a)) < 1e-3
    assert rel_err(dr.grad(y), central_fd(lambda v: ssim_map_ref(a, v).mean(), b)) < 1e-3


def test_ssim_map_gradients_and_forward_mode():
    """ssim_map with a non-uniform incoming gradient (backward) and forward-mode derivatives of ssim and ssim_map."""
    rng = np.random.default_rng(5)
    a, b, wts, d = (rng.random((11, 13, 3)) for _ in range(4))
    x, y = owned_tensor(a), owned_tensor(b)
    dr.enable_grad(x, y)
    dr.backward(dr.sum((image_ops.ssim_map(x, y) * owned_tensor(wts)).array))
    assert rel_err(dr.grad(x), central_fd(lambda v: (ssim_map_ref(v, b) * wts).sum(), a)) < 1e-3
    assert rel_err(dr.grad(y), central_fd(lambda v: (ssim_map_ref(a, v) * wts).sum(), b)) < 1e-3

    eps = 1e-6
    fd_map = (ssim_map_ref(a + eps * d, b) - ssim_map_ref(a - eps * d, b)) / (2 * eps)
    x = owned_tensor(a)
    dr.enable_grad(x)
    dr.set_grad(x, owned_tensor(d))
    s = image_ops.ssim(x, owned_tensor(b))
    dr.forward_to(s)
    assert abs(dr.grad(s)[0] - fd_map.mean()) < 1e-3 * abs(fd_map.mean())
    x = owned_tensor(a)
    dr.enable_grad(x)
    dr.set_grad(x, owned_tensor(d))
    m = image_ops.ssim_map(x, owned_tensor(b))
    dr.forward_to(m)
    assert rel_err(dr.grad(m), fd_map) < 1e-3


@pytest.mark.parametrize("shape", [(70, 150, 3), (131, 45, 3)])
def test_ssim_gradient_matches_pure_ad_reference(shape):
    """Larger images (several blocks and tiles, partial ones at the edges) against plain Dr.Jit AD."""
    rng = np.random.default_rng(6)
    a, b = structured_pair(rng, shape)
    x, y = owned_tensor(a), owned_tensor(b)
    dr.enable_grad(x, y)
    dr.backward(image_ops.ssim(x, y))
    xr, yr = owned_tensor(a), owned_tensor(b)
    dr.enable_grad(xr, yr)
    s_ref = ssim_ad_reference(xr, yr)
    dr.backward(s_ref)
    assert abs(image_ops.ssim(owned_tensor(a), owned_tensor(b))[0] - s_ref[0]) < 1e-5
    assert rel_err(dr.grad(x), np.array(dr.grad(xr))) < 1e-4
    assert rel_err(dr.grad(y), np.array(dr.grad(yr))) < 1e-4


def test_l1_value_and_gradient():
    """Mean absolute error; derivative sign(x - y) / N with 0 where x == y (torch's abs)."""
    rng = np.random.default_rng(7)
    a = rng.random((6, 7, 3)).astype(np.float32)
    b = rng.random((6, 7, 3)).astype(np.float32)
    b[0, :3] = a[0, :3]                                           # zero differences
    x = owned_tensor(a)
    dr.enable_grad(x)
    v = image_ops.l1(x, owned_tensor(b))
    dr.backward(v)
    assert abs(v[0] - np.abs(a - b).mean()) < 1e-7
    np.testing.assert_allclose(np.array(dr.grad(x)), np.sign(a - b) / a.size, rtol=1e-6)
    assert not np.array(dr.grad(x))[0, :3].any()


@pytest.mark.parametrize("lam", [0.2, 0.0, 1.0, 0.55])
def test_photometric_loss_value_and_gradient(lam):
    """The fused loss equals (1 - lambda) l1 + lambda (1 - ssim): value, gradient vs finite differences and vs the
    separately differentiated terms (with some exactly equal pixels, where the L1 derivative is 0)."""
    rng = np.random.default_rng(8)
    a = rng.random((12, 10, 3))
    b = np.clip(a + 0.2 * rng.standard_normal(a.shape), 0, 1)
    b[4, 2:6] = a[4, 2:6].astype(np.float32)
    a = a.astype(np.float32).astype(np.float64)
    b = b.astype(np.float32).astype(np.float64)
    x, y = owned_tensor(a), owned_tensor(b)
    dr.enable_grad(x)
    v = losses.photometric_loss(x, y, lam)
    dr.backward(v)
    assert abs(v[0] - loss_ref(a, b, lam)) < 1e-6
    g = np.array(dr.grad(x))
    # finite differences away from the kinks of |x - y|
    smooth = np.abs(a - b) > 1e-3
    fd = central_fd(lambda t: loss_ref(t, b, lam), a, eps=1e-7)
    assert np.abs(g - fd)[smooth].max() < 1e-3 * np.abs(fd).max()
    # separately: l1 with sign(0) = 0 plus the SSIM gradient
    x2 = owned_tensor(a)
    dr.enable_grad(x2)
    dr.backward((1 - lam) * image_ops.l1(x2, y) + lam * image_ops.d_ssim(x2, y))
    np.testing.assert_allclose(g, np.array(dr.grad(x2)), rtol=1e-4, atol=1e-9)
    # no gradient for the reference image unless asked, and with it: the mirror image
    y2 = owned_tensor(b)
    dr.enable_grad(y2)
    dr.backward(losses.photometric_loss(owned_tensor(a), y2, lam))
    fd_y = central_fd(lambda t: loss_ref(a, t, lam), b, eps=1e-7)
    assert np.abs(np.array(dr.grad(y2)) - fd_y)[smooth].max() < 1e-3 * np.abs(fd_y).max()


def valid_loss_ref(a, b, lam):
    """gsplat's trainer's loss in float64: SSIM as a "valid" convolution, i.e. the reference map's interior mean."""
    return (1 - lam) * np.abs(a - b).mean() + lam * (1 - ssim_map_ref(a, b)[5:-5, 5:-5].mean())


def test_photometric_loss_over_the_valid_region():
    """ssim_padding="valid": value and gradient against the float64 interior mean and finite differences (pixels
    near the edge get gradient only through the windows of interior pixels), and images too small for it refused."""
    rng = np.random.default_rng(11)
    a = rng.random((16, 19, 3)).astype(np.float32).astype(np.float64)
    b = np.clip(a + 0.2 * rng.standard_normal(a.shape), 0, 1).astype(np.float32).astype(np.float64)
    x = owned_tensor(a)
    dr.enable_grad(x)
    v = losses.photometric_loss(x, owned_tensor(b), 0.2, "valid")
    dr.backward(v)
    assert abs(v[0] - valid_loss_ref(a, b, 0.2)) < 1e-6
    assert abs(v[0] - loss_ref(a, b, 0.2)) > 1e-3                  # not the zero-padded mean
    fd = central_fd(lambda t: valid_loss_ref(t, b, 0.2), a, eps=1e-7)
    smooth = np.abs(a - b) > 1e-3
    assert np.abs(np.array(dr.grad(x)) - fd)[smooth].max() < 1e-3 * np.abs(fd).max()
    assert abs(losses.valid_ssim(owned_tensor(a), owned_tensor(b))[0] - ssim_map_ref(a, b)[5:-5, 5:-5].mean()) < 1e-6
    with pytest.raises(ValueError, match="larger than 10 pixels"):
        losses.photometric_loss(owned_tensor(a[:10]), owned_tensor(b[:10]), 0.2, "valid")
    with pytest.raises(ValueError, match="ssim_padding"):
        losses.photometric_loss(x, owned_tensor(b), 0.2, "reflect")


def test_default_lambda_matches_config():
    from mi_gaussians.config import OptimConfig

    rng = np.random.default_rng(9)
    a, b = rng.random((16, 16, 3)), rng.random((16, 16, 3))
    v = losses.photometric_loss(owned_tensor(a), owned_tensor(b), OptimConfig().lambda_dssim)
    assert abs(v[0] - loss_ref(a, b, 0.2)) < 1e-6


# --------------------------------------------------------------------------------------------------- compilation
def test_no_recompilation_for_new_images_of_the_same_size():
    """After one call, calls on other images and other lambdas of that size launch only the kernels of the first:
    a kernel specialized on a value (an image, a lambda baked in as a literal) has a new hash for every new value.
    (It did: the backward scaled the incoming gradient by ``lambda / N`` as a Python float, two kernels per lambda,
    hidden wherever Dr.Jit's disk cache had met that lambda before. The images are made beforehand: copying NumPy
    arrays in may compile kernels of its own.)"""
    rng = np.random.default_rng(10)
    shape = (40, 56, 3)
    images = [owned_tensor(rng.random(shape)) for _ in range(28)]
    dr.eval(images)

    def step(k, lam):
        x = mi.TensorXf(images[4 * k])
        dr.enable_grad(x)
        loss = losses.photometric_loss(x * 1.0, images[4 * k + 1], lam)
        dr.backward(loss)
        dr.eval(dr.grad(x))
        dr.eval(image_ops.ssim(images[4 * k + 2], images[4 * k + 3]))

    with KernelLog() as log:
        step(0, 0.2)
        log.cut()
        for k, lam in ((1, 0.3), (2, 0.25), (3, 0.35), (4, 0.15), (5, 0.45), (6, 0.1)):
            step(k, lam)
            log.cut()
    assert all(log.windows)
    unseen = [log.unseen(i) for i in range(1, len(log.windows))]
    assert not any(unseen), f"kernels not launched by an earlier call: {unseen}"


def test_short_blocks(monkeypatch):
    """Many lanes per line (the GPU configuration, and partial blocks everywhere) give the same values and
    gradients as the default blocks."""
    rng = np.random.default_rng(11)
    a, b = structured_pair(rng, (45, 38, 3))

    def run():
        x = owned_tensor(a)
        dr.enable_grad(x)
        v = losses.photometric_loss(x, owned_tensor(b), 0.2)
        dr.backward(v)
        return v[0], np.array(dr.grad(x))

    v0, g0 = run()
    monkeypatch.setattr(image_walk, "_BLOCK_Y", 7)
    monkeypatch.setattr(image_walk, "_BLOCK_X", 6)
    monkeypatch.setattr(image_walk, "_UNROLL", 4)
    v1, g1 = run()
    assert abs(v0 - loss_ref(a, b, 0.2)) < 1e-6 and abs(v1 - v0) < 1e-6
    np.testing.assert_allclose(g1, g0, rtol=1e-5, atol=1e-10)


@pytest.mark.parametrize("shape", [(64, 32, 1), (16, 8, 2), (8, 4, 1), (1024, 2, 1), (1024, 4, 2), (2, 256, 2)])
def test_the_loss_walk_that_blurs_twice_gives_the_two_walks_gradients_bit_for_bit(shape):
    """On the CPU the training loss blurs its SSIM derivative maps down the columns in its forward walk
    (``image_walk._sweep_twice``); the SSIM map's backward blurs them in a walk of their own. The mean SSIM's
    gradient is the same through both, bit for bit, on images shorter than the window, taller than a walk's block
    (512 rows) and of one or two channels: with a power-of-two pixel count the uniform incoming gradient 1/N scales
    exactly, before the blur (the map's path) or after it (the loss's)."""
    rng = np.random.default_rng(sum(shape))
    a = rng.uniform(size=shape).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.1, shape), 0, 1).astype(np.float32)
    grads = []
    for through_map in (False, True):
        x, y = owned_tensor(a), owned_tensor(b)
        dr.enable_grad(x, y)
        value = flat_mean(image_ops.ssim_map(x, y).array) if through_map else image_ops.ssim(x, y)
        dr.backward(value)
        grads.append((np.array(dr.grad(x)), np.array(dr.grad(y)), float(value[0])))
    (gx, gy, v), (mx, my, w) = grads
    assert np.array_equal(gx, mx) and np.array_equal(gy, my)
    assert abs(v - w) < 1e-6
