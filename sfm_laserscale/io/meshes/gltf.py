"""GLB/glTF meshes rewritten with their float POSITION accessors (and morph-target positions)
rescaled inside the binary buffers, accessor min/max and node translations with them; the JSON is
re-serialised. Draco-compressed, quantised or sparse positions are refused."""

from __future__ import annotations

import base64
import json
import struct
from pathlib import Path
from typing import Any

import numpy as np

from sfm_laserscale.errors import InputError
from sfm_laserscale.io.meshes.common import _AtomicOutput, _copy_side_file

_GLB_MAGIC = b"glTF"
_GLB_JSON, _GLB_BIN = 0x4E4F534A, 0x004E4942
_GLTF_FLOAT = 5126


def _read_glb(path: Path) -> tuple[dict[str, Any], bytearray | None]:
    """GLB -> (JSON dict, BIN chunk or None)."""
    raw = path.read_bytes()
    if len(raw) < 20 or raw[:4] != _GLB_MAGIC:
        raise InputError("not a GLB file (bad magic)", path)
    version, length = struct.unpack_from("<II", raw, 4)
    if version != 2 or length > len(raw):
        raise InputError(f"unsupported or truncated GLB (version {version})", path)
    pos, doc, binary = 12, None, None
    while pos + 8 <= length:
        size, kind = struct.unpack_from("<II", raw, pos)
        chunk = raw[pos + 8: pos + 8 + size]
        if len(chunk) != size:
            raise InputError("truncated GLB chunk", path)
        if kind == _GLB_JSON and doc is None:
            doc = _parse_json(chunk, path)
        elif kind == _GLB_BIN and binary is None:
            binary = bytearray(chunk)
        pos += 8 + size
    if doc is None:
        raise InputError("GLB has no JSON chunk", path)
    return doc, binary


def _parse_json(raw: bytes, path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"invalid glTF JSON: {exc}", path) from exc
    if not isinstance(doc, dict):
        raise InputError("invalid glTF JSON: not an object", path)
    return doc


def _glb_bytes(doc: dict[str, Any], binary: bytearray | None) -> bytes:
    """Assemble a GLB from its JSON and BIN chunk (4-byte padding: spaces / zeros)."""
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    chunks = struct.pack("<II", len(js), _GLB_JSON) + js
    if binary is not None:
        data = bytes(binary) + b"\0" * (-len(binary) % 4)
        chunks += struct.pack("<II", len(data), _GLB_BIN) + data
    return _GLB_MAGIC + struct.pack("<II", 2, 12 + len(chunks)) + chunks


def _gltf_position_accessors(doc: dict[str, Any]) -> list[int]:
    """Indices of accessors holding positions (primitive POSITION and morph-target POSITION)."""
    found: set[int] = set()
    for mesh in doc.get("meshes", []):
        for prim in mesh.get("primitives", []):
            for attrs in [prim.get("attributes", {}), *prim.get("targets", [])]:
                if "POSITION" in attrs:
                    found.add(int(attrs["POSITION"]))
    return sorted(found)


def _gltf_can_scale_buffers(doc: dict[str, Any]) -> bool:
    """True when every position accessor is plain float VEC3 data in a buffer view."""
    if "KHR_draco_mesh_compression" in doc.get("extensionsUsed", []):
        return False
    accessors = doc.get("accessors", [])
    for i in _gltf_position_accessors(doc):
        acc = accessors[i]
        if (acc.get("componentType") != _GLTF_FLOAT or acc.get("type") != "VEC3"
                or "sparse" in acc or "bufferView" not in acc):
            return False
    return True


def _scale_gltf_doc(doc: dict[str, Any], buffers: list[bytearray], scale: float) -> None:
    """Scale positions in ``buffers`` (in place), accessor min/max and node translations."""
    accessors, views = doc["accessors"], doc.get("bufferViews", [])
    done: set[tuple[int, int, int, int]] = set()
    for i in _gltf_position_accessors(doc):
        acc = accessors[i]
        view = views[acc["bufferView"]]
        offset = int(view.get("byteOffset", 0)) + int(acc.get("byteOffset", 0))
        stride = int(view.get("byteStride", 12))
        key = (int(view["buffer"]), offset, stride, int(acc["count"]))
        if key not in done:  # two accessors on the same bytes: scale once
            done.add(key)
            arr = np.ndarray((key[3], 3), dtype="<f4", buffer=buffers[key[0]], offset=offset,
                             strides=(stride, 4))
            arr[...] = arr.astype(np.float64) * scale
        for bound in ("min", "max"):
            if bound in acc:
                acc[bound] = [float(np.float32(v * scale)) for v in acc[bound]]
    for node in doc.get("nodes", []):
        if "translation" in node:
            node["translation"] = [v * scale for v in node["translation"]]
        if "matrix" in node:  # column-major 4x4: translation is elements 12..14
            node["matrix"] = [v * scale if k in (12, 13, 14) else v
                              for k, v in enumerate(node["matrix"])]


def _write_scaled_gltf(src: Path, dst: Path, scale: float) -> list[Path]:
    """glTF/GLB: scale position data in the buffers; other buffer bytes and images unchanged."""
    try:
        if src.suffix.lower() == ".glb":
            doc, binary = _read_glb(src)
            buffers = _gltf_buffers(doc, src, binary)
        else:
            doc, binary = _parse_json(src.read_bytes(), src), None
            buffers = _gltf_buffers(doc, src, None)
        if not _gltf_can_scale_buffers(doc):
            raise InputError("glTF with compressed, quantised or sparse positions is not "
                             "supported: export the mesh as PLY", src)
        _scale_gltf_doc(doc, buffers, scale)
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"invalid glTF structure: {type(exc).__name__}: {exc}", src) from exc
    return _write_gltf_outputs(src, dst, doc, buffers, src.suffix.lower() == ".glb", binary)


def _gltf_buffers(doc: dict[str, Any], src: Path, binary: bytearray | None) -> list[bytearray]:
    """Contents of every glTF buffer (GLB BIN chunk, data: URI or external file)."""
    out = []
    for i, buf in enumerate(doc.get("buffers", [])):
        uri = buf.get("uri")
        if uri is None:
            if i != 0 or binary is None:
                raise InputError(f"glTF buffer {i} has no data", src)
            out.append(binary)
        elif uri.startswith("data:"):
            out.append(bytearray(base64.b64decode(uri.split(",", 1)[1])))
        else:
            file = src.parent / _unquote(uri)
            if not file.is_file():
                raise InputError(f"glTF buffer file {uri!r} not found", src)
            out.append(bytearray(file.read_bytes()))
    return out


def _unquote(uri: str) -> str:
    from urllib.parse import unquote

    return unquote(uri)


def _write_gltf_outputs(src: Path, dst: Path, doc: dict[str, Any], buffers: list[bytearray],
                        glb: bool, binary: bytearray | None) -> list[Path]:
    """Write the scaled glTF/GLB, its external buffers (scaled) and its images (copied)."""
    written = [dst]
    for i, buf in enumerate(doc.get("buffers", [])):
        uri = buf.get("uri")
        if uri is None:
            continue
        if uri.startswith("data:"):
            head = uri.split(",", 1)[0]
            buf["uri"] = head + "," + base64.b64encode(bytes(buffers[i])).decode("ascii")
        else:
            target = dst.parent / _unquote(uri)
            if not target.resolve().is_relative_to(dst.parent.resolve()):
                raise InputError(f"glTF buffer {uri!r} points outside the mesh folder", src)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(bytes(buffers[i]))
            written.append(target)
    with _AtomicOutput(dst) as fo:
        if glb:
            first = doc.get("buffers", [{}])[0] if doc.get("buffers") else {}
            fo.write(_glb_bytes(doc, buffers[0] if buffers and "uri" not in first else binary))
        else:
            fo.write(json.dumps(doc, indent=2).encode("utf-8"))
    for image in doc.get("images", []):
        uri = image.get("uri")
        if uri and not uri.startswith("data:"):
            _copy_side_file(_unquote(uri), src.parent, dst.parent, written)
    return written
