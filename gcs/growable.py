"""An array that grows with room to spare.

A record that grows a flush at a time would copy every row before the new ones if it were
concatenated each time; `Growable` keeps a larger buffer and doubles it when it is full, so
adding rows costs those rows (amortized).
"""

import numpy as np
from numpy.typing import DTypeLike

__all__ = ["Growable"]


class Growable:
    """An array grown along one axis (its length there is `count`) in a buffer with room to
    spare. Views of it (`array`) are valid until its next change.

    Where nothing was put, the array holds `fill` (None: whatever the buffer held).
    """

    def __init__(
        self,
        shape: tuple[int, ...] | None = None,
        *,
        axis: int = 0,
        dtype: DTypeLike = float,
        fill: float | None = None,
    ) -> None:
        """shape: the array's shape, its length along `axis` ignored (None: that of the first
        values put, as their dtype)."""
        self.axis = axis
        self.fill = fill
        self.count = 0
        self._buffer: np.ndarray | None = None
        if shape is not None:
            self._buffer = self._empty(self._with_length(shape, 0), dtype)

    def _with_length(self, shape: tuple[int, ...], length: int) -> tuple[int, ...]:
        return (*shape[: self.axis], length, *shape[self.axis + 1 :])

    def _empty(self, shape: tuple[int, ...], dtype: DTypeLike) -> np.ndarray:
        if self.fill is None:
            return np.empty(shape, dtype=dtype)
        return np.full(shape, self.fill, dtype=dtype)

    def _along(self, start: int, stop: int) -> tuple[slice, ...]:
        """The index of positions `start` .. `stop` - 1 along the axis."""
        return (slice(None),) * self.axis + (slice(start, stop),)

    def _grow(self, length: int, keep: int, like: np.ndarray) -> np.ndarray:
        """The buffer, with room for `length` along the axis (twice that, at least 64, if it
        has to grow: its first `keep` kept), shaped and typed as `like` if there is none yet."""
        buffer = self._buffer
        if buffer is not None and length <= buffer.shape[self.axis]:
            return buffer
        source = like if buffer is None else buffer
        grown = self._empty(self._with_length(source.shape, max(2 * length, 64)), source.dtype)
        if buffer is not None:
            grown[self._along(0, keep)] = buffer[self._along(0, keep)]
        self._buffer = grown
        return grown

    def put(self, at: int, values: np.ndarray) -> None:
        """Positions `at` .. along the axis become `values`; those after them are dropped."""
        end = at + values.shape[self.axis]
        buffer = self._grow(end, at, values)
        buffer[self._along(at, end)] = values
        if self.fill is not None and end < self.count:
            buffer[self._along(end, self.count)] = self.fill
        self.count = end

    def append(self, values: np.ndarray) -> None:
        """`values` after the array's, along the axis."""
        self.put(self.count, values)

    def reserve(self, length: int) -> None:
        """The array at least `length` long along the axis (`fill` where nothing was put)."""
        if length > self.count:
            if self._buffer is None:
                raise ValueError("the array's shape is not known before values are put")
            self._grow(length, self.count, self._buffer)
            self.count = length

    @property
    def array(self) -> np.ndarray:
        """The array (a view of the buffer; an empty array if its shape is not known yet)."""
        if self._buffer is None:
            return np.empty((0,))
        return self._buffer[self._along(0, self.count)]
