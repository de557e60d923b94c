"""Loaders for public datasets used by the experiments (files in, numpy arrays out; no estimator code)."""
