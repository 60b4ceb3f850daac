"""Ground control: coordinate files, where each GCP is in each photo, marker detection."""

from geoortho.gcp.io import GcpSet, GroundControlPoint, marker_id_of, read_gcp_file

__all__ = ["GcpSet", "GroundControlPoint", "marker_id_of", "read_gcp_file"]
