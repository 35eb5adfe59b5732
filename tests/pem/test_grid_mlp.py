"""The PEM networks in order-free arithmetic (pemviz.pem.network.GridMLP): a row's answer depends on that row alone,
whatever the batch, the BLAS kernel or the vector unit, and stays within float32's precision of the float64 network."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pemviz.pem import load_pem
from pemviz.pem.encoding import salient_codes
from pemviz.pem.network import MLP_BLOCK, GridMLP
from pemviz.pem.store import load_noise_pem

from conftest import REPO, float64_network, load_script

rp = load_script(REPO / "benchmarks" / "fingerprint.py")


def raw_rows(n: int, seed: int = 0) -> np.ndarray:
    """KITTI-like raw salient inputs [n, 11]: every class and occlusion, poses from a few metres to 80 m, and some rows
    far outside the data (|z-score| up to 1e9, and 1e-30) that exercise the grids' edges."""
    rng = np.random.default_rng(seed)
    raw = np.zeros((n, 11))
    raw[:, 0] = rng.integers(0, 7, n)
    raw[:, 2] = rng.integers(0, 3, n)
    raw[:, 7:] = rng.normal(size=(n, 4)) * [4.0, 0.5, 20.0, 1.5] + [0.0, 1.7, 30.0, 0.0]
    raw[:7, 9] = [1e9, -1e9, 1e-30, 0.0, 3e7, 2.5, 1e300]
    return raw


@pytest.fixture(scope="module")
def networks():
    pem, noise = load_pem(), load_noise_pem()
    return {
        "detection": (pem._grid, pem._one_hot, pem._layers, pem.norm),
        "noise": (noise._grid, noise._one_hot, noise._layers, noise.norm),
    }


@pytest.mark.parametrize("head", ["detection", "noise"])
def test_a_row_gives_the_same_bits_in_every_batch(networks, head):
    grid, _, _, norm = networks[head]
    x = salient_codes(raw_rows(3 * MLP_BLOCK + 17), norm).features()
    whole = grid(x)
    assert np.isfinite(whole[7:]).all()
    order = np.random.default_rng(1).permutation(x.shape[0])
    np.testing.assert_array_equal(grid(x[order]), whole[order])  # other neighbours, other block positions
    np.testing.assert_array_equal(np.concatenate([grid(x[a : a + 37]) for a in range(0, x.shape[0], 37)]), whole)
    for i in (0, 2, 9, MLP_BLOCK, x.shape[0] - 1):
        np.testing.assert_array_equal(grid(x[i : i + 1])[0], whole[i])


@pytest.mark.parametrize("head", ["detection", "noise"])
def test_the_compact_encoding_gives_the_bits_of_the_one_hot_rows(networks, head):
    grid, one_hot, _, norm = networks[head]
    codes = salient_codes(raw_rows(MLP_BLOCK + 100), norm)  # rows 0-6: grids far from the ones', negative shifts
    np.testing.assert_array_equal(grid.of_codes(codes, one_hot), grid(codes.features()))


@pytest.mark.parametrize("head", ["detection", "noise"])
def test_within_float32_precision_of_the_float64_network(networks, head):
    grid, _, layers, norm = networks[head]
    x = salient_codes(raw_rows(20000)[7:], norm).features()  # KITTI-like rows only
    got, want = grid(x), float64_network(layers, x)
    # operands on 24-bit grids (float32's significand): measured 7e-6 at most on the shipped heads
    np.testing.assert_allclose(got, want, rtol=0, atol=3e-5)
    assert np.abs(got - want).max() > 0  # really the grid form, not the float64 products


def digests() -> dict[str, str]:
    """sha256 of the shipped heads' outputs on fixed rows (for a run under other kernels)."""
    out = {}
    for head, (grid, one_hot, _, norm) in {
        "detection": (load_pem()._grid, load_pem()._one_hot, None, load_pem().norm),
        "noise": (load_noise_pem()._grid, load_noise_pem()._one_hot, None, load_noise_pem().norm),
    }.items():
        codes = salient_codes(raw_rows(40960), norm)
        out[head] = hashlib.sha256(np.ascontiguousarray(grid.of_codes(codes, one_hot)).tobytes()).hexdigest()
        out[head + " features"] = hashlib.sha256(np.ascontiguousarray(grid(codes.features())).tobytes()).hexdigest()
    return out


@pytest.mark.skipif(not rp.DISPATCH_SETTINGS, reason="no dispatch settings")
@pytest.mark.parametrize("setting", ["OpenBLAS Haswell", "numpy without AVX-512", "all at their lowest"])
def test_other_kernels_give_the_same_bits(setting):
    # OpenBLAS's Haswell and Sandybridge kernels rounded these products differently before the grid form
    code = (
        "import json, sys; sys.path[:0] = ['tests/pem', 'tests']; import test_grid_mlp as t; "
        "print(json.dumps(t.digests()))"
    )
    env = {**os.environ, **rp.DISPATCH_SETTINGS[setting]}
    proc = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
        cwd=os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == digests()


def test_a_single_layer_is_an_affine_map_on_grids():
    # by hand: weights 3 and -0.5 (exact on any grid), bias 0.25; an inner dimension of 2 keeps 26 bits of each
    # input row's largest: 1e-3 < 2^-9 rounds to a multiple of 2^-35, the others are exact
    grid = GridMLP.of([(np.array([[3.0, -0.5]]), np.array([0.25]))])
    x = np.array([[1.0, 2.0], [0.5, -4.0], [0.0, 0.0], [1e-3, 0.0]])
    np.testing.assert_array_equal(
        grid(x)[:, 0], [3.0 - 1.0 + 0.25, 1.5 + 2.0 + 0.25, 0.25, np.rint(1e-3 * 2.0**35) * 2.0**-35 * 3.0 + 0.25]
    )


@settings(max_examples=200, deadline=None)
@given(
    cls=st.lists(st.sampled_from([0.0, 3.0, 6.0, 7.0, -1.0, 2.5, np.nan, 1e30]), min_size=1, max_size=12),
    occ=st.sampled_from([0.0, 1.0, 2.0, 3.0, 0.5]),
    pose=st.floats(-1e6, 1e6, allow_nan=False),
)
def test_the_compact_encoding_reads_what_the_one_hot_rows_hold_or_names_the_first_bad_row(cls, occ, pose):
    norm = load_pem().norm
    n = len(cls)
    raw = np.zeros((n, 11))
    raw[:, 0], raw[:, 2], raw[:, 7:] = cls, occ, [pose, 1.7, 20.0 + pose, 0.1]
    nan_rows = [i for i, c in enumerate(cls) if np.isnan(c)]
    bad_class = [i for i, c in enumerate(cls) if c not in (0.0, 3.0, 6.0)]
    if nan_rows:  # non-finite values are named first
        with pytest.raises(ValueError, match=f"non-finite value in row {nan_rows[0]}$"):
            salient_codes(raw, norm)
    elif bad_class:
        with pytest.raises(ValueError, match=f"class .* in row {bad_class[0]} is not an integer in 0..6"):
            salient_codes(raw, norm)
    elif occ not in (0.0, 1.0, 2.0):
        with pytest.raises(ValueError, match="occlusion .* in row 0 is not an integer in 0..2"):
            salient_codes(raw, norm)
    else:  # by hand: the class's and the occlusion's one-hot columns, then the z-scored pose
        want = np.zeros((n, 14))
        want[np.arange(n), np.array(cls, dtype=int)] = 1.0
        want[:, 7 + int(occ)] = 1.0
        want[:, 10:] = (raw[:, 7:] - norm.mean) / norm.std
        np.testing.assert_array_equal(salient_codes(raw, norm).features(), want)
