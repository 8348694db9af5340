"""The size a netCDF classic, 64-bit offset or CDF-5 file must have, from its header (`classic_shortfall`).

The netCDF library reads a classic file cut short without complaint: the variables past the end of the file come
back as fill values or zeros. An Exodus II file cut short would then be read as a mesh with nodes at the origin.
`classic_shortfall` parses the header (the format of the netCDF Users Guide, "The NetCDF Classic Format
Specification") and returns how many bytes the variables need beyond the end of the file. netCDF-4 (HDF5) files
are checked by the HDF5 library itself, which refuses a truncated file when it opens it.
"""

from __future__ import annotations

import os

#: Bytes per value of each netCDF external type (NC_BYTE .. NC_UINT64).
_TYPE_SIZE = {1: 1, 2: 1, 3: 2, 4: 4, 5: 4, 6: 8, 7: 1, 8: 2, 9: 4, 10: 8, 11: 8}
_DIMENSION, _VARIABLE, _ATTRIBUTE = 0x0A, 0x0B, 0x0C


class _Header:
    def __init__(self, data: bytes, version: int) -> None:
        self.data, self.pos = data, 4
        self.count = 8 if version == 5 else 4  # nelems, dimension lengths, dimension ids
        self.offset = 4 if version == 1 else 8  # a variable's begin

    def _int(self, size: int) -> int:
        if self.pos + size > len(self.data):
            raise EOFError
        value = int.from_bytes(self.data[self.pos : self.pos + size], "big")
        self.pos += size
        return value

    def number(self) -> int:
        return self._int(self.count)

    def _skip(self, n: int) -> None:
        self.pos += n + (-n % 4)
        if self.pos > len(self.data):
            raise EOFError

    def name(self) -> None:
        self._skip(self.number())

    def _list(self, tag: int) -> int:
        found = self._int(4)
        n = self.number()
        if found not in (0, tag):
            raise ValueError(f"bad header tag {found}")
        return n

    def attributes(self) -> None:
        for _ in range(self._list(_ATTRIBUTE)):
            self.name()
            kind = self._int(4)
            self._skip(self.number() * _TYPE_SIZE.get(kind, 1))


def classic_shortfall(path: str | os.PathLike) -> int | None:
    """How many bytes a netCDF classic / 64-bit offset / CDF-5 file lacks for its variables (0 when complete);
    None when the file is not such a file (netCDF-4 / HDF5, or not netCDF at all: the netCDF library says which).

    Raises `ValueError` for a header that cannot be parsed (cut inside the header, or corrupt).
    """
    with open(path, "rb") as f:
        head = f.read(4)
        if len(head) < 4 or head[:3] != b"CDF" or head[3] not in (1, 2, 5):
            return None
        size = os.fstat(f.fileno()).st_size
        f.seek(0)
        data = f.read(min(size, 1 << 26))  # headers are small; 64 MiB is far beyond any real one
    h = _Header(data, head[3])
    try:
        numrecs = h.number()
        if numrecs in (0xFFFFFFFF, 0xFFFFFFFFFFFFFFFF):  # "streaming": the number of records is not recorded
            numrecs = 0
        lengths = []
        for _ in range(h._list(_DIMENSION)):
            h.name()
            lengths.append(h.number())
        h.attributes()
        variables = []  # (is a record variable, begin, bytes of one record or of the whole variable)
        for _ in range(h._list(_VARIABLE)):
            h.name()
            dims = [h.number() for _ in range(h.number())]
            h.attributes()
            kind = h._int(4)
            h.number()  # vsize (padded; recomputed below without the padding)
            begin = h._int(h.offset)
            if kind not in _TYPE_SIZE or any(d >= len(lengths) for d in dims):
                raise ValueError("bad variable entry")
            record = bool(dims) and lengths[dims[0]] == 0
            n = _TYPE_SIZE[kind]
            for d in dims[1:] if record else dims:
                n *= lengths[d]
            variables.append((record, begin, n))
    except EOFError:
        raise ValueError(f"the header is cut short ({len(data)} bytes)") from None
    rec_vars = [v for v in variables if v[0]]
    if len(rec_vars) == 1:
        recsize = rec_vars[0][2]  # one record variable: records are not padded
    else:
        recsize = sum(n + (-n % 4) for _, _, n in rec_vars)
    end = 0
    for record, begin, n in variables:
        if record:
            end = max(end, begin + (numrecs - 1) * recsize + n if numrecs else 0)
        else:
            end = max(end, begin + n)
    return max(0, end - size)

