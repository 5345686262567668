"""A structure check of MATLAB v5 files before :func:`scipy.io.loadmat` reads them.

scipy's reader trusts the data types in a v5 file's element tags: a damaged type byte crashed the
whole process (segmentation fault) instead of raising. :func:`check_mat5` walks the variables as
scipy does and refuses a damaged element with a :class:`~facenormals.models.ModelFileError` naming
the file and the byte offset.
"""

from __future__ import annotations

import math
import struct
import zlib
from pathlib import Path
from typing import Any, Callable, Sequence

from facenormals.models.morphable import ModelFileError

__all__ = ["check_mat5"]


# MATLAB v5 data element types (MathWorks, "MAT-File Format"): 8, 10 and 11 are reserved.
_MI_INT8, _MI_INT32, _MI_UINT32, _MI_MATRIX, _MI_COMPRESSED, _MI_UTF8 = 1, 5, 6, 14, 15, 16
_MI_TYPES = frozenset({1, 2, 3, 4, 5, 6, 7, 9, 12, 13, 14, 15, 16, 17, 18})
#: The types scipy reads as numbers or characters: it looks any other type up in a C table of dtypes,
#: without a check, and a damaged type byte crashed the process (segmentation fault).
_MI_NUMERIC = _MI_TYPES - {_MI_MATRIX, _MI_COMPRESSED}
#: Array classes: 1 cell, 2 struct, 3 object, 4 char, 5 sparse, 6 to 15 numeric, 16 function, 17 opaque.
_MX_NUMERIC = range(6, 16)
_MAT_MAX_NESTING = 100  # cells and structs within each other (scipy reads them recursively in C)
_MAT_CHUNK = 1 << 16


class _MatDamage(Exception):
    """A damaged element of a MATLAB v5 file: ``where`` locates it, ``what`` says what is wrong."""

    def __init__(self, what: str, where: str) -> None:
        super().__init__(f"{what} (at {where})")


class _MatTruncated(Exception):
    """The data ends inside an element."""


class _MatFile:
    """Sequential reads of an open MATLAB file; positions are file offsets."""

    def __init__(self, handle: Any, size: int) -> None:
        self.handle, self.size = handle, size

    @property
    def pos(self) -> int:
        return self.handle.tell()

    def where(self, pos: int) -> str:
        return f"byte {pos}"

    def read(self, count: int) -> bytes:
        data = self.handle.read(count)
        if len(data) < count:
            raise _MatTruncated
        return data

    def skip(self, count: int) -> None:
        if self.pos + count > self.size:
            raise _MatTruncated
        self.handle.seek(count, 1)


class _MatCompressed:
    """Sequential reads of the decompressed content of a miCOMPRESSED element, decompressed in chunks
    (never held whole); positions are offsets in the decompressed data."""

    def __init__(self, source: _MatFile, count: int, start: int) -> None:
        self.source, self.left, self.start = source, count, start
        self.decompressor = zlib.decompressobj()
        self.buffer, self.offset, self.pos = b"", 0, 0

    def where(self, pos: int) -> str:
        return f"byte {pos} of the decompressed variable at byte {self.start}"

    def _more(self, limit: int) -> bytes:
        """Up to ``limit`` more decompressed bytes; ``b""`` at the end of the compressed data."""
        while True:
            if self.decompressor.unconsumed_tail:
                data = self.decompressor.unconsumed_tail
            elif self.decompressor.eof or self.left == 0:
                return b""
            else:
                data = self.source.read(min(self.left, _MAT_CHUNK))
                self.left -= len(data)
            try:
                out = self.decompressor.decompress(data, limit)
            except zlib.error as error:
                raise _MatDamage(f"damaged compressed data ({error})", f"the variable at byte {self.start}") from None
            if out:
                return out

    def read(self, count: int) -> bytes:
        while len(self.buffer) - self.offset < count:
            more = self._more(max(count, _MAT_CHUNK))
            if not more:
                raise _MatTruncated
            self.buffer, self.offset = self.buffer[self.offset:] + more, 0
        data = self.buffer[self.offset:self.offset + count]
        self.offset += count
        self.pos += count
        return data

    def skip(self, count: int) -> None:
        left = count - min(count, len(self.buffer) - self.offset)
        self.offset += count - left
        while left:
            more = self._more(min(left, 1 << 20))
            if not more:
                raise _MatTruncated
            left -= len(more)
        self.pos += count


class _Mat5Checker:
    """Walks a MATLAB v5 array as scipy's reader does (array flags, dimensions, name, then the parts its
    class has), checking each element's type, and that each fits inside its array, before scipy reads it."""

    def __init__(self, order: str) -> None:
        self.order = order

    def _tag(self, stream: Any, end: int, role: str) -> tuple[int, int, bytes | None]:
        """Type, byte count and, for a small data element, its data, of the element ``role`` at ``stream.pos``."""
        pos = stream.pos
        if pos + 8 > end:
            raise _MatDamage(f"the array ends before its {role}", stream.where(pos))
        raw = stream.read(8)
        first, count = struct.unpack(self.order + "II", raw)
        small = None
        if first >> 16:  # small data element: type and size in the first word, the data in the second
            first, count = first & 0xFFFF, first >> 16
            if count > 4:
                raise _MatDamage(f"{role}: a small data element of {count} bytes (at most 4)", stream.where(pos))
            small = raw[4:4 + count]
        if first not in _MI_TYPES:
            raise _MatDamage(f"{role}: unknown data type {first}", stream.where(pos))
        if small is None and pos + 8 + count > end:
            raise _MatDamage(f"{role}: {count} bytes run past the end of its array (at byte {end})", stream.where(pos))
        return first, count, small

    def _data(self, stream: Any, end: int, role: str, types: frozenset[int] | tuple[int, ...],
              expected: str, read: bool = True) -> bytes:
        pos = stream.pos
        mdtype, count, small = self._tag(stream, end, role)
        if mdtype not in types:
            raise _MatDamage(f"{role} of data type {mdtype}, expected {expected}", stream.where(pos))
        if small is not None:
            return small
        data = stream.read(count) if read else b""
        stream.skip(-count % 8 + (0 if read else count))  # the rest, and the padding to 8 bytes
        return data

    def _int32s(self, stream: Any, end: int, role: str) -> tuple[int, ...]:
        pos = stream.pos
        data = self._data(stream, end, role, (_MI_INT32, _MI_UINT32), "32-bit integers")
        if len(data) % 4 or len(data) > 128:
            raise _MatDamage(f"{role} of {len(data)} bytes, expected 1 to 32 integers", stream.where(pos))
        return struct.unpack(f"{self.order}{len(data) // 4}i", data)

    def _text(self, stream: Any, end: int, role: str) -> bytes:
        return self._data(stream, end, role, (_MI_INT8, _MI_UTF8), "text (miINT8)")

    def _numbers(self, stream: Any, end: int, role: str) -> None:
        self._data(stream, end, role, _MI_NUMERIC, "numbers or characters", read=False)

    def matrix_element(self, stream: Any, end: int, role: str, depth: int,
                       wanted: Callable[[bytes], bool] | None = None) -> None:
        """The miMATRIX element ``role`` at ``stream.pos``, which must end by ``end``; see :meth:`matrix`."""
        pos = stream.pos
        if pos + 8 > end:
            raise _MatDamage(f"the array ends before its {role}", stream.where(pos))
        mdtype, count = struct.unpack(self.order + "II", stream.read(8))
        if mdtype != _MI_MATRIX:
            raise _MatDamage(f"{role} of data type {mdtype}, expected an array (miMATRIX, 14)", stream.where(pos))
        if count % 8 or pos + 8 + count > end:
            raise _MatDamage(f"{role}: an array of {count} bytes, not a multiple of 8 or past the end of its parent "
                             f"(at byte {end})", stream.where(pos))
        if count:  # else an empty array
            self.matrix(stream, pos + 8 + count, depth + 1, wanted)

    def matrix(self, stream: Any, end: int, depth: int, wanted: Callable[[bytes], bool] | None = None) -> None:
        """The content of a miMATRIX element, from ``stream.pos`` to ``end``; only its header (flags,
        dimensions, name: what scipy reads of a variable it skips) unless ``wanted`` is ``None`` or
        says yes to its name."""
        if depth > _MAT_MAX_NESTING:
            raise _MatDamage(f"arrays nested more than {_MAT_MAX_NESTING} deep", stream.where(stream.pos))
        pos = stream.pos
        flags = self._data(stream, end, "array flags", (_MI_UINT32,), "two 32-bit unsigned integers")
        if len(flags) != 8:
            raise _MatDamage(f"array flags of {len(flags)} bytes, expected 8", stream.where(pos))
        (flags_class,) = struct.unpack(self.order + "I", flags[:4])
        mclass, complex_parts = flags_class & 0xFF, flags_class >> 11 & 1
        if mclass == 17:  # opaque (a MATLAB object): no dimensions
            name = self._text(stream, end, "name")
            if wanted is not None and not wanted(name):
                return
            for role in ("type system", "class name"):
                self._text(stream, end, role)
            self.matrix_element(stream, end, "object data", depth)
        else:
            dims_pos = stream.pos
            dims = self._int32s(stream, end, "dimensions")
            if any(size < 0 for size in dims):
                raise _MatDamage(f"negative dimensions {list(dims)}", stream.where(dims_pos))
            name = self._text(stream, end, "name")
            if wanted is not None and not wanted(name):
                return
            if mclass in _MX_NUMERIC:
                for role in ("real part", "imaginary part")[:1 + complex_parts]:
                    self._numbers(stream, end, role)
            elif mclass == 5:  # sparse
                for role in ("row indices", "column indices", "real part", "imaginary part")[:3 + complex_parts]:
                    self._numbers(stream, end, role)
            elif mclass == 4:
                self._numbers(stream, end, "characters")
            elif mclass == 1:
                for _ in range(math.prod(dims)):
                    self.matrix_element(stream, end, "cell", depth)
            elif mclass in (2, 3):  # struct, object (a struct with a class name)
                if mclass == 3:
                    self._text(stream, end, "class name")
                length_pos = stream.pos
                length = self._int32s(stream, end, "field name length")
                if len(length) != 1 or length[0] <= 0:
                    raise _MatDamage(f"field name length {list(length)}, expected one positive integer",
                                     stream.where(length_pos))
                fields = len(self._text(stream, end, "field names")) // length[0]
                for _ in range(math.prod(dims) * fields):
                    self.matrix_element(stream, end, "field", depth)
            elif mclass == 16:  # function handle
                self.matrix_element(stream, end, "function", depth)
            else:
                raise _MatDamage(f"unknown array class {mclass}", stream.where(pos))
        if stream.pos != end:
            raise _MatDamage(f"{end - stream.pos} bytes after the parts of its array (class {mclass}), which end "
                             f"at byte {end}", stream.where(stream.pos))


def check_mat5(path: Path, names: Sequence[str] | None = None) -> None:
    """Raise ``ModelFileError`` naming ``path`` and a byte offset if a MATLAB v5 file's element structure
    is damaged; other files (v4, v7.3 and what is no MATLAB file) are left to their readers.

    scipy's reader trusts the data types in a v5 file's element tags: a damaged type byte crashed the
    whole process (segmentation fault) instead of raising. This walks the variables as scipy does
    (compressed ones decompressed in chunks, never held whole) and checks each element's type and size
    against the array holding it, before scipy reads anything; numbers are skipped, not read. It checks
    what scipy reads: the header (flags, dimensions, name) of every variable and, of the variables
    ``names`` (default all), the whole. A file that ends inside a variable passes (scipy reads it only
    if asked for it, and then says so); damage there is scipy's to report.
    """
    def wanted(name: bytes) -> bool:  # as scipy names a variable
        return (name.decode("latin1") or "__function_workspace__") in names

    try:
        size = path.stat().st_size
        with open(path, "rb") as handle:
            header = handle.read(128)
            if len(header) < 128 or 0 in header[:4]:  # too short for v5, or a v4 file (scipy's Python reader)
                return
            indicator = header[126:128]
            if header[125 if indicator[:1] == b"I" else 124] != 1:  # the major version, as scipy finds it: no v5
                return
            if indicator not in (b"IM", b"MI"):
                raise ModelFileError(f"{path}: damaged MATLAB file: its endianness indicator (bytes 126-127) is "
                                     f"{indicator!r}, expected b'IM' or b'MI'")
            order = "<" if indicator == b"IM" else ">"
            stream, checker = _MatFile(handle, size), _Mat5Checker(order)
            while stream.pos < size:
                start, end = stream.pos, size + 1
                try:
                    mdtype, count = struct.unpack(order + "II", stream.read(8))
                    end = start + 8 + count
                    if mdtype == _MI_COMPRESSED:
                        inner = _MatCompressed(stream, count, start)
                        checker.matrix_element(inner, 1 << 40, "variable", 0, None if names is None else wanted)
                    elif mdtype == _MI_MATRIX:
                        handle.seek(start)
                        checker.matrix_element(stream, end, "variable", 0, None if names is None else wanted)
                    else:
                        raise _MatDamage(f"a variable of data type {mdtype}, expected an array (miMATRIX, 14) or "
                                         "compressed data (miCOMPRESSED, 15)", f"byte {start}")
                except _MatTruncated:
                    if end > size:  # the file ends inside this variable
                        return
                    raise _MatDamage("the compressed data ends inside the array it holds", f"byte {start}") from None
                handle.seek(end)
    except _MatDamage as damage:
        raise ModelFileError(f"{path}: damaged MATLAB file: {damage}") from None
    except OSError as error:
        raise ModelFileError(f"{path}: cannot read MATLAB file ({type(error).__name__}: {error})") from error
