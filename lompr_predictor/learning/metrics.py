# SPDX-License-Identifier: Apache-2.0
"""The seed paper's Table 1 metrics (docs/interface.md, metrics), per axis, and who leads by
them (`standings`), with whether the scored part can tell the leader at all
(`loss_difference_t`).

For a prediction p and the actual error a on the test window, with the training range
[low, high] of the error on that axis:

- normalised error n = (p - a) / (high - low) (the min-max normalisation of both p and a
  with the training range: the offsets cancel);
- MSE, RMSE, MAE of n in percent (MSE in %^2), and the same three of p - a in micrometres
  (MSE in um^2);
- IAE = int |n| dt, ISE = int n^2 dt, ITAE = int t |n| dt, ITSE = int t n^2 dt with n as a
  fraction (not %), t in seconds from the start of the test window, integrated by the
  trapezoidal rule over the sample stamps; a step longer than `max_step` (a gap) adds
  nothing, so a gap neither inflates nor hides the error.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from lompr_predictor.data.features import TARGETS
from lompr_predictor.stamps import seconds_since

#: The report's key of the BO-LSTM's committee (the mean of the study's best networks).
COMMITTEE = 'bo_lstm_committee'
#: The trained model's keys in a report: what it is compared with is every other model.
OWN_MODELS = ('bo_lstm', 'bo_lstm_generalist', COMMITTEE, 'published')
METRIC_NAMES = ('mse_pct', 'rmse_pct', 'mae_pct', 'mse_um2', 'rmse_um', 'mae_um',
                'iae', 'ise', 'itae', 'itse')


def _integral(t: np.ndarray, f: np.ndarray, max_step: float) -> float:
    """Trapezoidal integral of samples f(t), skipping steps longer than `max_step`."""
    step = np.diff(t)
    area = 0.5 * (f[1:] + f[:-1]) * step
    return float(area[step <= max_step].sum())


def axis_metrics(predicted: np.ndarray, actual: np.ndarray, seconds: np.ndarray,
                 low: float, high: float, max_step: float) -> dict[str, float]:
    """Table 1 metrics of one axis: (B,) predicted and actual [m], (B,) sample times [s]
    from the start of the test window, training range [low, high] [m]."""
    error = np.asarray(predicted, dtype=float) - np.asarray(actual, dtype=float)
    normalised = error / (high - low)
    micrometres = error * 1e6
    magnitude, square = np.abs(normalised), normalised ** 2
    return {
        'mse_pct': float(np.mean((100 * normalised) ** 2)),
        'rmse_pct': float(np.sqrt(np.mean((100 * normalised) ** 2))),
        'mae_pct': float(np.mean(np.abs(100 * normalised))),
        'mse_um2': float(np.mean(micrometres ** 2)),
        'rmse_um': float(np.sqrt(np.mean(micrometres ** 2))),
        'mae_um': float(np.mean(np.abs(micrometres))),
        'iae': _integral(seconds, magnitude, max_step),
        'ise': _integral(seconds, square, max_step),
        'itae': _integral(seconds, seconds * magnitude, max_step),
        'itse': _integral(seconds, seconds * square, max_step),
    }


def table_metrics(predicted: np.ndarray, actual: np.ndarray, stamps_ns: np.ndarray,
                  low: np.ndarray, high: np.ndarray,
                  max_step: float) -> dict[str, dict[str, float]]:
    """{axis: metrics} for (B, 2) predictions of the instants `stamps_ns` (int64 ns);
    t counts from the first of them."""
    seconds = seconds_since(stamps_ns)
    return {axis: axis_metrics(predicted[:, i], actual[:, i], seconds, float(low[i]),
                               float(high[i]), max_step)
            for i, axis in enumerate(TARGETS)}


def score_predictions(predictions: Mapping[str, np.ndarray], actual: np.ndarray,
                      stamps_ns: np.ndarray, low: np.ndarray, high: np.ndarray,
                      max_step: float) -> dict[str, dict[str, Any]]:
    """{model: {'metrics': Table 1 metrics per axis}} of each model's (B, 2) prediction of the
    same instants: the `models` part of a report."""
    return {name: {'metrics': table_metrics(predicted, actual, stamps_ns, low, high, max_step)}
            for name, predicted in predictions.items()}


#: The one-sided 5 % point of the standard normal: one model's loss exceeds another's by more
#: than chance at that level when the t of their difference is above it.
CRITICAL_T = 1.645


def loss_difference_t(difference: np.ndarray) -> float:
    """The t statistic of the mean of a loss difference series: its mean over the standard
    error of the means of ceil(sqrt(n)) long consecutive blocks (a Diebold-Mariano t whose
    correlated neighbours are not counted as independent evidence); 0 for a series of zeros,
    infinite for a constant positive one, 0 with fewer than two blocks (nothing to tell)."""
    n = len(difference)
    length = int(np.ceil(np.sqrt(n)))
    blocks = n // length if length else 0
    if blocks < 2:
        return 0.0
    means = np.asarray(difference[:blocks * length], dtype=np.float64).reshape(
        blocks, length).mean(axis=1)
    mean, spread = float(means.mean()), float(means.std(ddof=1))
    if spread == 0.0:
        return 0.0 if mean == 0.0 else float(np.copysign(np.inf, mean))
    return mean / (spread / np.sqrt(blocks))


def ratios(metrics: dict[str, dict[str, float]],
           baseline: dict[str, dict[str, float]]) -> dict[str, dict[str, Any]]:
    """Each metric divided by the baseline's (the paper's 'x % of BP' headline)."""
    return {axis: {name: (value / baseline[axis][name] if baseline[axis][name] else None)
                   for name, value in values.items()}
            for axis, values in metrics.items()}


def standings(models: Mapping[str, Any], published: Mapping[str, str] | None = None,
              errors: Mapping[str, np.ndarray] | None = None) -> dict[str, dict[str, Any]]:
    """Per axis, where the BO-LSTM stands on the test part by RMSE: the model that leads
    (of all), the best baseline (every model but the BO-LSTM's own: its fallback, what it
    publishes, `OWN_MODELS`) and the BO-LSTM's RMSE over that baseline's, minus 1
    (negative: it leads by that share; 0: a tie, as on an axis the error has no part in);
    and the model the axis publishes (`published`: axis -> its key, by default the BO-LSTM),
    with its RMSE over the best baseline's, minus 1; likewise the BO-LSTM's committee where
    the report scores one (`COMMITTEE`). With each model's (B, 2) test errors (`errors`),
    also the t of each one's squared error minus the best baseline's (`loss_difference_t`;
    positive: behind it): below `CRITICAL_T` in size, the test part cannot tell them
    apart."""
    out: dict[str, dict[str, Any]] = {}
    for i, axis in enumerate(TARGETS):
        rmse = {name: float(entry['metrics'][axis]['rmse_um'])
                for name, entry in models.items()}
        baselines = {name: value for name, value in rmse.items() if name not in OWN_MODELS}
        best = min(baselines, key=lambda name: baselines[name])
        theirs = baselines[best]
        chosen = (published or {}).get(axis, 'bo_lstm')
        out[axis] = {'leader': min(rmse, key=lambda name: rmse[name]),
                     'best_baseline': best, 'best_baseline_rmse_um': theirs,
                     'bo_lstm_rmse_um': rmse['bo_lstm'],
                     'bo_lstm_vs_best_baseline': _share(rmse['bo_lstm'], theirs),
                     'published': chosen, 'published_rmse_um': rmse[chosen],
                     'published_vs_best_baseline': _share(rmse[chosen], theirs)}
        if COMMITTEE in rmse:
            out[axis].update(committee_rmse_um=rmse[COMMITTEE],
                             committee_vs_best_baseline=_share(rmse[COMMITTEE], theirs))
        if errors is not None:
            out[axis].update(
                bo_lstm_vs_best_baseline_t=_t_against(errors, 'bo_lstm', best, i),
                published_vs_best_baseline_t=_t_against(errors, chosen, best, i))
            if COMMITTEE in rmse:
                out[axis]['committee_vs_best_baseline_t'] = _t_against(errors, COMMITTEE,
                                                                       best, i)
    return out


def _t_against(errors: Mapping[str, np.ndarray], name: str, baseline: str, axis: int) -> float:
    """`loss_difference_t` of `name`'s squared error [um^2] minus `baseline`'s on one axis."""
    ours, theirs = (np.asarray(errors[key][:, axis], dtype=np.float64) * 1e6
                    for key in (name, baseline))
    return loss_difference_t(ours ** 2 - theirs ** 2)


def _share(ours: float, theirs: float) -> float:
    """`ours` over `theirs`, minus 1 (0 where `theirs` is 0)."""
    return ours / theirs - 1.0 if theirs > 0 else 0.0


#: What `standing_text` calls a published model its caller has no label for.
PUBLISHED_LABELS = {'published': 'the mean of the candidates kept',
                    COMMITTEE: 'its committee (the mean of the best networks)'}
#: Baselines that have no form a model file can hold (trees: no TorchScript).
NOT_EXPORTABLE = ('hgb', 'hgb_no_preview')


def standing_text(axis: str, standing: Mapping[str, Any], labels: Mapping[str, str]) -> str:
    """One line on where the BO-LSTM stands on `axis` (`standings`), models by `labels`,
    then its committee where the report scored one, and what the axis publishes where that
    is not the BO-LSTM or a baseline leads it; a margin the test part cannot tell from
    chance (its t, where the standing has one) says so."""
    share = standing['bo_lstm_vs_best_baseline']
    best = labels.get(standing['best_baseline'], standing['best_baseline'])
    if share < 0:
        text = f'{axis.upper()}: the BO-LSTM leads, {-100 * share:.1f} % below {best}'
    elif share == 0:
        text = f'{axis.upper()}: the BO-LSTM ties {best}'
    else:
        text = f'{axis.upper()}: {best} leads, the BO-LSTM {100 * share:.1f} % behind it'
    text += _chance(share, standing.get('bo_lstm_vs_best_baseline_t'))
    if 'committee_vs_best_baseline' in standing:
        committee_share = standing['committee_vs_best_baseline']
        text += (f'; its committee {_behind(committee_share, best)}'
                 + _chance(committee_share, standing.get('committee_vs_best_baseline_t')))
    chosen = standing.get('published', 'bo_lstm')
    published_share = standing.get('published_vs_best_baseline', share)
    if chosen != 'bo_lstm':
        label = labels.get(chosen) or PUBLISHED_LABELS.get(chosen, chosen)
        text += (f"; {label} published (the validation part's choice), "
                 f'{_behind(published_share, best)}'
                 + _chance(published_share, standing.get('published_vs_best_baseline_t')))
    if standing['best_baseline'] in NOT_EXPORTABLE and published_share > 0:
        text += f'; {best} cannot be exported to TorchScript'
    return text


def _chance(share: float, t: float | None) -> str:
    """' (within chance on the test part: t ...)' where a margin `share` has a t below
    `CRITICAL_T` in size; nothing for a tie or a margin without its t."""
    if t is None or share == 0 or abs(t) >= CRITICAL_T:
        return ''
    return f' (within chance on the test part: t {t:+.2f})'


def _behind(share: float, best: str) -> str:
    """How a model (published, or the committee) stands against the best baseline `best`."""
    if share < 0:
        return f'{-100 * share:.1f} % below {best}'
    return f'as good as {best}' if share == 0 else f'{100 * share:.1f} % behind {best}'
