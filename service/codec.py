"""Arrays on the wire: ``.npy``, ``.npz`` and ``multipart/form-data`` bodies.

The decoders never unpickle and never trust a header: the ``.npy`` header is
parsed first and the declared shape and dtype must account for exactly the
bytes that follow (a truncated or padded body is an error, and a header that
declares a huge array allocates nothing). ``.npz`` members are size-checked
from the zip directory before they are inflated. Every problem raises
:class:`~bubsub.service.errors.APIError` with a 4xx status and a message that
says what is wrong.
"""

from __future__ import annotations

import io
import zipfile
from dataclasses import dataclass

import numpy as np
from numpy.lib import format as npformat

from bubsub.service.errors import APIError

__all__ = [
    "NPY",
    "NPZ",
    "JSON",
    "MULTIPART",
    "Part",
    "content_type",
    "decode_npy",
    "decode_npz",
    "decode_arrays",
    "parse_multipart",
    "encode_npy",
    "encode_npz",
]

NPY = "application/x-npy"
NPZ = "application/x-npz"
JSON = "application/json"
MULTIPART = "multipart/form-data"

#: accepted spellings of the array media types
_ALIASES = {
    "application/npy": NPY,
    "application/x-numpy": NPY,
    "application/npz": NPZ,
    "application/zip": NPZ,
}

_NUMERIC_KINDS = "biuf"


def content_type(header):
    """Split a ``Content-Type`` header into the lower-case media type and its parameters.

    Parameters
    ----------
    header : str or None

    Returns
    -------
    mime : str
        ``""`` when the header is missing.
    params : dict
    """
    if not header:
        return "", {}
    mime, *rest = header.split(";")
    params = {}
    for item in rest:
        key, sep, value = item.strip().partition("=")
        if sep:
            value = value.strip()
            if len(value) >= 2 and value[0] == value[-1] == '"':
                value = value[1:-1]
            params[key.strip().lower()] = value
    mime = mime.strip().lower()
    return _ALIASES.get(mime, mime), params


def decode_npy(body, name="body"):
    """Array from ``.npy`` bytes, without pickles and without trusting the header.

    Parameters
    ----------
    body : bytes
    name : str
        What the array is, for error messages.

    Returns
    -------
    numpy.ndarray
        A read-only view of ``body`` (copy it to modify).

    Raises
    ------
    APIError
        400 for a body that is not a complete ``.npy`` file; 422 for an
        object, structured or non-numeric dtype.
    """
    buf = memoryview(body)
    if len(buf) < 10 or bytes(buf[:6]) != b"\x93NUMPY":
        raise APIError(400, f"{name}: not a .npy file (missing the \\x93NUMPY magic); "
                            f"send numpy.save() output as {NPY}", "bad_npy")
    f = io.BytesIO(body)
    try:
        version = npformat.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = npformat.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, fortran, dtype = npformat.read_array_header_2_0(f)
        else:
            shape, fortran, dtype = npformat._read_array_header(f, version)  # noqa: SLF001
    except Exception as exc:  # numpy raises ValueError/EOFError/SyntaxError on bad headers
        raise APIError(400, f"{name}: invalid .npy header ({exc})", "bad_npy") from None
    if not isinstance(shape, tuple) or not all(type(s) is int and s >= 0 for s in shape):
        # numpy's header parser takes any tuple literal: (-1, 3), (True, 3), (1.5,) ...
        raise APIError(400, f"{name}: invalid .npy header: shape {shape!r} must be non-negative integers",
                       "bad_npy")
    if dtype.hasobject or dtype.fields is not None or dtype.kind not in _NUMERIC_KINDS:
        raise APIError(422, f"{name}: dtype {dtype.str!r} is not allowed; send a numeric array", "bad_dtype")
    count = 1
    for s in shape:
        count *= int(s)
    offset = f.tell()
    expected = count * dtype.itemsize
    have = len(buf) - offset
    if have != expected:
        what = "truncated" if have < expected else "has trailing bytes"
        raise APIError(400, f"{name}: .npy body {what}: shape {tuple(shape)} of {dtype.str} needs "
                            f"{expected} data bytes, got {have}", "bad_npy")
    arr = np.frombuffer(body, dtype=dtype, count=count, offset=offset)
    return arr.reshape(shape, order="F" if fortran else "C")


def decode_npz(body, max_bytes, name="body", max_members=16):
    """Arrays from ``.npz`` bytes (``numpy.savez`` or ``savez_compressed``).

    Parameters
    ----------
    body : bytes
    max_bytes : int
        Largest total inflated size; a zip that would inflate beyond it is refused.
    name : str
    max_members : int
        Most members; more are refused before any is read (each costs a
        header parse, and thousands of them would keep a decoder busy).

    Returns
    -------
    dict of str to numpy.ndarray
        Keyed by member name without the ``.npy`` suffix.
    """
    declared = _zip_entries(body)
    if declared is not None and declared > max_members:
        raise APIError(422, f"{name}: .npz has {declared} members, over the limit of {max_members}", "bad_npz")
    try:
        zf = zipfile.ZipFile(io.BytesIO(body))
    except (zipfile.BadZipFile, ValueError, OSError) as exc:
        raise APIError(400, f"{name}: not a valid .npz/zip file ({exc})", "bad_npz") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > max_members:
            raise APIError(422, f"{name}: .npz has {len(infos)} members, over the limit of {max_members}",
                           "bad_npz")
        total = sum(i.file_size for i in infos)
        if total > max_bytes:
            raise APIError(413, f"{name}: .npz inflates to {total} bytes, over the {max_bytes}-byte limit",
                           "too_large")
        out = {}
        for info in infos:
            key = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            try:
                raw = zf.read(info)
            except Exception as exc:  # CRC errors, truncated members, bad compression
                raise APIError(400, f"{name}: cannot read .npz member {info.filename!r} ({exc})",
                               "bad_npz") from None
            out[key] = decode_npy(raw, f"{name}[{key}]")
    return out


def _zip_entries(body):
    """Entry count from a zip's end-of-central-directory record (None if not found).

    Read before :class:`zipfile.ZipFile` parses the whole central directory,
    which for a zip of many tiny members is most of the cost.
    """
    tail = bytes(memoryview(body)[-(22 + 65535):])
    at = tail.rfind(b"PK\x05\x06")
    if at < 0 or at + 22 > len(tail):
        return None
    return int.from_bytes(tail[at + 10:at + 12], "little")  # 0xFFFF for zip64: over any limit here


@dataclass(frozen=True)
class Part:
    """One part of a ``multipart/form-data`` body."""

    name: str
    content_type: str
    data: bytes
    filename: str | None = None


def parse_multipart(body, boundary, max_parts=16):
    """Split a fully read ``multipart/form-data`` body into its parts.

    Parameters
    ----------
    body : bytes
    boundary : str
        The ``boundary`` parameter of the ``Content-Type`` header.
    max_parts : int
        Most parts; more are refused (400).

    Returns
    -------
    list of Part

    Raises
    ------
    APIError
        400 if the body is truncated, a part lacks a name, or the structure
        is broken.
    """
    if not boundary or len(boundary) > 200:
        raise APIError(400, "multipart body without a valid boundary parameter", "bad_multipart")
    delim = b"--" + boundary.encode("latin-1")
    body = bytes(body)
    start = body.find(delim)
    if start < 0:
        raise APIError(400, "multipart body does not contain its boundary", "bad_multipart")
    parts = []
    pos = start + len(delim)
    while True:
        if body[pos:pos + 2] == b"--":
            break  # closing delimiter
        if body[pos:pos + 2] != b"\r\n":
            raise APIError(400, "multipart boundary is not followed by CRLF", "bad_multipart")
        pos += 2
        nxt = body.find(b"\r\n" + delim, pos)
        if nxt < 0:
            raise APIError(400, "multipart body is truncated (closing boundary not found)", "bad_multipart")
        if len(parts) >= max_parts:
            raise APIError(400, f"multipart body has more than {max_parts} parts", "bad_multipart")
        parts.append(_parse_part(body[pos:nxt]))
        pos = nxt + 2 + len(delim)
    return parts


def _parse_part(chunk):
    if chunk.startswith(b"\r\n"):  # a part without any header line
        head, sep, data = b"", True, chunk[2:]
    else:
        head, sep, data = chunk.partition(b"\r\n\r\n")
    if not sep:
        raise APIError(400, "multipart part without a header block", "bad_multipart")
    headers = {}
    for line in head.decode("latin-1").split("\r\n"):
        key, colon, value = line.partition(":")
        if colon:
            headers[key.strip().lower()] = value.strip()
    disp, params = content_type(headers.get("content-disposition", ""))
    if disp != "form-data" or not params.get("name"):
        raise APIError(400, "multipart part without Content-Disposition: form-data; name=...", "bad_multipart")
    ctype, _ = content_type(headers.get("content-type", "application/octet-stream"))
    return Part(params["name"], ctype, data, params.get("filename"))


def decode_arrays(body, ctype, params, max_bytes, allowed):
    """Named arrays from an ``.npy``, ``.npz`` or multipart body.

    Parameters
    ----------
    body : bytes
    ctype : str
        Media type (from :func:`content_type`).
    params : dict
        Content-type parameters (``boundary`` for multipart).
    max_bytes : int
        Inflation limit for ``.npz``.
    allowed : sequence of str
        Array names the endpoint takes; a single ``.npy`` body is the first.

    Returns
    -------
    dict of str to numpy.ndarray
    """
    if ctype == NPY:
        return {allowed[0]: decode_npy(body, allowed[0])}
    if ctype == NPZ:
        arrays = decode_npz(body, max_bytes)
    elif ctype == MULTIPART:
        arrays = {}
        for part in parse_multipart(body, params.get("boundary")):
            if part.name in arrays:
                raise APIError(400, f"multipart part {part.name!r} given twice", "bad_multipart")
            arrays[part.name] = decode_npy(part.data, part.name)
    else:
        raise APIError(415, f"unsupported Content-Type {ctype or '(none)'!r}; send {NPY}, {NPZ} or "
                            f"{MULTIPART} with .npy parts", "unsupported_media_type")
    unknown = sorted(set(arrays) - set(allowed))
    if unknown:
        raise APIError(422, f"unexpected arrays {unknown}; this endpoint takes {list(allowed)}", "unknown_array")
    return arrays


def encode_npy(array):
    """``.npy`` bytes of ``array``."""
    buf = io.BytesIO()
    np.save(buf, np.asarray(array), allow_pickle=False)
    return buf.getvalue()


def encode_npz(arrays):
    """Uncompressed ``.npz`` bytes of a dict of arrays."""
    buf = io.BytesIO()
    np.savez(buf, **{k: np.asarray(v) for k, v in arrays.items()})
    return buf.getvalue()
