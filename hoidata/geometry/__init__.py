"""Geometry shared by the offline pipelines: transforms, mirroring, crops, signed distance."""
