"""OpenEXR files with JSON metadata, written atomically: the tables (named 2D float32 or float16 arrays,
`write_exr`/`read_exr`) and the RGBA textures the Blender back ends read (`write_rgba_exr`)."""
import json
from pathlib import Path

import numpy as np

from ..errors import FlowBSDFError
from .files import atomic_path

META_KEY = "flowbsdf"


def write_exr(path, arrays, meta):
    """One part per array (2D, ZIP: lossless; float16 arrays as half, others as float32), metadata
    as JSON in the first header. Written to a temporary file in the same folder and renamed, so a
    crash leaves no broken file."""
    path = Path(path)
    import OpenEXR
    parts = []
    for i, (name, array) in enumerate(arrays.items()):
        array = np.asarray(array)
        array = np.ascontiguousarray(array, dtype=np.float16 if array.dtype == np.float16 else np.float32)
        if array.ndim != 2 or array.size == 0:
            raise ValueError(f"{name}: EXR parts hold non-empty 2D arrays, got shape {array.shape}")
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                  "displayWindow": ((0, 0), (0, 0))}
        if i == 0:
            header[META_KEY] = json.dumps(meta, sort_keys=True)
        parts.append(OpenEXR.Part(header, {"Y": array}, name=name))
    try:
        with atomic_path(path) as tmp:
            OpenEXR.File(parts).write(tmp)
    except OSError as e:
        where = f" ({e.filename})" if getattr(e, "filename", None) else ""
        raise FlowBSDFError(f"cannot write the table file: {e.strerror or e}{where}", path) from None


def write_rgba_exr(path, image, meta_key, meta, attributes=None):
    """One RGBA float32 image (ZIP: lossless) with `meta` as JSON in the header attribute `meta_key`
    (and `attributes`, {name: int or float (float32)}, as header attributes of their own)."""
    import OpenEXR
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              meta_key: json.dumps(meta, sort_keys=True), **(attributes or {})}
    with atomic_path(path) as tmp:
        OpenEXR.File(header, {"RGBA": np.ascontiguousarray(image)}).write(tmp)


def read_rgba_exr(path, meta_key, what):
    """(image (H, W, 4) float32, metadata) of an RGBA texture written by write_rgba_exr with
    `meta_key`; FlowBSDFError naming `what` ("OSL texture", ...) if it is missing or not one."""
    path = Path(path)
    if not path.is_file():
        raise FlowBSDFError(f"{what} not found", path)
    import OpenEXR
    try:
        f = OpenEXR.File(str(path))
        raw = f.header().get(meta_key)
        img = f.channels()["RGBA"].pixels
    except Exception as e:      # noqa: BLE001  (foreign or broken files)
        raise FlowBSDFError(f"not a readable FlowBSDF {what} ({e})", path) from None
    if raw is None:
        raise FlowBSDFError(f"an OpenEXR file, but not a FlowBSDF {what}", path)
    return img, json.loads(raw)


def read_exr(path):
    """(arrays by part name, metadata dict); FlowBSDFError naming the file on any problem."""
    path = Path(path)
    if not path.is_file():
        raise FlowBSDFError("table file not found", path)
    import OpenEXR
    try:
        f = OpenEXR.File(str(path))
        parts = f.parts
        arrays = {p.name(): p.channels["Y"].pixels for p in parts}
        raw = parts[0].header.get(META_KEY)
    except Exception as e:     # OpenEXR raises RuntimeError/KeyError/... on foreign or broken files
        raise FlowBSDFError(f"not a readable FlowBSDF table file ({e})", path) from None
    if raw is None:
        raise FlowBSDFError("an OpenEXR file, but not a FlowBSDF table (no metadata)", path)
    try:
        meta = json.loads(raw)
    except (TypeError, ValueError):
        raise FlowBSDFError("table metadata is not valid JSON", path) from None
    if not isinstance(meta, dict):
        raise FlowBSDFError(f"table metadata is not a JSON object (got {type(meta).__name__})", path)
    for name, a in arrays.items():
        if a.dtype not in (np.float32, np.float16):
            raise FlowBSDFError(f"part {name!r} is {a.dtype}, tables are float32 (and float16)", path)
    return arrays, meta
