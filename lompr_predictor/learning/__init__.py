"""Learning: models, training, Bayesian tuning, metrics, reports and the model file.

ROS-free; the training pipeline (`pipeline.train_predictor`) is what `lompr train`, `lompr
evaluate`, the demo and the benches call.
"""
