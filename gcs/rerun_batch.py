"""Rerun component columns of many entities on one timeline, sent as one record batch.

`ColumnBatch` collects the columns of one logging call: positions and vectors, line strips,
Scalars series and AnyValues rows, each a list array with one row per time. Its Arrow arrays
are built when it is sent, few and large: every 2-D point of every column in one float32
array and every scalar in one float64 array, which the columns then slice (an Arrow conversion
costs a few microseconds whatever its size, and a flush has some twenty columns). Each column's
field carries `rerun:entity_path` metadata, so `rr.chunk.Chunk.from_record_batch` makes one
chunk per entity, and all the chunks of a call go out in one `rr.send_chunks`
(`send_batches`: batches on different times, e.g. slices of different lengths, go together).

Rerun's own cost is per column (some 25 us to make a chunk's column) and per chunk (some 15 us
to send it), not per row: fewer columns and entities are what make a flush cheaper.
"""

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import pyarrow as pa
import rerun as rr

__all__ = ["ColumnBatch", "send_batches"]

_F32_XY = pa.list_(pa.field("item", pa.float32(), nullable=False), 2)
"""Arrow type of one 2-D position or vector (rerun.datatypes.Vec2D)."""
_STRIP = pa.list_(pa.field("item", _F32_XY, nullable=False))
"""Arrow type of one line strip (rerun.components.LineStrip2D)."""
_SCALARS = rr.Scalars.descriptor_scalars()
_STRIPS = rr.LineStrips2D.descriptor_strips()

_FIELDS: dict[tuple[str, str], pa.Field] = {}
"""Schema fields by (entity path, component): the same few dozen every flush (keyed without the
Arrow type, whose hash costs some 8 us; a field is made anew if its column's type differs)."""
_INDEXES: dict[str, pa.Field] = {}
"""Index fields by timeline name."""


@lru_cache(maxsize=256)
def _uniform(count: int, m: int) -> pa.Array:
    """Offsets of `count` lists of m items each."""
    return pa.array(np.arange(0, count * m + 1, m, dtype=np.int32))


def _offsets(lengths: np.ndarray) -> np.ndarray:
    """Offsets (int32) of lists of the given lengths."""
    out = np.zeros(len(lengths) + 1, dtype=np.int32)
    np.cumsum(lengths, out=out[1:])
    return out


def _lists(
    lengths: np.ndarray,
    items: pa.Array,
    *,
    present: np.ndarray | None = None,
    dtype: pa.DataType | None = None,
) -> pa.Array:
    """A list array (of type dtype, default a list of items) of the given lengths of items;
    the rows not `present` null. Built from its buffers: `pa.ListArray.from_arrays` with a mask
    goes through pyarrow.compute (some 50 us, and 130 ms to import it)."""
    validity = None
    if present is not None:
        validity = pa.py_buffer(np.packbits(present, bitorder="little"))
    offsets = pa.py_buffer(_offsets(lengths))
    dtype = pa.list_(items.type) if dtype is None else dtype
    return pa.Array.from_buffers(dtype, len(lengths), [validity, offsets], children=[items])


def _field(path: str, descriptor: rr.ComponentDescriptor | str, dtype: pa.DataType) -> pa.Field:
    """The schema field of a column (an archetype's descriptor, or a bare name: AnyValues)."""
    component = descriptor if isinstance(descriptor, str) else descriptor.component
    key = (path, component)
    f = _FIELDS.get(key)
    if f is None or not f.type.equals(dtype):
        meta = {"rerun:kind": "data", "rerun:entity_path": path, "rerun:component": component}
        if not isinstance(descriptor, str):
            meta["rerun:archetype"] = descriptor.archetype
            meta["rerun:component_type"] = descriptor.component_type
        f = _FIELDS[key] = pa.field(f"{path}:{component}", dtype, metadata=meta)
    return f


@dataclass(frozen=True)
class _Points:
    """A column of 2-D points (or several columns of the same points): `per_row` items a row,
    or strips of them."""

    path: str
    descriptors: tuple[rr.ComponentDescriptor, ...]
    count: int
    """Points in the column."""
    per_row: int
    """Items (points, or strips) in each present row."""
    strip: int | np.ndarray | None = None
    """None: the items are points; else the points of each strip (one number for all)."""
    present: np.ndarray | None = None
    """(rows,) bool: the rows that hold items (the others are null); None: every row."""


class ColumnBatch:
    """The component columns of one logging call, on one timeline.

    t_ns: the (rows,) times [ns] of the batch's rows, a duration timeline.
    """

    def __init__(self, timeline: str, t_ns: np.ndarray) -> None:
        self.rows = len(t_ns)
        index = _INDEXES.get(timeline)
        if index is None:
            meta = {"rerun:kind": "index", "rerun:index_name": timeline}
            index = _INDEXES[timeline] = pa.field(timeline, pa.duration("ns"), metadata=meta)
        self._fields = [index]
        self._arrays = [pa.array(np.asarray(t_ns, dtype="timedelta64[ns]"))]
        self._xy: list[np.ndarray] = []
        self._points: list[_Points] = []
        self._scalars: list[tuple[str, np.ndarray]] = []

    def add(self, path: str, descriptor: rr.ComponentDescriptor | str, column: pa.Array) -> None:
        """A list array of `rows` rows (an archetype's descriptor, or a bare name: AnyValues)."""
        self._fields.append(_field(path, descriptor, column.type))
        self._arrays.append(column)

    def points(
        self,
        path: str,
        descriptors: rr.ComponentDescriptor | tuple[rr.ComponentDescriptor, ...],
        xy: np.ndarray,
        *,
        per_row: int,
    ) -> None:
        """Positions or vectors: xy (rows x per_row, 2), `per_row` of them in every row (the
        same array in the column of every descriptor given)."""
        if not isinstance(descriptors, tuple):
            descriptors = (descriptors,)
        xy = xy.reshape(-1, 2)
        self._xy.append(xy)
        self._points.append(_Points(path, descriptors, len(xy), per_row))

    def strips(
        self,
        path: str,
        xy: np.ndarray,
        *,
        points_per_strip: int | np.ndarray,
        per_row: int,
        present: np.ndarray | None = None,
    ) -> None:
        """LineStrips2D: `per_row` strips in every `present` row (default: every row; a row
        that is not present is null: nothing logged at that time, so the viewer keeps the
        previous strips), of `points_per_strip` points of xy (M, 2) each (one number, or one
        per strip of the present rows)."""
        xy = xy.reshape(-1, 2)
        self._xy.append(xy)
        strips = _Points(path, (_STRIPS,), len(xy), per_row, points_per_strip, present)
        self._points.append(strips)

    def scalars(self, path: str, values: np.ndarray) -> None:
        """Scalars: values (rows,) or (rows, lines), one line per column (an entity with
        several lines names them with a static SeriesLines). A row with no finite value stays
        empty (null); a series with no finite value at all is not logged."""
        self._scalars.append((path, np.asarray(values).reshape(self.rows, -1)))

    def values(self, path: str, name: str, rows: np.ndarray) -> None:
        """AnyValues component `name`: (rows, m) float64 or bool, one list of m per row."""
        flat = pa.array(np.ascontiguousarray(rows).ravel())
        self.add(path, name, pa.ListArray.from_arrays(_uniform(self.rows, rows.shape[1]), flat))

    def _add_points(self) -> None:
        if not self._points:
            return
        flat = np.concatenate(self._xy, dtype=np.float32).ravel()
        vec2 = pa.FixedSizeListArray.from_arrays(pa.array(flat), type=_F32_XY)
        at = 0
        for c in self._points:
            items = vec2.slice(at, c.count)
            at += c.count
            if c.strip is not None:
                if isinstance(c.strip, int | np.integer):
                    offsets = _uniform(c.count // c.strip, int(c.strip))
                    items = pa.ListArray.from_arrays(offsets, items, type=_STRIP)
                else:
                    items = _lists(c.strip, items, dtype=_STRIP)
            if c.present is None or c.present.all():
                column = pa.ListArray.from_arrays(_uniform(self.rows, c.per_row), items)
            else:
                counts = np.where(c.present, c.per_row, 0)
                column = _lists(counts, items, present=c.present)
            for descriptor in c.descriptors:
                self.add(c.path, descriptor, column)

    def _add_scalars(self) -> None:
        if not self._scalars:
            return
        values = np.concatenate([v.ravel() for _, v in self._scalars], dtype=np.float64)
        flat = pa.array(values)
        every_finite = bool(np.isfinite(values).all())
        at = 0
        for path, v in self._scalars:
            size = v.size
            mask = None
            if not every_finite:
                missing = ~np.isfinite(v).any(axis=1)
                if missing.all():
                    at += size
                    continue
                mask = missing if missing.any() else None
            items = flat.slice(at, size)
            if mask is None:
                column = pa.ListArray.from_arrays(_uniform(self.rows, v.shape[1]), items)
            else:
                # A null row keeps its (non-finite) values under its offsets.
                column = _lists(np.full(self.rows, v.shape[1]), items, present=~mask)
            self.add(path, _SCALARS, column)
            at += size

    def chunks(self) -> list[rr.chunk.Chunk]:
        """Build the columns' arrays: one chunk per entity."""
        self._add_points()
        self._add_scalars()
        if len(self._arrays) == 1:
            return []
        batch = pa.RecordBatch.from_arrays(self._arrays, schema=pa.schema(self._fields))
        return rr.chunk.Chunk.from_record_batch(batch)


def send_batches(stream: rr.RecordingStream, *batches: ColumnBatch) -> None:
    """Send the chunks of every batch in one call."""
    chunks = [c for batch in batches for c in batch.chunks()]
    if chunks:
        rr.send_chunks(chunks, recording=stream)
