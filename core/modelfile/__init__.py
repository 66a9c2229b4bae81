"""The .pgt model file (one zip of JSON + raw little-endian arrays; numpy only, never unpickled)."""
from core.modelfile.pgt import FORMAT_VERSION, PgtFile, load_pgt, read_meta, save_pgt

__all__ = ["FORMAT_VERSION", "PgtFile", "load_pgt", "read_meta", "save_pgt"]
