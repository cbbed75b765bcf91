"""MATLAB MAT files (v4 and v5, as ``scipy.io.loadmat`` reads them) read within a memory bound.

``scipy.io.loadmat`` trusts a file's declared sizes: a compressed variable of a few kilobytes
can inflate to gigabytes, and a cell array's dimensions alone make it allocate. So the file's
element headers are walked here first, without inflating more than a variable's header of any
compressed element: every variable is listed with its name, class and dimensions, and only the
variables a record needs are handed to loadmat, after their declared sizes were checked against
the limit, as a new in-memory file holding nothing else (compressed ones inflated here, at most
to their declared size). Only real numeric matrices are handed over, so loadmat never builds
cells, structs, objects or sparse matrices; a MAT file never unpickles anything. A scalar
struct's numeric fields (``data.u``; ``yout.signals.values`` through nested structs, as
Simulink logs them) are read alike: the struct's element is walked in order, inflated as it is
read within a bound, and each field's element is handed over as a variable of its own.

The element layout is MathWorks' "MAT-File Format" (v5: a 128-byte header, then tagged data
elements; v4: a 20-byte header per variable). v7.3 files are HDF5 and are refused with advice.
"""

from __future__ import annotations

import io
import math
import struct
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import scipy

from models.errors import InputError

# v5 data types and array classes (MAT-File Format, tables 1-2 and 1-3).
MI_INT8, MI_INT32, MI_UINT32, MI_MATRIX, MI_COMPRESSED = 1, 5, 6, 14, 15
STRUCT_CLASS = 2
# The data types a numeric matrix's values may be stored in: (u)int8…(u)int64, single, double.
# scipy's reader indexes a table by this code unchecked: another code crashed the process (SIGBUS).
NUMBER_TYPES = frozenset({1, 2, 3, 4, 5, 6, 7, 9, 12, 13})
CLASSES = {
    1: "cell",
    2: "struct",
    3: "object",
    4: "char",
    5: "sparse",
    6: "double",
    7: "single",
    8: "int8",
    9: "uint8",
    10: "int16",
    11: "uint16",
    12: "int32",
    13: "uint32",
    14: "int64",
    15: "uint64",
    16: "function",
    17: "opaque",
}
NUMERIC_CLASSES = frozenset(range(6, 16))
COMPLEX_FLAG = 0x0800
V5_HEADER_BYTES = 128
# A variable's header (tag, flags, dimensions, name) within a compressed element is read from
# at most this many inflated bytes: 63-character names and 2-D arrays need about 120.
VARIABLE_HEADER_BYTES = 1024
# Variables a file may hold, so that walking its headers stays cheap.
MAX_VARIABLES = 256
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
# v4: precision digit P of the type code → item size; type digit T: 0 numeric, 1 text, 2 sparse.
V4_ITEM_BYTES = {0: 8, 1: 4, 2: 4, 3: 2, 4: 2, 5: 1}
V4_CLASSES = {0: "double", 1: "single", 2: "int32", 3: "int16", 4: "uint16", 5: "uint8"}
INFLATE_CHUNK = 1 << 16
MAX_STRUCT_DEPTH = 8  # structs within structs a field's name may pass through


@dataclass(frozen=True)
class MatVariable:
    """One variable as its header declares it, and where its element lies in the file."""

    name: str
    shape: tuple[int, ...]
    class_name: str
    numeric: bool  # a real numeric (or logical) full matrix: what a signal can be read from
    start: int
    end: int
    compressed: bool
    # A struct's field: its miMATRIX element, read out of the struct's and named for loadmat.
    element: bytes | None = None

    def describe(self) -> str:
        return f"{self.name} ({'×'.join(str(size) for size in self.shape)} {self.class_name})"


@dataclass(frozen=True)
class MatFile:
    data: bytes
    version: int  # 4 or 5
    byte_order: str  # '<' or '>'
    variables: dict[str, MatVariable]  # by name, in the file's order

    def describe(self) -> str:
        return ", ".join(variable.describe() for variable in self.variables.values()) or "no variables"


def list_mat(data: bytes) -> MatFile:
    """The variables a MAT file declares, read from their headers alone."""
    if data.startswith(HDF5_SIGNATURE) or data[512:520] == HDF5_SIGNATURE:
        raise _v73_error()
    if len(data) < 4:
        raise InputError("the file is too short to be a MAT file")
    if 0 in data[:4]:  # as scipy.io tells a v4 file: its first type code has a zero byte
        order = _v4_byte_order(data)
        return MatFile(data, 4, order, _unique(_v4_variables(data, order)))
    if len(data) < V5_HEADER_BYTES or data[126:128] not in (b"IM", b"MI"):
        raise InputError("the file is not a MAT file (no MAT v5 header)")
    order = "<" if data[126:128] == b"IM" else ">"
    (version,) = struct.unpack_from(order + "H", data, 124)
    if version == 0x0200:
        raise _v73_error()
    if version != 0x0100:
        raise InputError(f"the MAT file has an unknown version 0x{version:04x}")
    return MatFile(data, 5, order, _unique(_v5_variables(data, order)))


def load_variables(mat: MatFile, variables: Sequence[MatVariable]) -> dict[str, np.ndarray]:
    """The named variables, real numeric arrays of their declared shapes, as float64.

    The caller bounds their declared size (:func:`declared_bytes`); no compressed element is
    then inflated beyond what its dimensions can hold, so memory stays within a few times that.
    """
    for variable in variables:
        if variable.class_name == "struct":
            raise InputError(
                f"MAT variable {variable.describe()} is a struct: name one of its fields, "
                f"as {variable.name}.FIELD"
            )
        if not variable.numeric:
            raise InputError(f"MAT variable {variable.describe()} is not a real numeric array")
    if mat.version == 4:
        content = b"".join(mat.data[variable.start : variable.end] for variable in variables)
    else:
        header = mat.data[:116] + bytes(8) + mat.data[124:V5_HEADER_BYTES]  # no subsystem offset
        content = header + b"".join(_v5_element(mat, variable) for variable in variables)
    try:
        # A variable scipy cannot read comes back as a string (with a warning): refused below.
        loaded = scipy.io.loadmat(io.BytesIO(content), squeeze_me=False, spmatrix=False)
    except Exception as exc:  # scipy.io raises many kinds on a damaged file; all mean that
        raise InputError(f"the MAT file is damaged ({type(exc).__name__}: {exc})") from None
    arrays = {}
    for variable in variables:
        value = loaded.get(variable.name)
        if not isinstance(value, np.ndarray) or value.dtype.kind not in "biuf":
            raise InputError(f"MAT variable {variable.describe()} cannot be read as numbers")
        arrays[variable.name] = np.asarray(value, dtype=np.float64)
    return arrays


def declared_bytes(variables: Sequence[MatVariable]) -> int:
    """What the variables take as float64 arrays, by their declared dimensions."""
    return sum(math.prod(variable.shape) for variable in variables) * np.float64().nbytes


def _v73_error() -> InputError:
    return InputError(
        "the MAT file is a v7.3 (HDF5) file, which is not read: save it with "
        "save(name, ..., '-v7') in MATLAB, or as CSV"
    )


def _unique(variables: list[MatVariable]) -> dict[str, MatVariable]:
    names = [variable.name for variable in variables]
    twice = sorted({name for name in names if names.count(name) > 1})
    if twice:
        raise InputError(f"the MAT file holds the variable(s) {', '.join(twice)} more than once")
    return {variable.name: variable for variable in variables}


def _too_many() -> InputError:
    return InputError(f"the MAT file holds more than {MAX_VARIABLES} variables; save only the signals")


# --- v5 ---------------------------------------------------------------------------------------


def _v5_variables(data: bytes, order: str) -> list[MatVariable]:
    variables = []
    position = V5_HEADER_BYTES
    while position < len(data):
        if len(variables) == MAX_VARIABLES:
            raise _too_many()
        if len(data) - position < 8:
            raise InputError(f"the MAT file ends inside an element header at byte {position}")
        kind, size = struct.unpack_from(order + "2I", data, position)
        end = position + 8 + size
        if size == 0 or end > len(data):
            raise InputError(
                f"the MAT file is cut off or damaged: element at byte {position} declares {size} bytes"
            )
        if kind == MI_COMPRESSED:
            head = _inflate(data, position + 8, end, VARIABLE_HEADER_BYTES)
        elif kind == MI_MATRIX:
            head = data[position : min(end, position + VARIABLE_HEADER_BYTES)]
        else:
            raise InputError(
                f"the MAT file holds an element of type {kind} at byte {position}, not a variable"
            )
        variables.append(_v5_header(head, order, position, end, kind == MI_COMPRESSED))
        position = end
    return variables


def _v5_header(head: bytes, order: str, start: int, end: int, compressed: bool) -> MatVariable:
    """Name, class and dimensions from the first bytes of a miMATRIX element."""
    where = f"the MAT variable at byte {start}"
    try:
        kind, _ = struct.unpack_from(order + "2I", head, 0)
        if kind != MI_MATRIX:
            raise InputError(f"{where} is not a matrix (data type {kind})")
        flags_kind, flags, after = _subelement(head, 8, order)
        dims_kind, dims, after = _subelement(head, after, order)
        name_kind, name, after = _subelement(head, after, order)
    except struct.error:
        raise InputError(
            f"{where} has a header cut off or longer than {VARIABLE_HEADER_BYTES} bytes"
        ) from None
    if (
        flags_kind != MI_UINT32
        or len(flags) != 8
        or dims_kind != MI_INT32
        or len(dims) % 4
        or name_kind != MI_INT8
    ):
        raise InputError(f"{where} has a malformed header")
    (word,) = struct.unpack_from(order + "I", flags)
    class_code = word & 0xFF
    shape = struct.unpack(order + f"{len(dims) // 4}i", dims)
    if len(shape) < 2 or min(shape) < 0:
        raise InputError(f"{where} declares dimensions {shape}")
    numeric = class_code in NUMERIC_CLASSES and not word & COMPLEX_FLAG
    class_name = CLASSES.get(class_code, f"class {class_code}") + (" complex" if word & COMPLEX_FLAG else "")
    if numeric and (values_kind := _data_type(head, after, order)) not in NUMBER_TYPES:
        # Listed, but never handed to loadmat: asked for, it is refused as not numeric.
        numeric = False
        class_name += f" stored as data type {values_kind}"
    return MatVariable(name.decode("latin1"), shape, class_name, numeric, start, end, compressed)


def _subelement(head: bytes, position: int, order: str) -> tuple[int, bytes, int]:
    """(data type, data, next position) of the data element at ``position``; small elements
    keep up to 4 bytes of data in their tag."""
    (word,) = struct.unpack_from(order + "I", head, position)
    if word >> 16:
        size = word >> 16
        if size > 4:
            raise struct.error("small data element longer than 4 bytes")
        return word & 0xFFFF, head[position + 4 : position + 4 + size], position + 8
    (size,) = struct.unpack_from(order + "I", head, position + 4)
    data = head[position + 8 : position + 8 + size]
    if len(data) != size:
        raise struct.error("data element runs past the header bytes")
    return word, data, position + 8 + -(-size // 8) * 8


def _data_type(head: bytes, position: int, order: str) -> int | None:
    """The data type in the tag at ``position``, None if the header ends before it."""
    if len(head) < position + 4:
        return None
    (word,) = struct.unpack_from(order + "I", head, position)
    return word & 0xFFFF if word >> 16 else word


def _v5_element(mat: MatFile, variable: MatVariable) -> bytes:
    """The variable's uncompressed miMATRIX element, inflated at most to its declared size.

    Its data (in its stored type) takes at most 8 bytes a value, within the checked float64 size;
    the header around it at most :data:`VARIABLE_HEADER_BYTES`.
    """
    if variable.element is not None:
        return variable.element
    if not variable.compressed:
        return mat.data[variable.start : variable.end]
    (size,) = struct.unpack_from(
        mat.byte_order + "I", _inflate(mat.data, variable.start + 8, variable.end, 8), 4
    )
    if size > declared_bytes([variable]) + VARIABLE_HEADER_BYTES:
        raise InputError(
            f"MAT variable {variable.describe()} declares {size} bytes, more than its values can hold"
        )
    element = _inflate(mat.data, variable.start + 8, variable.end, 8 + size)
    if len(element) < 8 + size:
        raise InputError(f"MAT variable {variable.name!r} is shorter than its header says")
    return element


def _inflate(data: bytes, start: int, end: int, limit: int) -> bytes:
    """At most ``limit`` bytes inflated from the zlib stream in ``data[start:end]``."""
    return _Inflating(memoryview(data)[start:end]).take(limit)


class _Inflating:
    """A zlib stream inflated on demand, fed in chunks so that no more than a chunk of input is
    pending at any time."""

    def __init__(self, source: memoryview) -> None:
        self._inflater = zlib.decompressobj()
        self._source = source

    def take(self, limit: int) -> bytes:
        """The next ``limit`` bytes, fewer where the stream ends."""
        out = bytearray()
        try:
            while len(out) < limit and not self._inflater.eof:
                pending = self._inflater.unconsumed_tail
                if not pending:
                    if not self._source:
                        break
                    pending, self._source = self._source[:INFLATE_CHUNK], self._source[INFLATE_CHUNK:]
                out += self._inflater.decompress(pending, limit - len(out))
        except zlib.error as exc:
            raise InputError(f"a compressed MAT variable is damaged ({exc})") from None
        return bytes(out)


# --- struct fields ----------------------------------------------------------------------------


def with_fields(mat: MatFile, names: Iterable[str], budget: int | None = None) -> MatFile:
    """``mat`` with the fields of the scalar structs that dotted ``names`` begin with listed as
    variables of their own, named by their path (``data.u``, ``yout.signals.values``), so that
    they are found, bounded and loaded as variables are. Other structs are not walked.

    A struct's element is read in order, inflated as it is read where it is compressed, and at
    most ``budget`` bytes of it (None: no bound); numeric fields' elements are kept, every other
    field is listed by its header alone and skipped.
    """
    roots = {name.split(".", 1)[0] for name in names if "." in name}
    found: dict[str, MatVariable] = {}
    for variable in mat.variables.values():
        if variable.name in roots and mat.version == 5 and variable.class_name == "struct":
            walk = _Walk(_Reader(mat.data, variable, budget), mat.byte_order, variable, found)
            _, size = struct.unpack(mat.byte_order + "2I", walk.reader.read(8))  # a matrix: listed as one
            walk.struct(variable.name, size, depth=1)
    clash = sorted(found.keys() & mat.variables.keys())
    if clash:
        raise InputError(f"the MAT file names both a variable and a struct's field {', '.join(clash)}")
    return replace(mat, variables=mat.variables | found)


class _Reader:
    """A variable's miMATRIX element read in order: from the file, or inflated as it is read
    where the variable is compressed; more than ``budget`` bytes in all is refused."""

    def __init__(self, data: bytes, variable: MatVariable, budget: int | None) -> None:
        self._name = variable.name
        self._budget = budget
        self._read = 0
        view = memoryview(data)
        # Compressed: inflated from after the element's tag; otherwise the element as it lies.
        self._inflating = _Inflating(view[variable.start + 8 : variable.end]) if variable.compressed else None
        self._source = view[variable.start : variable.end] if not variable.compressed else view[:0]

    def read(self, size: int) -> bytes:
        """The next ``size`` bytes; InputError where the element ends before them."""
        self._read += size
        if self._budget is not None and self._read > self._budget:
            raise InputError(
                f"the MAT struct {self._name!r} unpacks to more than {self._budget} bytes before the "
                "fields named are read: save those signals as variables of their own"
            )
        if self._inflating is not None:
            chunk = self._inflating.take(size)
        else:
            chunk, self._source = bytes(self._source[:size]), self._source[size:]
        if len(chunk) < size:
            raise InputError(f"the MAT struct {self._name!r} ends inside one of its fields")
        return chunk

    def skip(self, size: int) -> None:
        while size > 0:
            step = min(size, INFLATE_CHUNK)
            self.read(step)
            size -= step


Subelement = tuple[int, bytes, bytes]  # data type, data, the raw bytes read (tag and padding)


@dataclass
class _Walk:
    """One struct variable's walk (:func:`with_fields`): its element read in order, the file's
    byte order, and the fields found, by path."""

    reader: _Reader
    order: str
    root: MatVariable
    found: dict[str, MatVariable]

    def struct(self, path: str, size: int, depth: int, header: list[Subelement] | None = None) -> None:
        """List the fields of the struct whose element (``size`` bytes after its tag) the reader
        is at, each by ``path``.field: numeric ones with their element, structs walked in turn
        (to ``MAX_STRUCT_DEPTH``), the others by their header alone. ``header``: its flags,
        dimensions and name, where they were read already."""
        header = header or [self._subelement() for _ in range(3)]
        shape = self._dimensions(header[1])
        if math.prod(shape) != 1:
            raise InputError(
                f"the MAT struct {path!r} is an array of {'×'.join(map(str, shape))} structs; "
                "only a single struct's fields are read"
            )
        length, names = self._subelement(), self._subelement()
        (width,) = struct.unpack(self.order + "i", length[1]) if len(length[1]) == 4 else (0,)
        if length[0] != MI_INT32 or names[0] != MI_INT8 or width <= 0 or len(names[1]) % width:
            raise InputError(f"the MAT struct {path!r} has malformed field names")
        used = sum(len(raw) for _, _, raw in (*header, length, names))
        for offset in range(0, len(names[1]), width):
            field = names[1][offset : offset + width].rstrip(b"\x00").decode("latin1")
            kind, field_size = struct.unpack(self.order + "2I", self.reader.read(8))
            used += 8 + field_size
            if kind != MI_MATRIX or used > size:
                raise InputError(f"the MAT struct {path!r} has a malformed field {field!r}")
            self.field(f"{path}.{field}", field_size, depth)

    def field(self, path: str, size: int, depth: int) -> None:
        """One field's element (``size`` bytes after its tag), listed as the variable ``path``."""
        if len(self.found) == MAX_VARIABLES:
            raise _too_many()
        root = self.root
        if size == 0:  # an empty field: MATLAB writes its tag alone
            self.found[path] = MatVariable(path, (0, 0), "empty", False, root.start, root.end, False)
            return
        header = [self._subelement() for _ in range(3)]
        flags, dims, _ = header
        head = b"".join(raw for _, _, raw in header)
        if len(head) > size or flags[0] != MI_UINT32 or len(flags[1]) != 8:
            raise InputError(f"the MAT struct field {path!r} has a malformed header")
        (word,) = struct.unpack_from(self.order + "I", flags[1])
        if word & 0xFF == STRUCT_CLASS and depth < MAX_STRUCT_DEPTH:
            self.struct(path, size, depth + 1, header)
            return
        label = path.encode("latin1")
        named = struct.pack(self.order + "2I", MI_INT8, len(label)) + label + bytes(-len(label) % 8)
        body = flags[2] + dims[2] + named
        if word & 0xFF in NUMERIC_CLASSES and not word & COMPLEX_FLAG:
            values = math.prod(self._dimensions(dims)) * np.float64().nbytes
            if size - len(head) > values + VARIABLE_HEADER_BYTES:
                raise InputError(f"the MAT struct field {path!r} declares more bytes than its values hold")
            body += self.reader.read(size - len(head))
        else:  # listed by its header, as variables are, and skipped
            self.reader.skip(size - len(head))
        element = struct.pack(self.order + "2I", MI_MATRIX, len(body)) + body
        variable = _v5_header(element[:VARIABLE_HEADER_BYTES], self.order, root.start, root.end, False)
        self.found[path] = replace(variable, element=element if variable.numeric else None)

    def _subelement(self) -> Subelement:
        """The next data element (:func:`_subelement`, read in order)."""
        tag = self.reader.read(8)
        (word,) = struct.unpack_from(self.order + "I", tag)
        if word >> 16:  # a small element: its data in the tag's last four bytes
            size = word >> 16
            if size > 4:
                raise InputError("a MAT struct holds a malformed data element")
            return word & 0xFFFF, tag[4 : 4 + size], tag
        (size,) = struct.unpack_from(self.order + "I", tag, 4)
        if size > VARIABLE_HEADER_BYTES:
            raise InputError("a MAT struct holds a header element longer than a header can be")
        data = self.reader.read(-(-size // 8) * 8)
        return word, data[:size], tag + data

    def _dimensions(self, dims: Subelement) -> tuple[int, ...]:
        kind, data, _ = dims
        if kind != MI_INT32 or len(data) % 4 or len(data) < 8:
            raise InputError("a MAT struct holds a field with malformed dimensions")
        return struct.unpack(self.order + f"{len(data) // 4}i", data)


# --- v4 ---------------------------------------------------------------------------------------


def _v4_byte_order(data: bytes) -> str:
    (mopt,) = struct.unpack_from("<i", data, 0)
    return "<" if 0 <= mopt <= 5000 else ">"


def _v4_variables(data: bytes, order: str) -> list[MatVariable]:
    variables = []
    position = 0
    while position < len(data):
        if len(variables) == MAX_VARIABLES:
            raise _too_many()
        if len(data) - position < 20:
            raise InputError(f"the MAT v4 file ends inside a variable header at byte {position}")
        mopt, rows, columns, imaginary, name_length = struct.unpack_from(order + "5i", data, position)
        order_code, rest = divmod(mopt, 1000)
        unused, rest = divmod(rest, 100)
        precision, kind = divmod(rest, 10)
        if not (0 <= mopt <= 5000 and order_code in (0, 1) and unused == 0 and precision in V4_ITEM_BYTES):
            raise InputError(f"the MAT v4 variable at byte {position} has an unknown type code {mopt}")
        if min(rows, columns, name_length) < 0 or kind not in (0, 1, 2):
            raise InputError(f"the MAT v4 variable at byte {position} has a malformed header")
        name_end = position + 20 + name_length
        end = name_end + rows * columns * V4_ITEM_BYTES[precision] * (2 if imaginary else 1)
        if end > len(data):
            raise InputError(f"the MAT v4 variable at byte {position} is cut off")
        name = data[position + 20 : name_end].rstrip(b"\x00").decode("latin1")
        class_name = {0: V4_CLASSES[precision], 1: "char", 2: "sparse"}[kind] + (
            " complex" if imaginary else ""
        )
        variables.append(
            MatVariable(name, (rows, columns), class_name, kind == 0 and not imaginary, position, end, False)
        )
        position = end
    return variables
