"""Estimators and optimizers that produce camera models from decoded maps."""
