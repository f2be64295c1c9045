"""Simulation: MJX-ready models, batched rollouts (MJX and CPU), and datasets on disk."""
