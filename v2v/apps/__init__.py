"""v2v.apps: V2V safety applications run on the relative positioning output (truth or estimates)."""
