"""Diffusion priors behind one interface, and what score distillation needs from them."""
