"""Measurements on the products: volumes (and, to come, change between flights)."""
