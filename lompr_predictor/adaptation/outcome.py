# SPDX-License-Identifier: Apache-2.0
"""What an adaptation attempt decided and why, typed: the one document that passes from the
attempt process to the node (`result.json`, read once the process has ended) and into the
node's log (`adaptation.jsonl`).

A document the node cannot read as a result (missing, not JSON, a decision it does not
know) is an attempt that failed, with the reason; fields the node does not know are kept
for the log.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

from lompr_predictor.online.inference import ExportedGraph


class Decision(StrEnum):
    """How an attempt ended."""

    ACCEPTED = 'accepted'  # a candidate better than the model in force by the margin
    REFUSED = 'refused'  # a candidate, not better by the margin
    FAILED = 'failed'  # no candidate: the process failed, was killed, or the swap failed
    #: the model in force cannot be fine-tuned at all (not a BO-LSTM, its network not
    #: rebuildable): no attempt runs again until another model is in force
    CANNOT_ADAPT = 'cannot adapt'


@dataclass(frozen=True)
class AttemptResult:
    """An attempt's decision, why, and what it measured and wrote."""

    decision: Decision
    reason: str
    parent: str = ''  # the model file in force it started from
    parent_sha256: str = ''
    scores_um: dict[str, float] = field(default_factory=dict)  # XY RMS on the held-out part
    held_out_seconds: float = 0.0
    epochs: int = 0
    best_epoch: int = 0
    data: dict[str, Any] = field(default_factory=dict)  # what it learned from (`data_span`)
    model_path: str = ''  # the model it wrote ('': none)
    model_sha256: str = ''
    seconds: float = 0.0  # the attempt's own time
    cpu: dict[str, Any] = field(default_factory=dict)  # `threads.CoreUse.summary`

    @classmethod
    def failed(cls, reason: str) -> AttemptResult:
        return cls(Decision.FAILED, reason)

    @classmethod
    def from_json(cls, document: object) -> AttemptResult:
        """The result a document says (unknown keys dropped), or a failed one saying what
        is wrong with it."""
        if not isinstance(document, dict):
            return cls.failed('the attempt wrote no result document')
        try:
            decision = Decision(str(document.get('decision')))
        except ValueError:
            return cls.failed(f'the attempt wrote an unknown decision {document.get("decision")!r}')
        known = {item.name for item in dataclasses.fields(cls)} - {'decision'}
        try:
            return cls(decision, **{key: value for key, value in document.items()
                                    if key in known})
        except TypeError as err:
            return cls.failed(f'the attempt wrote an unreadable result: {err}')

    @classmethod
    def read(cls, path: Path) -> AttemptResult | None:
        """The result in `path`, None if there is no readable JSON there."""
        try:
            return cls.from_json(json.loads(path.read_text(encoding='utf-8')))
        except (OSError, ValueError):
            return None

    def to_json(self) -> dict[str, Any]:
        """The document (the decision as its text)."""
        return {**dataclasses.asdict(self), 'decision': str(self.decision)}


@dataclass
class AttemptOutcome:
    """How one attempt ended, as the node saw it."""

    number: int
    started_clock_ns: int  # the node's clock when it started...
    ended_clock_ns: int  # ... and when its end was seen
    result: AttemptResult
    graph: ExportedGraph | None = None  # an accepted model's, exported by the attempt

    @property
    def decision(self) -> Decision:
        return self.result.decision

    @property
    def model(self) -> tuple[str, str]:
        """(path, sha256) of the model it wrote ('', '': none)."""
        return self.result.model_path, self.result.model_sha256

    def with_reason(self, reason: str, decision: Decision | None = None) -> None:
        """Say why in other words (and, given, decide otherwise): the node knows more than
        the attempt did (a swap that failed, a reset while it ran)."""
        self.result = dataclasses.replace(self.result, reason=reason,
                                          decision=decision or self.result.decision)
