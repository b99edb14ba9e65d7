"""The ``eskf`` array layouts (:mod:`iotnav.engines.eskf.layout`): declared once, contiguous, named."""

from __future__ import annotations

import numpy as np
import pytest

from iotnav.engines.eskf import EskfConfig, layout, noise_vector


@pytest.mark.parametrize(
    "lay", [layout.ERROR_STATE, layout.NOISE, layout.ACC, layout.ST, layout.PRM, layout.REC]
)
def test_blocks_tile_the_array(lay: layout.Layout) -> None:
    """Every element belongs to exactly one block, in declaration order, and describe() names each."""
    covered = np.zeros(lay.size, dtype=int)
    stop = 0
    for sl, _doc in lay.blocks.values():
        assert sl.start == stop
        covered[sl] += 1
        stop = sl.stop
    assert stop == lay.size and (covered == 1).all()
    text = lay.describe()
    assert all(name in text for name in lay.blocks)
    with pytest.raises(ValueError, match="declared twice"):
        lay.add(next(iter(lay.blocks)))


def test_error_state_sizes() -> None:
    """24 states without the scale factors (they come last), 30 with them."""
    assert (layout.N_BASE, layout.N_FULL) == (24, 30)
    assert layout.GNM.stop == layout.N_BASE and layout.SA.stop == layout.N_FULL
    assert layout.n_states(False) == 24 and layout.n_states(True) == 30


def test_noise_record_by_name_and_short_vectors_completed() -> None:
    """noise_vector fills the record by name; a 12-entry vector is completed with the documented defaults."""
    c = EskfConfig(gnss_corr_time_s=150.0, gnss_corr_time_v_s=200.0, gnss_receiver_filter_s=2.0)
    noise = noise_vector(c)
    assert noise.shape == (layout.NOISE_SIZE,)
    assert noise[layout.NZ_INV_TE_H] == 1.0 / 150.0 and noise[layout.NZ_INV_TE_V] == 1.0 / 200.0
    assert noise[layout.NZ_INV_TF] == 0.5
    np.testing.assert_array_equal(layout.noise_record(noise), noise)
    short = layout.noise_record(noise[:12])
    np.testing.assert_array_equal(short[:12], noise[:12])
    assert short[layout.NZ_K_A] == short[layout.NZ_K_S] == short[layout.NZ_INV_TF] == 0.0
    assert short[layout.NZ_INV_TE_V] == noise[layout.NZ_INV_TE_H]
    assert layout.noise_record(noise[:15])[layout.NZ_INV_TE_V] == noise[layout.NZ_INV_TE_H]
    with pytest.raises(ValueError, match="11 entries"):
        layout.noise_record(noise[:11])
