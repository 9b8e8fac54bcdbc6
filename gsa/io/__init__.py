"""Model file formats."""

from gsa.io.ply import PlyError, read_ply, write_ply

__all__ = ["PlyError", "read_ply", "write_ply"]
