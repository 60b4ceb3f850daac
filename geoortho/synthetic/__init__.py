"""Synthetic surveys with exact ground truth: the scene, the flight, the rendering."""
