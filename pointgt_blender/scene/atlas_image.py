"""The packed atlas as a Blender image datablock, and back.

The .pgt atlas is display-space (sRGB-encoded) float [H, W, 3] with row 0 at the top. The Blender image is a
float buffer in scene-linear Rec.709 with row 0 at the bottom: Blender's paint tools and colour management work
on it natively, it packs into the .blend as OpenEXR, and a pack/save/reload cycle returns the same floats
(checked in tests/pointgt_blender). Alpha is always 1: Blender premultiplies float images with alpha < 1 when
packing, which would change the colours.
"""
from __future__ import annotations

import numpy as np

from core.util.errors import InputError


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values [...] in [0, 1] -> scene-linear (the IEC 61966-2-1 curve), float32."""
    c = np.clip(np.asarray(c, dtype=np.float32), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    """Scene-linear values [...] -> sRGB-encoded in [0, 1], float32 (inverse of srgb_to_linear)."""
    c = np.clip(np.nan_to_num(np.asarray(c, dtype=np.float32), nan=0.0), 0.0, 1.0)
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * c ** (1 / 2.4) - 0.055).astype(np.float32)


def atlas_to_pixels(atlas: np.ndarray) -> np.ndarray:
    """Display-space atlas [H, W, 3] (row 0 = top) -> Blender pixel buffer [H*W*4] float32 (linear, row 0 =
    bottom, alpha 1)."""
    if atlas.ndim != 3 or atlas.shape[2] not in (3, 4) or atlas.shape[0] < 1 or atlas.shape[1] < 1:
        raise InputError(f"atlas image must have shape [H, W, 3]; got {list(atlas.shape)}")
    h, w = atlas.shape[:2]
    rgba = np.ones((h, w, 4), dtype=np.float32)
    rgba[..., :3] = srgb_to_linear(np.nan_to_num(atlas[..., :3], nan=0.0))
    return np.ascontiguousarray(rgba[::-1]).reshape(-1)


def pixels_to_atlas(pixels: np.ndarray, height: int, width: int, linear: bool = True) -> np.ndarray:
    """Blender pixel buffer [H*W*4] (row 0 = bottom; scene-linear, or already display-space when `linear` is
    False) -> display-space atlas [H, W, 3] (row 0 = top)."""
    rgb = np.asarray(pixels, dtype=np.float32).reshape(height, width, 4)[::-1, :, :3]
    rgb = linear_to_srgb(rgb) if linear else np.clip(np.nan_to_num(rgb, nan=0.0), 0.0, 1.0)
    return np.ascontiguousarray(rgb, dtype=np.float32)


def new_atlas_image(name: str, atlas: np.ndarray):
    """Create a packed float image datablock holding `atlas` [H, W, 3]; returns the bpy Image."""
    import bpy

    pixels = atlas_to_pixels(atlas)
    h, w = atlas.shape[:2]
    image = bpy.data.images.new(name, width=w, height=h, alpha=True, float_buffer=True)
    try:
        image.colorspace_settings.name = "Linear Rec.709"
        image.pixels.foreach_set(pixels)
        image.update()
        image.pack()  # travels inside the .blend; generated float images pack as OpenEXR
    except Exception:
        bpy.data.images.remove(image)
        raise
    return image


def copy_atlas_image(image, name: str):
    """A packed copy of a Blender atlas image with bit-identical pixels (no colour conversion round trip)."""
    import bpy

    w, h = image.size
    buf = np.empty(w * h * image.channels, dtype=np.float32)
    image.pixels.foreach_get(buf)
    copy = bpy.data.images.new(name, width=w, height=h, alpha=True, float_buffer=bool(image.is_float))
    try:
        copy.colorspace_settings.name = image.colorspace_settings.name
        if image.channels != copy.channels:
            raise InputError(f"image '{image.name}' has {image.channels} channels; PointGT atlases have 4")
        copy.pixels.foreach_set(buf)
        copy.update()
        copy.pack()
    except Exception:
        bpy.data.images.remove(copy)
        raise
    return copy


def read_atlas_image(image) -> np.ndarray:
    """The display-space atlas [H, W, 3] float32 (row 0 = top) held by a Blender image (painted or not)."""
    w, h = image.size
    if w == 0 or h == 0:
        raise InputError(f"image '{image.name}' has no pixels (missing file?); reload or re-import the model")
    buf = np.empty(w * h * image.channels, dtype=np.float32)
    image.pixels.foreach_get(buf)
    if image.channels != 4:
        rgba = np.ones((h * w, 4), dtype=np.float32)
        rgba[:, :min(3, image.channels)] = buf.reshape(h * w, image.channels)[:, :3]
        buf = rgba.reshape(-1)
    # byte images (an artist's PNG) hand out their stored sRGB-encoded values; float buffers are scene-linear
    return pixels_to_atlas(buf, h, w, linear=bool(image.is_float))


def repack_painted_atlases() -> list[str]:
    """Pack again every packed PointGT atlas whose pixels changed (painting or paint transfer), so the .blend
    saves the painted atlas, not the one packed at import. Atlases kept as files outside the .blend are left to
    Blender's own image saving. Returns the image names."""
    import bpy

    done = []
    for obj in bpy.data.objects:
        s = getattr(obj, "pointgt", None)
        img = s.atlas if s is not None and s.is_model else None
        if img is not None and img.name not in done and img.packed_file is not None and img.is_dirty:
            img.pack()
            done.append(img.name)
    return done
