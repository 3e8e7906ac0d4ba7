# SPDX-License-Identifier: Apache-2.0
"""Which recordings a run reads and how it cleans them, and the read-then-clean step itself:
what `lompr train` and `lompr evaluate` share before their data diverge.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lompr_predictor.data.bags import BagSource, BagTopics, read_bags
from lompr_predictor.data.cleaning import (
    CleanData,
    CleaningConfig,
    clean_recordings,
    implausible_error,
)
from lompr_predictor.errors import LomprError
from lompr_predictor.robot.chain import KinematicChain
from lompr_predictor.robot.description import ROBOT_FRAME


class ImplausibleDataError(LomprError):
    """The recordings' error is no machine's: the joints are mapped wrong (names swapped,
    another order or unit) or the description is another robot's."""


@dataclass(frozen=True)
class BagInputs:
    """rosbag2 directories, the topics to read, the frame their poses must be in, what to
    do with a bad bag, the cleaning rules."""

    bags: tuple[str, ...]
    topics: BagTopics = field(default_factory=BagTopics)
    skip_bad: bool = False  # a bad bag is left out whole and listed, instead of stopping
    #: The robot frame the reference is in (header.frame_id); a bag in another is refused.
    frame: str = ROBOT_FRAME
    cleaning: CleaningConfig = field(default_factory=CleaningConfig)


def load_clean_data(inputs: BagInputs,
                    chain: KinematicChain) -> tuple[CleanData, list[BagSource]]:
    """Read the bags whole (`bags.read_bags`, the joints by the chain's `joint_names`) and
    clean them (`cleaning.clean_recordings`); the sources list every bag, used or
    skipped. `ImplausibleDataError` (one line) when their error is no machine's
    (`cleaning.implausible_error`): every command reading joints (train, evaluate, with
    --closed-loop too) refuses a wrong mapping before it trains on, scores or compares
    millimetres of kinematics as an error."""
    recordings, sources = read_bags(inputs.bags, topics=inputs.topics,
                                    skip_bad=inputs.skip_bad, joint_names=chain.joint_names,
                                    frame=inputs.frame)
    data = clean_recordings(recordings, chain, inputs.cleaning)
    why = implausible_error(data)
    if why:
        raise ImplausibleDataError(why)
    return data, sources
