"""3D products that viewers open directly: the point cloud as COPC."""
