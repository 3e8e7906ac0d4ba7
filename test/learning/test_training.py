# SPDX-License-Identifier: Apache-2.0
"""learning.training's small parts, by hand: the training windows sampled evenly, the
normalisation's moments (a constant column kept at scale 1), each network of a pair given
the same targets (the training itself: test_models, test_objective)."""

from __future__ import annotations

import numpy as np
import torch

from lompr_predictor.learning.training import each_output, evenly_spaced, moments


def test_windows_are_sampled_evenly_from_the_first_to_the_last() -> None:
    ends = np.arange(100, 200)
    np.testing.assert_array_equal(evenly_spaced(ends, 5), [100, 124, 149, 174, 199])
    assert evenly_spaced(ends, 100) is ends and evenly_spaced(ends, 1000) is ends


def test_moments_keep_a_constant_column_at_scale_one() -> None:
    values = np.array([[1.0, 5.0], [3.0, 5.0]])
    centre, scale = moments(values)
    np.testing.assert_array_equal(centre, [2.0, 5.0])
    np.testing.assert_array_equal(scale, [1.0, 1.0])  # std 1 and a constant column's 1
    _, spread = moments(np.array([[0.0], [4.0]]))
    np.testing.assert_array_equal(spread, [2.0])


def test_a_pairs_two_networks_learn_the_same_targets() -> None:
    targets = torch.tensor([[1.0, 2.0], [3.0, 4.0]])
    assert each_output(torch.zeros(2, 4), targets).tolist() == [[1.0, 2.0, 1.0, 2.0],
                                                               [3.0, 4.0, 3.0, 4.0]]
    assert torch.equal(each_output(torch.zeros(2, 2), targets), targets)
