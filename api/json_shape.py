"""Count what parsing a JSON body would build, from its raw bytes, before any parser runs.

`json.loads` turns a 3-byte `{}` into a 64-byte dict and `0,` into a list slot and an
int, so a body's size alone does not bound the memory its parse needs: `[{},{},...]`
grows about 25-fold. `JsonShape` reads the bytes as they arrive (in any pieces) and counts
every value the parse would create (keys included), every array and object, and the
deepest nesting, so a caller can refuse a body past its budget while nothing but the raw
bytes exists. Strings are skipped as JSON defines them (a quote ends a string unless an
odd run of backslashes precedes it), so brackets, commas and colons inside strings do not
count. The scan is vectorised with numpy over fixed slices: its own memory is a few MiB
and its time about a tenth of a second per 10 MB, whatever the body holds.

The counts are exact for a valid document and for the valid prefix of an invalid one (a
parser stops at the first error, so it never builds more than that prefix holds).
"""

from __future__ import annotations

import numpy as np

SLICE_BYTES = 1 << 18  # bytes scanned per vector step: bounds the scan's own memory

_QUOTE, _BACKSLASH, _BRACE = ord('"'), ord("\\"), ord("{")
_DEPTH_STEP = np.zeros(256, np.int8)  # +1 opens an array/object, -1 closes one
_DEPTH_STEP[[ord("["), ord("{")]] = 1
_DEPTH_STEP[[ord("]"), ord("}")]] = -1
_SEPARATOR = np.zeros(256, bool)  # each ',' and ':' outside strings starts one more value
_SEPARATOR[[ord(","), ord(":")]] = True


class JsonShape:
    """Running counts over a JSON byte stream fed piece by piece.

    `values` counts every value a parser would build, object keys included, plus one per
    empty array or object (an upper bound that is exact for non-empty containers);
    `containers` the arrays and objects, `objects` the objects alone, `strings` the strings
    (keys included); `max_depth` the deepest nesting; `has_nul` a raw NUL byte (never in
    UTF-8 JSON; its presence would let a parser guess UTF-16 or UTF-32, whose bytes this
    scan does not read as characters).
    """

    def __init__(self) -> None:
        self.size = 0
        self.values = 1  # the top-level value
        self.containers = 0
        self.objects = 0
        self.quotes = 0  # quotes that open or close a string
        self.depth = 0
        self.max_depth = 0
        self.has_nul = False
        self._in_string = 0  # 1 while inside a string at the end of the last piece
        self._odd_backslashes = 0  # 1 if the last piece ended in an odd run of backslashes

    @property
    def strings(self) -> int:
        """Strings begun so far (each has an opening quote)."""
        return (self.quotes + 1) // 2

    def feed(self, data: bytes) -> None:
        """Account for the next piece of the body."""
        if not data:
            return
        self.size += len(data)
        self.has_nul = self.has_nul or b"\x00" in data
        view = memoryview(data)
        for start in range(0, len(view), SLICE_BYTES):
            self._scan(np.frombuffer(view[start:start + SLICE_BYTES], np.uint8))

    def _scan(self, piece: np.ndarray) -> None:
        quote = piece == _QUOTE
        backslash = piece == _BACKSLASH
        if self._odd_backslashes or backslash.any():
            quote &= ~self._escaped(backslash)
        # a byte is inside a string when an odd number of real quotes precede or are it
        # (the opening quote counts as inside, the closing one as outside)
        parity = np.cumsum(quote, dtype=np.int32)
        parity += self._in_string
        parity &= 1
        self._in_string = int(parity[-1])
        self.quotes += int(np.count_nonzero(quote))
        outside = parity == 0
        step = _DEPTH_STEP[piece]
        step *= outside
        opened = int(np.count_nonzero(step > 0))
        separators = int(np.count_nonzero(_SEPARATOR[piece] & outside))
        self.containers += opened
        self.objects += int(np.count_nonzero((piece == _BRACE) & outside))
        self.values += opened + separators
        depth = np.cumsum(step, dtype=np.int32)
        depth += self.depth
        self.max_depth = max(self.max_depth, int(depth.max()))
        self.depth = int(depth[-1])

    def _escaped(self, backslash: np.ndarray) -> np.ndarray:
        """Which bytes of the piece follow an odd run of backslashes (escaped characters)."""
        n = backslash.size
        index = np.arange(n, dtype=np.int32)
        last_other = np.where(backslash, -1, index)  # last non-backslash at or before i
        np.maximum.accumulate(last_other, out=last_other)
        run = index - last_other  # backslashes ending at i ...
        run[last_other < 0] += self._odd_backslashes  # ... a leading run continues the last
        escaped = np.empty(n, bool)
        escaped[0] = bool(self._odd_backslashes)
        np.bitwise_and(run[:-1], 1, out=run[:-1])
        escaped[1:] = run[:-1].astype(bool)
        self._odd_backslashes = int(run[-1] & 1)
        return escaped
