"""v2v.config."""
