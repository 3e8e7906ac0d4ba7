# SPDX-License-Identifier: Apache-2.0
"""learning.report: report.md as a reader gets it, for an evaluation by hand: the run's
settings, a table per axis with every model's metrics, the model file's sha256 and where
else it is, the data counts and a skipped bag, the tuning's line on a network that kept its
ridge start and on a committee smaller than asked (a training's report: test/cli/test_train)."""

from __future__ import annotations

from lompr_predictor.learning.metrics import METRIC_NAMES
from lompr_predictor.learning.report import markdown, model_label


def metrics(scale: float) -> dict[str, dict[str, float]]:
    return {axis: {name: scale * (k + 1) for k, name in enumerate(METRIC_NAMES)}
            for axis in ('x', 'y')}


def evaluation(**changes: object) -> dict[str, object]:
    report: dict[str, object] = {
        'command': 'evaluate', 'horizon': 5, 'window': 25, 'sample_period': 0.001,
        'split': {'test': 1234}, 'counts': {'joint_read': 2000, 'segments': 2},
        'bags': [{'path': 'a'}, {'path': 'b', 'skipped_reason': 'truncated'}],
        'models': {'model': {'metrics': metrics(1.0)},
                   'persistence': {'metrics': metrics(2.0), 'label': 'Persistence'}},
        'model_sha256': 'ab' * 32, 'model_file': 'm.pt', 'model_sha256_file': 'm.pt.sha256'}
    report.update(changes)
    return report


def test_an_evaluation_reads_as_its_settings_tables_file_and_data() -> None:
    text = markdown(evaluation())
    lines = text.splitlines()
    assert lines[0] == '# lompr evaluate report'
    assert lines[2] == ('Horizon 5 samples (0.005 s), window 25 samples, sample period 1 ms; '
                        'scored on all 1234 windows of the recordings.')
    header = lines.index('## Axis X') + 2
    assert lines[header] == '| metric | Model | Persistence |'
    assert lines[header + 2] == '| MSE (%^2) | 1 | 2 |'  # the first metric, 1 and 2 x 1
    assert '| RMSE (um) | 5 | 10 |' in lines  # the fifth metric
    assert f"Model file `m.pt`, sha256 `{'ab' * 32}` (also in `m.pt.sha256`; pin it" in text
    assert '- joint_read: 2000' in lines and '- skipped bag b: truncated' in lines
    without_sidecar = markdown(evaluation(model_sha256_file=None))
    assert 'also in' not in without_sidecar and '`None`' not in without_sidecar


def test_a_model_is_named_by_its_label_else_the_known_name_else_its_key() -> None:
    assert model_label('x', {'label': 'Mine'}) == 'Mine'
    assert model_label('bo_lstm', {}) == 'BO-LSTM'
    assert model_label('ridge_7', {}) == 'ridge_7'


def test_a_network_that_kept_its_ridge_start_is_said_so() -> None:
    tuning = {'study_name': 's', 'trials_spent': 3, 'trials_run_now': 3, 'best_trial': 1,
              'best_value': 0.5, 'best_params': {'hidden': 8}, 'best_epoch': 0}
    study = next(line for line in markdown(evaluation(tuning=tuning)).splitlines()
                 if line.startswith('Study `s`'))
    assert study == ("Study `s` (3 trials spent, 3 in this run); best trial 1 with validation "
                     "MSE 0.5: {'hidden': 8}. Its best epoch is 0, its ridge start: no epoch "
                     'predicted the validation part better than the ridge over its window (its '
                     'LSTM adds nothing there).')
    trained = markdown(evaluation(tuning={**tuning, 'best_epoch': 7}))
    assert "{'hidden': 8}." in trained and 'ridge start' not in trained
    held = markdown(evaluation(tuning={**tuning, 'best_epoch': 7, 'best_highway_held': True}))
    assert ("{'hidden': 8}. Its linear highway was held at its ridge start (too few training "
            "windows for the highway's width to train it on, `--highway`); its LSTM and head "
            'trained.') in held
    # a network that is its ridge start says that alone
    at_start = markdown(evaluation(tuning={**tuning, 'best_highway_held': True}))
    assert 'Its best epoch is 0' in at_start and 'highway was held' not in at_start


def test_restarts_not_run_at_a_ridge_start_are_said_so() -> None:
    """Two restarts asked, none run, the best network its ridge start: the line says so;
    every restart run, or a network trained past its start, says nothing on restarts."""
    tuning = {'study_name': 's', 'trials_spent': 3, 'trials_run_now': 3, 'best_trial': 1,
              'best_value': 0.5, 'best_params': {'hidden': 8}, 'best_epoch': 0,
              'restarts': 2, 'restarts_run': 0}
    assert ('Its point was restarted 0 of the 2 times asked for: every seed starts at that '
            'same ridge, so another seed has nothing else to begin from.'
            in markdown(evaluation(tuning=tuning)))
    for changes in ({'restarts_run': 2}, {'best_epoch': 7}):
        assert 'restarted' not in markdown(evaluation(tuning={**tuning, **changes}))


def test_a_committee_below_its_size_says_why() -> None:
    """Five networks asked, four trials complete, one distinct: the line says one of five
    and why; a study of one trial, or a full committee, says nothing on it."""
    tuning = {'study_name': 's', 'trials_spent': 4, 'trials_run_now': 4, 'best_trial': 1,
              'best_value': 0.5, 'best_params': {'hidden': 8}, 'best_epoch': 0,
              'committee': [{'trial': 1, 'value': 0.5}], 'committee_asked': 5,
              'trials_complete': 4, 'budget': 4, 'trials_pruned': 0, 'trials_failed': 0,
              'workers': {}}
    text = markdown(evaluation(tuning=tuning))
    assert ("Its committee is 1 of the 5 networks asked for: the other complete trials' "
            "validation losses equal a member's to the last bit") in text
    for changes in ({'trials_complete': 1}, {'committee_asked': 1}):
        assert 'Its committee' not in markdown(evaluation(tuning={**tuning, **changes}))
