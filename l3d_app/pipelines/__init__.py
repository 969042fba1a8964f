"""Pieces composed from the middle layer that several tasks share: a method family's training and
evaluation, views scored against images, a finished run's renderer. Plain arguments, no config
objects: the tasks read their configs and call these."""
