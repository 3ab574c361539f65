"""Dynamics: the paper's systems, KNODE hybrid models and their training (Algorithm 1)."""
