"""The input checks every file reader of the project shares (scene, manifest, target, DET, CALIB, --init).

One owner for the questions every reader has to answer before it looks at a field:
- Can the file be read at all: a folder, unreadable, larger than `MAX_JSON_BYTES`, UTF-16/32 or another
  non-UTF-8 encoding, image bytes where JSON was expected; each is one line naming the file.
- Is the JSON shallow enough: nesting deeper than `MAX_JSON_DEPTH` is refused before the parser recurses
  (Python's parser would raise RecursionError), so the recursive code that walks the result is safe too.
- Is a number a number the code can compute with: finite, not an integer too large for a float
  (`1` followed by 400 digits), inside float32's range where the tracer computes in float32
  (`FLOAT32_MAX`; non-zero magnitudes below `FLOAT32_TINY` flush to zero there), positive where physical.
- Is an allocation affordable: `check_memory` compares an estimate with the memory available now.

Limits, stated once (docs/file_formats.md prints them):
    MAX_JSON_BYTES    64 MiB per JSON file
    MAX_JSON_DEPTH    64 nested lists/objects
    MAX_EXTENDS       32 files in a scene's `extends` chain
    MAX_SET_SEGMENTS  64 dot-separated keys in one `--set` path

Each function takes the exception class to raise (`SceneError`, `TargetError`, `CalibFileError`, ...), so
each package keeps its own error type; messages are `<file>: <field>: <problem>` on one line.
"""
from __future__ import annotations

import copy
import json
import math
import os
import re

from camio.errors import SceneError, UsageError, one_line, os_reason

MAX_JSON_BYTES = 64 << 20
MAX_JSON_DEPTH = 64
MAX_EXTENDS = 32
MAX_SET_SEGMENTS = 64
FLOAT32_MAX = 3.4028234663852886e38
FLOAT32_TINY = 1.1754943508222875e-38
FLOAT64_MAX = 1.7976931348623157e308

_STRING = re.compile(r'"(?:[^"\\]|\\.)*"', re.S)
_BRACKET = re.compile(r"[\[\]{}]")


def describe(value) -> str:
    """A short, one-line rendering of a received value for messages (huge integers by their digit count)."""
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) > 10**20:
        return f"a {len(str(abs(value)))}-digit integer"
    text = repr(value)
    text = one_line(text)
    return text if len(text) <= 80 else text[:77] + "..."


def is_number(x) -> bool:
    """int or float, not bool (whatever its size)."""
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def is_finite_number(x) -> bool:
    """A number that converts to a finite float64 (integers beyond 1.8e308 do not)."""
    if not is_number(x):
        return False
    if isinstance(x, int):
        return abs(x) <= FLOAT64_MAX
    return math.isfinite(x)


def number(where: str, value, error=ValueError, *, positive=False, nonnegative=False, integer=False,
           float32=False, low=None, high=None):
    """Check one number and return it as float (or int when `integer`).

    Args:
        where: the message prefix naming the file and field, e.g. "scene.json: image.width".
        positive / nonnegative: physical quantities (a radius, a pixel pitch, a blur width).
        integer: must be integral (a count, a size in pixels).
        float32: must be representable in float32 without overflow or flushing to zero.
        low / high: inclusive bounds (the stated limits).
    Raises:
        error(one line) when the value fails.
    """

    def fail(expected):
        raise error(f"{where}: expected {expected}, got {describe(value)}")

    kind = "an integer" if integer else "a number"
    if not is_number(value):
        fail(kind)
    if not is_finite_number(value):
        fail(f"a finite {kind[2:] if integer else 'number'}")
    if integer and float(value) != int(value):
        fail("an integer")
    f = float(value)
    if float32:
        if abs(f) > FLOAT32_MAX:
            fail(f"a magnitude below {FLOAT32_MAX:.3g} (the tracer computes in float32)")
        if 0 < abs(f) < FLOAT32_TINY:
            fail(f"0 or a magnitude above {FLOAT32_TINY:.3g} (smaller ones flush to zero in float32)")
    if positive and not f > 0:
        fail(f"a positive {kind[2:] if integer else 'number'}")
    if nonnegative and not f >= 0:
        fail(f"a non-negative {kind[2:] if integer else 'number'}")
    if low is not None and f < low:
        fail(f"{kind} >= {low:g}")
    if high is not None and f > high:
        fail(f"{kind} <= {high:g}")
    return int(value) if integer else f


def check_tree(value, where: str, error=ValueError, *, float32=False, max_depth: int = MAX_JSON_DEPTH) -> None:
    """Walk parsed JSON without recursion: depth, and every number finite (float32-representable when
    `float32`). `where` names the file; messages give the path of the field (`objects[2].shape.radius`)."""
    stack = [(value, "", 0)]
    while stack:
        v, path, depth = stack.pop()
        if isinstance(v, (dict, list)):
            if depth >= max_depth:
                raise error(f"{where}: {path or 'top level'}: nested deeper than {max_depth} levels")
            items = v.items() if isinstance(v, dict) else enumerate(v)
            for k, x in items:
                sub = (f"{path}.{k}" if path else str(k)) if isinstance(v, dict) else f"{path}[{k}]"
                stack.append((x, sub, depth + 1))
        elif is_number(v):
            prefix = f"{where}: {path}" if where else path
            if not is_finite_number(v):
                raise error(f"{prefix}: expected a finite number, got {describe(v)}")
            if float32:
                number(prefix, v, error, float32=True)


# Bytes that text files do not hold: C0 controls other than tab, newline, form feed and carriage return.
_CONTROL = bytes(b for b in range(32) if b not in b"\t\n\f\r") + b"\x7f"


def _wide_text(data: bytes) -> bool:
    """Whether `data` holding NUL bytes is text in UTF-16 or UTF-32: a byte-order mark, or decoding to printable,
    mostly ASCII text."""
    if data.startswith((b"\xff\xfe", b"\xfe\xff", b"\x00\x00\xfe\xff")):
        return True
    head = data[:4096]
    for codec in ("utf-32-le", "utf-32-be", "utf-16-le", "utf-16-be"):
        width = 4 if "32" in codec else 2
        try:
            text = head[:len(head) - len(head) % width].decode(codec)
        except UnicodeDecodeError:
            continue
        # JSON and YAML are ASCII in their syntax: wide text of them decodes to mostly ASCII characters.
        if text and sum(c.isprintable() or c in "\t\n\r" for c in text) >= 0.95 * len(text) \
                and sum(c < "\x80" for c in text) >= 0.5 * len(text):
            return True
    return False


def _binary(data: bytes) -> bool:
    """Whether `data` is binary data rather than text in any encoding: NUL bytes not explained by UTF-16/32,
    or more than 1 % control bytes in its first 4 KiB (text in a legacy 8-bit encoding has none)."""
    head = data[:4096]
    if b"\x00" in head:
        return not _wide_text(data)
    return len(head) > 0 and sum(head.count(c) for c in _CONTROL) > 0.01 * len(head)


def _decode(path: str, data: bytes, error, what: str) -> str:
    if data.startswith(b"\x89PNG") or data.startswith(b"\xff\xd8\xff") or data.startswith(b"II*\x00") \
            or data.startswith(b"MM\x00*") or data.startswith(b"v/1\x01"):
        raise error(f"{path}: is an image, not a JSON {what}")
    if _binary(data):
        raise error(f"{path}: binary data, not a text file; a {what} is JSON text (UTF-8)")
    if data.startswith((b"\xff\xfe", b"\xfe\xff")) or b"\x00" in data[:4096]:
        raise error(f"{path}: not UTF-8 text (looks like UTF-16 or UTF-32); save the {what} as UTF-8")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise error(f"{path}: not UTF-8 text (byte 0x{data[e.start]:02x} at offset {e.start}); "
                    f"save the {what} as UTF-8") from None
    return text[1:] if text.startswith("\ufeff") else text


def json_depth(text: str) -> int:
    """The deepest nesting of lists/objects in JSON text (brackets inside strings do not count)."""
    depth = deepest = 0
    for m in _BRACKET.finditer(_STRING.sub('""', text)):
        depth += 1 if m.group() in "[{" else -1
        deepest = max(deepest, depth)
    return deepest


def read_json(path: str, error=ValueError, what: str = "file", max_depth: int = MAX_JSON_DEPTH):
    """Read and parse a JSON file; every problem is `error("<path>: <problem>")` on one line.

    NaN, Infinity and huge integers parse (the field checks name them); the nesting depth is checked on the
    text before parsing, so no reader ever meets a RecursionError.
    """
    try:
        if os.path.isdir(path):
            raise error(f"{path}: is a folder, not a {what}")
        size = os.path.getsize(path)
        if size > MAX_JSON_BYTES:
            raise error(f"{path}: {size} bytes; a {what} is at most {MAX_JSON_BYTES >> 20} MiB")
        with open(path, "rb") as f:
            data = f.read(MAX_JSON_BYTES + 1)
    except OSError as e:
        raise error(f"{path}: cannot read {what} ({os_reason(e)})") from None
    return parse_json(path, _decode(path, data, error, what), error, max_depth)


def parse_json(path: str, text: str, error=ValueError, max_depth: int = MAX_JSON_DEPTH):
    """Parse JSON text read from `path` (see `read_json`)."""
    depth = json_depth(text)
    if depth > max_depth:
        raise error(f"{path}: JSON nested {depth} levels deep; at most {max_depth} are allowed")
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise error(f"{path}:{e.lineno}:{e.colno}: not valid JSON ({e.msg})") from None
    except (ValueError, RecursionError) as e:  # e.g. an integer of more than 4300 digits
        raise error(f"{path}: not valid JSON ({' '.join(str(e).split())})") from None


def available_memory_bytes() -> int:
    """Memory the process may still allocate: MemAvailable on Linux, else physical memory; 2^62 if unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 1 << 62


def check_memory(where: str, n_bytes: float, error=ValueError, what: str = "this") -> None:
    """Refuse before allocating when an estimate exceeds the memory available now."""
    avail = available_memory_bytes()
    if n_bytes > avail:
        raise error(f"{where}: {what} needs about {_gib(n_bytes)} of memory; {_gib(avail)} is available")


def _gib(n: float) -> str:
    return f"{n / 2**30:.3g} GiB" if n < 2**70 else f"{n:.3g} bytes"


def read_scene_json(path: str, _seen: tuple[str, ...] = ()) -> dict:
    """Read a scene file and resolve its `extends` chain into one plain dict (not yet validated)."""
    real = os.path.realpath(path)
    if real in _seen:
        raise SceneError(f"{path}: extends: circular reference")
    if len(_seen) >= MAX_EXTENDS:
        raise SceneError(f"{path}: extends: a chain of more than {MAX_EXTENDS} files (from {_seen[0]})")
    cfg = read_json(path, SceneError, "scene file")
    if not isinstance(cfg, dict):
        raise SceneError(f"{path}: expected a JSON object at the top level, got {type(cfg).__name__}")
    base = cfg.pop("extends", None)
    if base is None:
        return cfg
    if not isinstance(base, str):
        raise SceneError(f"{path}: extends: expected a file name, got {base!r}")
    base_path = os.path.join(os.path.dirname(path), base)
    return merge(read_scene_json(base_path, _seen + (real,)), cfg)


def merge(base: dict, over: dict) -> dict:
    """`over` merged onto `base`: objects key by key (recursively), anything else replaced."""
    out = copy.deepcopy(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def parse_device(name: str):
    """A --device value as a torch.device that can render here (cpu, cuda, cuda:N); UsageError otherwise."""
    import torch

    try:
        device = torch.device(name)
    except RuntimeError:
        raise UsageError(f"--device: unknown device {name!r} (expected cpu or cuda)") from None
    if device.type not in ("cpu", "cuda"):
        raise UsageError(f"--device: {name!r} cannot render (expected cpu or cuda)")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise UsageError("--device cuda: CUDA is not available on this machine")
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise UsageError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA device(s), "
                         f"numbered from 0")
    return device
