"""The binning's stable sorts (``raster/binning.py``) against NumPy's stable sort, on all of their paths.

The CUDA paths (8-bit digit passes; padding inside a frozen function) are forced here on whichever backend the suite
runs on, so that the LLVM suite checks their logic and the CUDA suite checks them where they matter (stability of
Dr.Jit's CUDA ``block_mkperm``, and its replay inside a frozen function)."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_gaussians.drjit_utils import owned_array
from mi_gaussians.raster.binning import stable_argsort, stable_bucket_perm


def _keys(rng, n):
    k = rng.normal(0.0, 3.0, n).astype(np.float32)
    k[rng.integers(0, n, n // 4)] = 1.5                      # many ties
    special = np.array([0.0, -0.0, np.inf, -np.inf, 1e-38, -1e-38, 3.4e38, -3.4e38], np.float32)
    k[: min(n, len(special))] = special[:n]
    return rng.permutation(k)


def _numpy_order(keys):
    """NumPy's stable ascending order of float keys, -0.0 before +0.0 (the order of their bits, as dr.argsort has it)."""
    return np.lexsort((np.arange(len(keys)), np.signbit(keys) == 0, keys))


@pytest.mark.parametrize("pad", [False, True])
@pytest.mark.parametrize("n", [0, 1, 2, 1000, 70_001])
def test_stable_argsort_is_numpys_stable_argsort(pad, n):
    keys = _keys(np.random.default_rng(n), n) if n else np.zeros(0, np.float32)
    got = np.array(stable_argsort(mi.Float(keys), pad=pad), dtype=np.int64)
    np.testing.assert_array_equal(got, _numpy_order(keys))


@pytest.mark.parametrize("digits, pad", [(False, False), (True, False), (True, True)])
@pytest.mark.parametrize("buckets", [1, 3, 256, 257, 4096, 70_000])
def test_stable_bucket_perm_is_numpys_stable_argsort(digits, pad, buckets):
    if not digits and buckets > 256 and dr.backend_v(mi.UInt32) == dr.JitBackend.CUDA:
        pytest.skip("one block_mkperm pass over more than 256 buckets is not stable on CUDA (seen on an H100 with "
                    "70,000 buckets: 114 of 50,000 elements out of order), which is why the CUDA path uses digits")
    rng = np.random.default_rng(buckets)
    n = 50_000
    values = rng.integers(0, buckets, n).astype(np.uint32)
    values[:100] = buckets - 1
    perm = np.array(stable_bucket_perm(mi.UInt32(values), buckets, digits=digits, pad=pad), dtype=np.int64)
    np.testing.assert_array_equal(perm, np.argsort(values, kind="stable"))


def test_the_sorts_replay_in_a_frozen_function():
    """The sorts as the frozen training step records them (padded on CUDA by default; forced here): the replays on
    new data give the permutations of NumPy's stable sort."""
    @dr.freeze
    def both(keys, tiles):
        return stable_argsort(keys, pad=True), stable_bucket_perm(tiles, 4096, digits=True, pad=True)

    rng = np.random.default_rng(5)
    for _ in range(4):
        keys = _keys(rng, 3000)
        tiles = rng.integers(0, 4096, 3000).astype(np.uint32)
        # (inputs in Dr.Jit's own memory: NumPy-mapped ones differ in alignment, which makes new recordings)
        k, t = owned_array(mi.Float, keys), owned_array(mi.UInt32, tiles)
        dr.eval(k, t)
        order, perm = both(k, t)
        np.testing.assert_array_equal(np.array(order), _numpy_order(keys))
        np.testing.assert_array_equal(np.array(perm), np.argsort(tiles, kind="stable"))
    assert both.n_recordings == 1        # one recording, three replays
