# SPDX-License-Identifier: Apache-2.0
"""The paired model (`lompr train`'s default, network inputs 'paired'): the tuned network
that reads every feature and, beside it, one that reads the machine map's residuals alone.

Why. A network that reads the path learns what the programs it was trained on do next
(where they accelerate, reverse, turn): on those programs it is as good as boosted trees on
the same inputs and near the noise floor, on any other it can be worse than persistence. A
network that reads only what the machine map leaves of the error cannot learn the path: it
holds on programs it was not trained on and gives away that accuracy on the trained ones
(docs/results.md, "Programs"). The model file carries both (`models.PairedNet`); its
prediction is the first's, and the node's live guard publishes the second's (the model's
prior, `map_prior`) on an axis where the first does worse.

How. The tuning study tunes the first alone, the paper's BO-LSTM on every feature (its
validation loss is the model's). `train_generalist` then trains the second once at the best
point, on the same windows and normalisation, and `paired_module` joins the two into one
module with the first's constants. The generalist reads the map's residuals relative to the
window's last row only, never their level, even where the tuned point gives the first the
error level: what the map leaves of the error's level carries the machine's slow state
(heat, drift), which differs between programs and days, and read as input it took the
generalist to 2.9 / 4.2x persistence on a held-out program of the warming machine
(docs/lab/programs_transfer.md, "The map fitted on the error's changes"). Fine-tuning (`lompr train
--init`, online adaptation) trains both together, each on its own output.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from lompr_predictor.data.problem import LearningProblem
from lompr_predictor.learning.machine_map import MachineMap
from lompr_predictor.learning.models import (
    LSTM_STEPS,
    PredictorModule,
    build_network,
    network_features,
    paired_columns,
)
from lompr_predictor.learning.options import TrainSettings
from lompr_predictor.learning.training import TrainedModel, train_network

#: Relative difference allowed between the normalisation constants the two networks were
#: trained with for the same columns (both are moments of the same training windows, summed
#: in another order).
CONSTANTS_TOLERANCE = 1e-9


def train_generalist(problem: LearningProblem, params: Mapping[str, Any],
                     settings: TrainSettings, machine_map: MachineMap, *,
                     progress: bool = False) -> TrainedModel:
    """The network on the map's residuals alone ('machine' inputs, relative, without their
    level: module docstring) at the tuned point `params`, trained once."""
    return train_network(problem, 'lstm', {**params, 'error_level': False}, settings,
                         progress=progress, label='generalist', machine_map=machine_map,
                         network_inputs='machine')


def paired_module(specialist: Any, generalist: Any, machine_map: MachineMap,
                  problem: LearningProblem, params: Mapping[str, Any]) -> PredictorModule:
    """One module (trainable, `models.PairedNet`) of a trained specialist (a 'paired' inputs
    module with one network, scripted or not) and a trained generalist ('machine' inputs),
    both of `problem` on `machine_map` at the tuned point `params`; ValueError if their
    normalisations disagree."""
    state = specialist.state_dict()
    error_level = bool(params.get('error_level', False))
    machine = paired_columns(network_features(problem.features, True))
    for name in ('feature_centre', 'feature_inverse_half'):
        ours, theirs = state[name][machine], generalist.state_dict()[name]
        if not torch.allclose(ours, theirs, rtol=CONSTANTS_TOLERANCE, atol=0.0):
            msg = f'the generalist was trained with another normalisation ({name})'
            raise ValueError(msg)
    width = len(state['input_columns'])
    net = build_network('lstm', width, problem.window, int(params['hidden']),
                        int(params.get('lstm_steps', LSTM_STEPS)), machine)
    module = PredictorModule(net, np.zeros(width), np.ones(width), np.zeros(2), np.ones(2),
                             residual=True, relative_errors=True, error_level=error_level,
                             features=problem.features, machine_map=copy.deepcopy(machine_map),
                             inputs='paired')
    joined = {('net.specialist.' + key[4:] if key.startswith('net.') else key): value
              for key, value in state.items()}
    joined.update({'net.generalist.' + key[4:]: value
                   for key, value in generalist.state_dict().items() if key.startswith('net.')})
    joined['net.machine_columns'] = net.machine_columns
    module.load_state_dict(joined)
    module.eval()
    return module
