"""Evaluation of dynamics models on held-out data."""
