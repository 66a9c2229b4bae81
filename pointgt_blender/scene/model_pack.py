"""The model packed into the .blend, so one .blend renders anywhere (a render farm without the .pgt).

The .pgt bytes live in a bytes custom property of a Text datablock '<file>.pgt' (visible in the Text Editor, where
its text says what it is); each object points to it (`object.pointgt.packed_model`), so duplicates share one
copy. Rendering extracts it once per Blender process into Blender's temporary folder, named by its SHA-256, and
loads it from there (after a .blend is opened, the add-on's warm-up extracts it in its background thread). A
packed model takes precedence over the file at the model path, as packed images do.
"""
from __future__ import annotations

import hashlib
import os
import threading

import bpy

from core.util.atomic import atomic_write_bytes
from core.util.errors import InputError, ModelFileError

DATA = "pointgt_model"      # bytes: the .pgt file
SHA = "pointgt_sha256"      # its SHA-256 (hex)
SOURCE = "pointgt_source"   # the file name it was packed from

_EXTRACTED: dict = {}  # sha -> extracted path (this Blender process)
_LOCK = threading.Lock()  # one extraction at a time (the warm-up thread and a frame may both ask)


def pack_file(path: str, name: str = ""):
    """A Text datablock holding the bytes of the model at `path` (an existing one with the same bytes is
    reused). Returns the Text."""
    with open(path, "rb") as fh:
        data = fh.read()
    sha = hashlib.sha256(data).hexdigest()
    for text in bpy.data.texts:
        if text.get(SHA) == sha and isinstance(text.get(DATA), bytes):
            return text
    base = name or os.path.basename(path)
    text = bpy.data.texts.new(base)
    text[DATA] = data
    text[SHA] = sha
    text[SOURCE] = os.path.basename(path)
    text.write(f"PointGT model '{os.path.basename(path)}' ({len(data)} bytes, SHA-256 {sha[:16]}...) is packed "
               f"into this .blend.\nThe PointGT sidebar's Unpack Model writes it back to a file.\n")
    text.use_fake_user = False
    return text


def packed_bytes(text) -> bytes:
    data = text.get(DATA)
    if not isinstance(data, bytes) or not data:
        raise ModelFileError(f"text '{text.name}' holds no packed PointGT model; unpack or re-import the model")
    return data


def extracted_path(text) -> str:
    """A file holding the packed model (written once per process, checked against its SHA-256)."""
    path, extract = extraction(text)
    return path if extract is None else extract()


def extraction(text):
    """(the file the packed model is extracted to, None when it is there already | a function that writes it
    there and returns the path). The function touches no Blender data, so a background thread may run it
    (bridge/warmup.py); it checks the SHA-256 and writes atomically, so running it twice is harmless."""
    data = packed_bytes(text)
    sha = text.get(SHA) or hashlib.sha256(data).hexdigest()
    path = _EXTRACTED.get(sha)
    if path is not None and os.path.isfile(path):
        return path, None
    name = text.name
    folder = os.path.join(bpy.app.tempdir or os.path.join(os.path.expanduser("~"), ".cache"), "pointgt-packed")
    path = os.path.join(folder, f"{sha}.pgt")

    def extract() -> str:
        with _LOCK:
            if _EXTRACTED.get(sha) == path and os.path.isfile(path):
                return path  # the other caller was first
            if hashlib.sha256(data).hexdigest() != sha:
                raise ModelFileError(f"the model packed in text '{name}' is damaged (checksum mismatch); unpack a "
                                     f"good copy or re-import the model")
            os.makedirs(folder, exist_ok=True)
            if not os.path.isfile(path) or os.path.getsize(path) != len(data):
                atomic_write_bytes(path, data, backup=False)
            _EXTRACTED[sha] = path
            return path

    return path, extract


def unpack(obj, filepath: str) -> str:
    """Write the object's packed model to `filepath` (an existing file is kept as .bak) and point the object (and
    every object sharing the packed copy) at it; the packed copy is removed when nobody uses it. Returns the
    absolute path."""
    text = obj.pointgt.packed_model
    if text is None:
        raise InputError(f"object '{obj.name}': its model is not packed")
    data = packed_bytes(text)
    path = bpy.path.abspath(filepath)
    if not path.lower().endswith(".pgt"):
        raise InputError(f"{path}: choose a file name ending in .pgt")
    os.makedirs(os.path.dirname(os.path.abspath(path)) or ".", exist_ok=True)
    atomic_write_bytes(path, data, backup=True)
    from ..operators.model_import import stored_path

    for other in bpy.data.objects:
        s = getattr(other, "pointgt", None)
        if s is not None and s.is_model and s.packed_model == text:
            s.packed_model = None
            s.model_path = stored_path(path)
    if text.users == 0:
        bpy.data.texts.remove(text)
    return path
