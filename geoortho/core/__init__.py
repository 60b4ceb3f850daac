"""What every stage stands on: cameras and poses, CRSs, surfaces, point clouds, hole filling,
worker pools, atomic outputs."""
