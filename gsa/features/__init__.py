"""Feature extractors (2D), lifting onto 3DGS models, background pruning."""
