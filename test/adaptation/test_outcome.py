# SPDX-License-Identifier: Apache-2.0
"""adaptation.outcome: the typed result an attempt hands the node, and what a document the
node cannot read becomes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from lompr_predictor.adaptation.outcome import AttemptOutcome, AttemptResult, Decision


def test_a_result_goes_through_its_document_unchanged(tmp_path: Path) -> None:
    result = AttemptResult(Decision.ACCEPTED, 'better', 'm.pt', 'ab',
                           scores_um={'bo_lstm': 1.5, 'parent': 2.0}, held_out_seconds=12.5,
                           epochs=4, best_epoch=3, data={'samples': 900},
                           model_path='adapted-1.pt', model_sha256='cd', seconds=7.25,
                           cpu={'cores_max': 1.0})
    document = result.to_json()
    assert document['decision'] == 'accepted' and type(document['decision']) is str
    (tmp_path / 'result.json').write_text(json.dumps(document))
    assert AttemptResult.read(tmp_path / 'result.json') == result


@pytest.mark.parametrize(('document', 'reason'), [
    ([1, 2], 'the attempt wrote no result document'),
    ({'reason': 'x'}, 'the attempt wrote an unknown decision None'),
    ({'decision': 'maybe'}, "the attempt wrote an unknown decision 'maybe'"),
    ({'decision': 'refused'}, 'the attempt wrote an unreadable result: '),
])
def test_a_document_the_node_cannot_read_is_a_failed_attempt_saying_why(
        document: object, reason: str) -> None:
    result = AttemptResult.from_json(document)
    assert result.decision is Decision.FAILED and result.reason.startswith(reason)


def test_unknown_fields_are_dropped_and_no_file_reads_as_none(tmp_path: Path) -> None:
    result = AttemptResult.from_json({'decision': 'cannot adapt', 'reason': 'linear',
                                      'parent_sha256': 'ab', 'future_field': 3})
    assert result == AttemptResult(Decision.CANNOT_ADAPT, 'linear', parent_sha256='ab')
    assert AttemptResult.read(tmp_path / 'missing.json') is None
    (tmp_path / 'bad.json').write_text('{not json')
    assert AttemptResult.read(tmp_path / 'bad.json') is None


def test_the_node_can_decide_otherwise_and_say_why() -> None:
    outcome = AttemptOutcome(1, 0, 10, AttemptResult(Decision.ACCEPTED, 'better',
                                                     model_path='a.pt', model_sha256='ef'))
    assert outcome.model == ('a.pt', 'ef')
    outcome.with_reason('not swapped in: sha256 mismatch', Decision.FAILED)
    assert (outcome.decision, outcome.result.reason) == (
        Decision.FAILED, 'not swapped in: sha256 mismatch')
    assert outcome.model == ('a.pt', 'ef')  # what it wrote is still named in the log
