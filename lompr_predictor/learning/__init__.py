# SPDX-License-Identifier: Apache-2.0
"""Learning: models, training, Bayesian tuning, metrics, reports and the model file.

ROS-free; the training pipeline (`trainer.train_predictor`) is what `lompr train`, the demo
and the training bench call, and `lompr evaluate` scores and reports with the same pieces
(`metrics.score_predictions`, `report.base_report`, `report.irreducible_fields`).
"""
