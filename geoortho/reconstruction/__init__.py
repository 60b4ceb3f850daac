"""From photos to 3D: the sparse SfM (pycolmap), split-merge for large blocks, the dense surface."""
