"""v2v.world."""
