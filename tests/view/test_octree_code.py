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


@settings(max_examples=25, deadline=None)
@given(n=st.integers(1, 300), depth=st.integers(1, 10), bits=st.integers(1, 8), seed=st.integers(0, 10_000))
def test_pack_and_offsets_roundtrip(n, depth, bits, seed):
    """pack → unpack → decode gives the same centres; the normal offset refines each point
    along its normal to within half a bin (reference: the exact signed distance)."""
    from opacityhull.view.octree_code import OFFSET_RANGE, apply_offsets, encode_offsets, pack, unpack

    rng = np.random.default_rng(seed)
    P = rng.uniform(-1, 1, (n, 3))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm[0] = 0.0  # a surfel without a normal keeps its cell centre
    oc = encode_positions(P, depth)
    head, cz, nz = pack(oc)
    C = decode_positions(unpack(head, cz, nz))
    np.testing.assert_array_equal(C, decode_positions(oc))
    h = oc.size / 2**depth
    Po, No = P[oc.order], nrm[oc.order]
    q = encode_offsets(Po, C, No, h, bits)
    Q = apply_offsets(C, No, q, h, bits)
    lam_true = np.sum((Po - C) * No, axis=1)
    lam_got = np.sum((Q - C) * No, axis=1)
    has_n = np.linalg.norm(No, axis=1) > 0
    assert np.all(np.abs(lam_true - lam_got)[has_n] <= OFFSET_RANGE / 2**bits * h * (1 + 1e-9) + 1e-12)
    np.testing.assert_array_equal(Q[~has_n], C[~has_n])
    # the point moved only along its normal
    np.testing.assert_allclose(np.cross(Q - C, No), 0.0, atol=1e-12)


def test_unpack_rejects_corrupt_streams():
    from opacityhull.view.octree_code import apply_offsets, pack, unpack

    oc = encode_positions(np.random.default_rng(2).random((200, 3)), 3)
    head, cz, nz = pack(oc)
    assert len(nz)  # 200 points in 8³ cells: some share
    with pytest.raises(FormatError, match="unreadable"):
        unpack(head, cz[:-4], nz)
    with pytest.raises(FormatError, match="counts sum"):
        unpack({**head, "n_points": 199}, cz, nz)
    with pytest.raises(FormatError, match="byte codes"):
        unpack({**head, "n_codes": head["n_codes"] + 1}, cz, nz)
    with pytest.raises(FormatError, match="out of range"):
        apply_offsets(np.zeros((2, 3)), np.ones((2, 3)), np.array([0, 8]), 1.0, 3)
