"""Training-data tools for the learned canonical-coordinate head (not part of the gsa package)."""
