"""From a point cloud to DSM and DTM: gridding, tiles for large clouds, the ground filter, and
coverage to the edge of what the photos saw."""
