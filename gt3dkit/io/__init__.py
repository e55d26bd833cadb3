"""Input loaders and atomic output writers."""
