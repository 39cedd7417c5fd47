"""Octree position coding (Botsch et al. 2002): decode(encode(P)) gives every point's cell
centre, checked against a plain quantisation; compact on surfaces; corrupt streams fail."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opacityhull.errors import FormatError, InputError
from opacityhull.render.synthetic import fibonacci_sphere
from opacityhull.view.octree_code import OctreeCode, decode_positions, encode_positions


@settings(max_examples=25, deadline=None)
@given(n=st.integers(1, 400), depth=st.integers(1, 12), seed=st.integers(0, 10_000), dup=st.booleans())
def test_roundtrip_equals_cell_centres(n, depth, seed, dup):
    rng = np.random.default_rng(seed)
    P = rng.uniform(-1, 3, (n, 3))
    if dup:
        P[: n // 2] = P[0]
    oc = encode_positions(P, depth)
    dec = decode_positions(oc)
    assert sorted(oc.order.tolist()) == list(range(n))
    # reference: quantise each point on its own and take the centre of its cell
    h = oc.size / 2**depth
    cell = np.clip(np.floor((P - oc.origin) / h), 0, 2**depth - 1)
    np.testing.assert_allclose(dec, (oc.origin + (cell + 0.5) * h)[oc.order], atol=1e-9 * oc.size)
    assert np.all(np.abs(dec - P[oc.order]) <= 0.5 * h + 1e-9 * oc.size)


def test_compact_on_a_surface():
    n = 50_000
    P = 0.08 * fibonacci_sphere(n)
    spacing = np.sqrt(4 * np.pi * 0.08**2 / n)
    oc = encode_positions(P, cell_m=spacing)
    # branching ≈ 4 per level: ≈ 8/3 bits per cell before entropy coding
    n_cells = len(oc.counts) if len(oc.counts) else n
    assert 8 * len(oc.codes) / n_cells < 4.0
    assert 8 * len(__import__("zlib").compress(oc.codes.tobytes(), 9)) / n < 3.0
    assert oc.bits_per_point() < 4.0  # with the per-cell counts
    dec = decode_positions(oc)
    assert np.linalg.norm(dec - P[oc.order], axis=1).max() <= np.sqrt(3) / 2 * spacing + 1e-12


def test_corrupt_streams():
    oc = encode_positions(np.random.default_rng(1).random((100, 3)), 6)
    with pytest.raises(FormatError, match="ends at level"):
        decode_positions(OctreeCode(oc.origin, oc.size, oc.depth, oc.codes[:-5], oc.counts, oc.order))
    bad = oc.codes.copy()
    bad[3] = 0
    with pytest.raises(FormatError):
        decode_positions(OctreeCode(oc.origin, oc.size, oc.depth, bad, oc.counts, oc.order))
    with pytest.raises(InputError, match="non-finite"):
        encode_positions(np.array([[0.0, np.nan, 0.0]]), 4)
    with pytest.raises(InputError, match="exactly one"):
        encode_positions(np.zeros((3, 3)))
