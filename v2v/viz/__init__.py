"""v2v.viz."""
