"""Sim-to-real gap diagnosis: logs, effects, replay, diagnosis, report and a blind benchmark."""
