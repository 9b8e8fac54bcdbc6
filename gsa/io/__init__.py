"""Model file formats: INRIA PLY (gsa.io.ply) and every other 3DGS format (gsa.io.formats)."""

from gsa.io.formats import FORMATS, FormatError, read_model, sniff, write_model
from gsa.io.ply import PlyError, read_ply, write_ply

__all__ = ["FORMATS", "FormatError", "PlyError", "read_model", "read_ply", "sniff", "write_model", "write_ply"]
