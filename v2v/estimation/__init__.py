"""v2v.estimation."""
