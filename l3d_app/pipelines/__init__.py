"""Pipelines: library code that composes the middle layer (render, models, losses, metrics, data,
strategies) for several tasks, with plain arguments (no Hydra): a task wires a pipeline to its config."""
