"""Held-out evaluation sources: which synthetic seeds ``fastgha eval`` measures (``--first-seed``)."""

from __future__ import annotations

import pytest

from fastgha_core.data.synthetic import HELDOUT_SEEDS
from fastgha_core.train.builders import build_eval_sources


def test_default_and_shifted_held_out_seeds():
    assert [s.seed for s in build_eval_sources("synthetic-heldout", 3, resolution=64)] == [1000000, 1000001, 1000002]
    assert [s.seed for s in build_eval_sources("synthetic-heldout", 4, resolution=64, first_seed=1000200)] == [1000200, 1000201, 1000202, 1000203]


def test_seeds_outside_the_held_out_range_are_refused(tmp_path):
    with pytest.raises(ValueError, match="held-out synthetic seeds"):
        build_eval_sources("synthetic-heldout", 4, resolution=64, first_seed=12)  # a training seed
    with pytest.raises(ValueError, match="held-out synthetic seeds"):
        build_eval_sources("synthetic-heldout", 4, resolution=64, first_seed=HELDOUT_SEEDS.stop - 2)  # runs past the range
    with pytest.raises(ValueError, match="synthetic held-out data only"):
        build_eval_sources(str(tmp_path), 4, resolution=64, first_seed=1000200)
