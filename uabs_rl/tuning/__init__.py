"""Hyper-parameter tuning: ``uabs-train -m hydra/sweeper=optuna`` (docs/tuning.md)."""
