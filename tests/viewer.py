"""A recording as its user sees it: Rerun's web viewer in headless Chromium, read as pixels.

Importable from any test module as ``viewer`` (the tests folder is on the import path through
its conftest). `open_viewer` serves a recording with ``rerun FILE --serve-web`` on loopback,
shows it in a headless Chromium driven over the DevTools protocol (a small WebSocket client on
the standard library, below) and hands back screenshots; `locate_views` finds where each view
of the recording's own blueprint is on a screenshot, and `panel_ink` says whether a view drew
data there.

What counts as drawn: in the light theme pinned here the viewer paints its chrome, axes, grid
lines, tick labels and time cursor in greys (chroma, max - min of R, G, B, under 10), while the
fleet's lines, trails and points are in the recording's colours. Coloured pixels (chroma at
least `MIN_CHROMA`) that join into a piece bigger than a legend swatch (`MAX_SWATCH_PX` on
both sides) are strokes: a line, a trail. A view drew data when its plot area (the view less
its title bar) holds at least `MIN_STROKE_PX` pixels of strokes. An empty view shows no colour
at all; a view whose data is missing shows none either, or only the swatches of its legend
and, in a map, labels and points, none of which is a stroke.

Where the views are: the viewer tiles its viewport as the blueprint's containers say and draws
a one-pixel rule between neighbouring tiles, in the colour of the rules under its top bar and
above its time panel. `locate_views` finds those two rules and the open side panels' borders
(the viewport lies between them), then splits the viewport as the blueprint does: a horizontal or
vertical container at the rules nearest to where its shares put them, a grid at the rules that
cross it from side to side (its cells filled row by row, in the blueprint's order), a tabs
container's active tab below its bar of tab names (the others are not shown). A collapsed side
panel leaves the viewport the window's edge.

How fast the viewer redraws after an input: `FRAME_PROBE`, put in the page before it loads,
notes every animation frame (its start and end on the page's clock, and its WebGL draw calls)
and every pointer and key press. The viewer asks for a frame every display frame but draws only
in those where something changed; `Viewer.redraw_after` gives an idle viewer (no frame drawn
for `QUIET_S`, its frames at the display's rate again: `STEADY_FRAMES`) an input (a click, a
key), waits until it is idle again, and times the redraw
from the press to the start of the second frame after the last that drew (`Redraw`): the
browser keeps one frame in flight, so then the last is shown.

Nothing leaves the machine: the viewer binds 127.0.0.1, its usage analytics are disabled in a
private HOME before it starts, and Chromium resolves no host name but 127.0.0.1 and sends
everything else to a proxy that does not exist. The page asks for more than the recording (web
fonts, Rerun's latest release, its examples, and it posts usage analytics of its own);
`Viewer.off_loopback` lists those requests, none of which may get an answer.
"""

import base64
import contextlib
import io
import json
import os
import shutil
import signal
import socket
import struct
import subprocess
import time
import urllib.parse
import urllib.request
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import rerun as rr
from helpers import ProcessGroup, free_port_block, live_processes_naming
from PIL import Image
from scipy import ndimage

__all__ = [
    "CHROMIUM",
    "MAX_SWATCH_PX",
    "MIN_CHROMA",
    "MIN_STROKE_PX",
    "WINDOW",
    "Container",
    "Ink",
    "FRAME_PROBE",
    "LayoutNotFound",
    "Redraw",
    "Rect",
    "View",
    "Viewer",
    "ViewerError",
    "blueprint_fields",
    "locate_views",
    "open_viewer",
    "panel_ink",
    "recorded_blueprint",
    "rerun_binary",
    "rerun_home",
    "scrub_points",
]

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
"""The Chromium executable, or None where it is not installed."""

WINDOW = (1600, 1000)
"""Browser viewport [px], at one device pixel per CSS pixel: a laptop's screen (the recording's
blueprint starts the viewer's side panels collapsed; one left open would take its side)."""

MIN_CHROMA = 30
"""Least max - min of a pixel's R, G, B for it to count as coloured (the viewer's greys: < 10;
the fleet's palette, its lighter shades and faint truth lines blended on white: 30 or more)."""

MAX_SWATCH_PX = 12
"""Size of the largest piece of colour that is not a stroke [px, both sides]: a legend swatch,
a point, a letter of a label."""

MIN_STROKE_PX = 100
"""Least pixels of strokes in a plot area for its view to count as having drawn data (one line
across a plot: several hundred; an empty view: none)."""

TITLE_BAR_PX = 28
"""Height of a view's title bar, which `panel_ink` leaves out [px]."""
TAB_BAR_PX = 24
"""Height of a tabs container's bar of tab names, which draws no rule under it [px]."""

SETTLE_S = 3.0
"""A page counts as loaded when its screenshots have not changed for this long [s]."""

_KINDS = {1: "tabs", 2: "horizontal", 3: "vertical", 4: "grid"}
"""Rerun's ContainerKind values."""


class ViewerError(AssertionError):
    """The viewer or the browser did not come up, or did not show the recording in time."""


class LayoutNotFound(ViewerError):
    """A screenshot does not show the blueprint's layout (the viewer is still loading)."""


class Rect(NamedTuple):
    """A screenshot region [px]: columns x0..x1 - 1, rows y0..y1 - 1."""

    x0: int
    y0: int
    x1: int
    y1: int


# --- the recording's blueprint ---------------------------------------------------------------


@dataclass(frozen=True)
class View:
    """One view of a blueprint: its class ("2D", "TimeSeries", "TextLog", ...), title and
    origin, and its entity in the blueprint (`view/<uuid>`), which tells apart look-alikes."""

    kind: str
    name: str
    origin: str
    path: str


@dataclass(frozen=True)
class Container:
    """One container of a blueprint: "horizontal", "vertical", "grid" or "tabs", its visible
    children in order and their shares along its axis (none for a grid); its name, and for
    tabs the index of the active one among the children."""

    kind: str
    children: tuple["View | Container", ...]
    shares: tuple[float, ...] = ()
    name: str = ""
    active: int = 0

    def shown(self) -> tuple["View | Container", ...]:
        """The children the viewer shows: all of them, or a tabs container's active one."""
        return (self.children[self.active],) if self.kind == "tabs" else self.children

    def views(self, *, hidden: bool = False) -> list[View]:
        """Every view the viewer shows under this container (with `hidden`, also those of
        tabs not active), depth first, in the blueprint's order."""
        out = []
        for child in self.children if hidden else self.shown():
            out.extend(child.views(hidden=hidden) if isinstance(child, Container) else [child])
        return out


def blueprint_fields(rrd: Path) -> dict[str, dict[str, list]]:
    """The blueprint stored in `rrd` that the viewer opens with (the last sent): entity path
    (no leading /) -> component field -> the value its last row logged (a list: Rerun
    components are batches)."""
    reader = rr.chunk.RrdReader(Path(rrd))
    stores = reader.blueprints()
    if not stores:
        raise ViewerError(f"{rrd} holds no blueprint")
    fields: dict[str, dict[str, list]] = {}
    for chunk in reader.stream(store=max(stores, key=lambda s: _logged_at(reader, s))):
        batch = chunk.to_record_batch()
        entity = fields.setdefault(chunk.entity_path.strip("/"), {})
        for column in batch.schema.names:
            if ":" in column:  # "Archetype:field"; the rest are row ids and indexes
                values = [v for v in batch.column(column).to_pylist() if v is not None]
                if values:
                    entity[column.split(":", 1)[1]] = values[-1]
    return fields


def _logged_at(reader: rr.chunk.RrdReader, store) -> int:
    """When a blueprint store was made (its chunks' newest `log_time`): a recording that holds
    several opens on the one sent last (each is sent to be the active one)."""
    times = [
        max(chunk.to_record_batch().column("log_time").cast("int64").to_pylist())
        for chunk in reader.stream(store=store)
    ]
    return max(times)


def recorded_blueprint(rrd: Path) -> Container:
    """The root container of the blueprint stored in the recording `rrd`, the one its viewer
    starts with, down to its views."""
    fields = blueprint_fields(rrd)

    def one(path: str, field: str, default=None):
        value = fields.get(path, {}).get(field)
        return value[0] if value else default

    def build(path: str) -> "View | Container":
        if path not in fields:
            raise ViewerError(f"{rrd}: the blueprint names {path} but does not define it")
        if path.startswith("view/"):
            return View(
                kind=one(path, "class_identifier"),
                name=one(path, "display_name", ""),
                origin=one(path, "space_origin", ""),
                path=path,
            )
        kind = _KINDS[one(path, "container_kind")]
        contents = fields[path].get("contents") or []
        shown = [i for i, child in enumerate(contents) if one(child, "visible", True)]
        children = tuple(build(contents[i]) for i in shown)
        name = one(path, "display_name", "")
        if kind == "tabs":
            active = [contents[i] for i in shown].index(one(path, "active_tab", contents[0]))
            return Container(kind, children, name=name, active=active)
        if kind != "horizontal" and kind != "vertical":
            return Container(kind, children, name=name)
        given = fields[path].get("col_shares" if kind == "horizontal" else "row_shares") or []
        shares = tuple(given[i] if i < len(given) else 1.0 for i in shown)
        return Container(kind, children, shares, name=name)

    root = one("viewport", "root_container")
    if root is None:
        raise ViewerError(f"{rrd}: the blueprint has no root container")
    return build(f"container/{uuid.UUID(bytes=bytes(root))}")


# --- where the views are on a screenshot -----------------------------------------------------


def _rules_across(image: np.ndarray, colour: np.ndarray, rect: Rect, *, vertical: bool) -> list:
    """Positions of the one-pixel rules of `colour` that cross `rect` from side to side (97 %
    of their length; a neighbouring tile's own drawing may touch an end): columns if
    `vertical`, else rows, inside the rect's edges."""
    region = image[rect.y0 : rect.y1, rect.x0 : rect.x1]
    on = (region == colour).all(axis=-1).mean(axis=0 if vertical else 1) >= 0.97
    start = rect.x0 if vertical else rect.y0
    found: list[int] = []
    for i in np.flatnonzero(on):
        pos = start + int(i)
        if pos in (start, start + len(on) - 1):
            continue
        if found and pos == found[-1] + 1:
            continue  # the same rule, two pixels wide where it falls between pixels
        found.append(pos)
    return found


def _viewport(image: np.ndarray) -> tuple[Rect, np.ndarray]:
    """The viewer's viewport (where the blueprint's views are) and the colour of its rules."""
    height, width = image.shape[:2]
    rows = []
    for y in range(1, height - 1):
        colour = image[y, width // 2]
        line = (image[y - 1 : y + 2] == colour).all(axis=-1).mean(axis=1)
        if line[1] >= 0.98 and line[0] < 0.5 and line[2] < 0.5:
            rows.append((y, colour))
    if len(rows) < 2:
        raise LayoutNotFound("no top bar and time panel rules")
    (top, colour), (bottom, _) = rows[0], rows[1]
    band = Rect(0, top + 1, width, bottom)
    columns = _rules_across(image, colour, band, vertical=True)
    # A side panel's border, where the panel is open (a collapsed one leaves the views the
    # window's edge).
    left = columns[0] if columns and columns[0] < width // 4 else -1
    right = columns[-1] if columns and columns[-1] > 3 * width // 4 else width
    return Rect(left + 1, top + 1, right, bottom), colour


def _split(rect: Rect, cuts: list[int], *, vertical: bool) -> list[Rect]:
    """`rect` cut at the rules `cuts` (columns if `vertical`, else rows), rules left out."""
    lo, hi = (rect.x0, rect.x1) if vertical else (rect.y0, rect.y1)
    edges = [lo - 1, *cuts, hi]
    spans = [(a + 1, b) for a, b in zip(edges, edges[1:], strict=False)]
    if vertical:
        return [Rect(a, rect.y0, b, rect.y1) for a, b in spans]
    return [Rect(rect.x0, a, rect.x1, b) for a, b in spans]


def _place(image, colour, node, rect: Rect, out: dict) -> None:
    if isinstance(node, View):
        out[node] = rect
        return
    n = len(node.children)
    if node.kind == "tabs":  # (the active tab fills what its tab bar leaves)
        below = Rect(rect.x0, rect.y0 + TAB_BAR_PX, rect.x1, rect.y1)
        _place(image, colour, node.children[node.active], below, out)
        return
    if node.kind == "grid":
        cols = _rules_across(image, colour, rect, vertical=True)
        rows = _rules_across(image, colour, rect, vertical=False)
        ncols, nrows = len(cols) + 1, len(rows) + 1
        if not ncols * (nrows - 1) < n <= ncols * nrows:
            raise LayoutNotFound(f"{ncols} x {nrows} cells for a grid of {n} in {rect}")
        cells = [
            cell
            for band in _split(rect, rows, vertical=False)
            for cell in _split(band, cols, vertical=True)
        ]
        for child, cell in zip(node.children, cells, strict=False):
            _place(image, colour, child, cell, out)
        return
    vertical = node.kind == "horizontal"  # side by side: cut at columns
    lo, hi = (rect.x0, rect.x1) if vertical else (rect.y0, rect.y1)
    found = _rules_across(image, colour, rect, vertical=vertical)
    shares = np.asarray(node.shares, dtype=float)
    expected = lo + (hi - lo) * np.cumsum(shares)[:-1] / shares.sum()
    tolerance = max(12.0, 0.02 * (hi - lo))
    cuts = []
    for x in expected:
        near = [f for f in found if abs(f - x) <= tolerance]
        if not near:
            raise LayoutNotFound(f"no rule near {x:.0f} in {node.kind} container {rect}")
        cuts.append(min(near, key=lambda f, x=x: abs(f - x)))
    for child, part in zip(node.children, _split(rect, cuts, vertical=vertical), strict=True):
        _place(image, colour, child, part, out)


def locate_views(image: np.ndarray, blueprint: Container) -> dict[View, Rect]:
    """Where each view of `blueprint` is on `image` (H, W, 3 uint8 RGB) [px].

    Raises LayoutNotFound when the screenshot does not show the blueprint's tiles."""
    viewport, colour = _viewport(image)
    out: dict[View, Rect] = {}
    _place(image, colour, blueprint, viewport, out)
    return out


# --- what a view drew ------------------------------------------------------------------------


@dataclass(frozen=True)
class Ink:
    """The coloured pixels of a view's plot area: all of them, those in strokes (connected
    pieces bigger than a legend swatch, `MAX_SWATCH_PX` on both sides), and the share of the
    area's pixel columns the strokes reach."""

    pixels: int
    stroke_pixels: int
    spread: float

    @property
    def drawn(self) -> bool:
        """Whether the view drew data (see the module's docstring)."""
        return self.stroke_pixels >= MIN_STROKE_PX

    def __str__(self) -> str:
        return (
            f"{self.stroke_pixels} px in strokes ({self.pixels} coloured), "
            f"across {self.spread:.0%} of the width"
        )


def panel_ink(image: np.ndarray, rect: Rect) -> Ink:
    """The coloured pixels of the view at `rect` on `image`, its title bar and edges left out."""
    area = image[rect.y0 + TITLE_BAR_PX : rect.y1 - 3, rect.x0 + 3 : rect.x1 - 3].astype(np.int16)
    if area.size == 0:
        return Ink(0, 0, 0.0)
    coloured = (area.max(axis=-1) - area.min(axis=-1)) >= MIN_CHROMA
    pieces, _ = ndimage.label(coloured, structure=np.ones((3, 3), dtype=bool))
    strokes = np.zeros_like(coloured)
    for i, (rows, cols) in enumerate(ndimage.find_objects(pieces), start=1):
        if rows.stop - rows.start > MAX_SWATCH_PX or cols.stop - cols.start > MAX_SWATCH_PX:
            strokes[rows, cols] |= pieces[rows, cols] == i
    return Ink(int(coloured.sum()), int(strokes.sum()), float(strokes.any(axis=0).mean()))


# --- redraw after input ----------------------------------------------------------------------

FRAME_PROBE = r"""
(() => {
  // frames: [start, end, draw calls, picture] of every animation-frame callback [ms];
  // inputs: [type, timeStamp] of every pointer press and key press; read: hash the pictures.
  let draws = 0, gl = null, pixels = null;
  const probe = {frames: [], inputs: [], read: false};
  for (const cls of [window.WebGL2RenderingContext, window.WebGLRenderingContext]) {
    if (!cls) continue;
    for (const name of ["drawArrays", "drawElements", "drawArraysInstanced",
                        "drawElementsInstanced", "drawRangeElements"]) {
      const draw = cls.prototype[name];
      if (!draw) continue;
      cls.prototype[name] = function (...args) {
        draws += 1; gl = this; return draw.apply(this, args);
      };
    }
  }
  // What a drawn frame left on the canvas, as a number: a hash of its pixels, read back from
  // the drawing buffer before the browser shows it (the GL state the read needs is restored).
  const picture = () => {
    if (!gl || !(gl instanceof WebGL2RenderingContext)) return null;
    const w = gl.drawingBufferWidth, h = gl.drawingBufferHeight;
    if (!pixels || pixels.length !== w * h * 4) pixels = new Uint8Array(w * h * 4);
    const read = gl.getParameter(gl.READ_FRAMEBUFFER_BINDING);
    const pack = gl.getParameter(gl.PIXEL_PACK_BUFFER_BINDING);
    gl.bindFramebuffer(gl.READ_FRAMEBUFFER, null);
    gl.bindBuffer(gl.PIXEL_PACK_BUFFER, null);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, pixels);
    gl.bindBuffer(gl.PIXEL_PACK_BUFFER, pack);
    gl.bindFramebuffer(gl.READ_FRAMEBUFFER, read);
    const words = new Uint32Array(pixels.buffer);
    let hash = 2166136261;
    for (let i = 0; i < words.length; i++) hash = Math.imul(hash ^ words[i], 16777619);
    return hash >>> 0;
  };
  const request = window.requestAnimationFrame.bind(window);
  window.requestAnimationFrame = (callback) => request((t) => {
    const start = performance.now();
    draws = 0;
    try { callback(t); } finally {
      let seen = null;
      try { seen = draws && probe.read ? picture() : null; } catch (e) { seen = null; }
      probe.frames.push([start, performance.now(), draws, seen]);
    }
  });
  for (const type of ["pointerdown", "keydown"])
    window.addEventListener(type, (e) => probe.inputs.push([type, e.timeStamp]), true);
  window.__redrawProbe = probe;
})();
"""
"""Page script (`open_viewer(on_new_document=FRAME_PROBE)`) that times the viewer's frames.

The viewer asks for an animation frame every display frame, drawn or not, and draws (WebGL draw
calls) only in those where something changed, and sometimes draws again what it drew; the probe
notes each frame's start and end on the page's clock, its draw calls, and the time of every
pointer and key press. With ``__redrawProbe.read = true`` (`Viewer.read_pictures`) it also
notes a hash of the picture each drawn frame left, its pixels read back: that waits for the
software renderer to finish the frame, and slows the frames some threefold, so a redraw is
timed with it off."""

QUIET_S = 1.5
"""The viewer has redrawn what an input asked for when its frames have drawn nothing for this
long [s]."""
STEADY_FRAMES = 10
"""... and its last this many frames came at the display's rate (`STEADY_GAP_MS` apart at
most): the browser has shown every frame the viewer drew. Frames that draw nothing still wait
for the frame before them to be shown (most of a second each with software rendering), so a
page whose last drawn frame is 1.5 s old may still be showing it, and an input then waits."""
STEADY_GAP_MS = 50.0
"""Longest gap between two frames of a page at rest [ms] (a display frame is 16.7 ms)."""

REDRAW_TIMEOUT_S = 60.0
"""Longest wait for the viewer to stop drawing after an input [s]."""

TIME_SLIDER_Y = WINDOW[1] - 14
"""Row of the collapsed time panel's time slider [px] (the recording's blueprint collapses the
panel to one row at the window's foot)."""
TIME_SLIDER_X = (400, 1300)
"""Columns of the time slider that are safe to click [px], between its controls and its time
field."""


def _steady(starts: list[float]) -> bool:
    """Whether frames that began at `starts` [ms] came at the display's rate: `STEADY_FRAMES`
    of them, each within `STEADY_GAP_MS` of the one before."""
    gaps = np.diff(starts)
    return len(starts) == STEADY_FRAMES and bool(np.all(gaps <= STEADY_GAP_MS))


def scrub_points(count: int) -> list[tuple[int, int]]:
    """`count` points on the time slider, each far from the one before (alternately in its
    left and right halves), none twice."""
    lo, hi = TIME_SLIDER_X
    fractions = [0.5 + (-1) ** i * (0.1 + 0.35 * ((i * 0.618) % 1.0)) for i in range(count)]
    return [(round(lo + f * (hi - lo)), TIME_SLIDER_Y) for f in fractions]


@dataclass(frozen=True)
class Redraw:
    """What the viewer drew after one input: for each frame that drew, when it was on the
    screen [ms from the input's press, on the page's clock: the start of the second frame
    after it]; and, when the probe read the pictures (`Viewer.read_pictures`), whether each
    changed the picture (its hash differs from the frame drawn before it). The browser keeps
    one frame in flight: it may begin the next frame while the last drawn one is still being
    drawn, but not the one after (with software rendering a frame of the viewer takes most of
    a second, and that one begins that much later), so by then the frame is on the screen."""

    shown_ms: tuple[float, ...]
    changed: tuple[bool, ...] | None = None

    @property
    def drawn(self) -> int:
        return len(self.shown_ms)

    @property
    def first_ms(self) -> float:
        """When the input's effect is first on the screen."""
        return self.shown_ms[0] if self.shown_ms else 0.0

    @property
    def done_ms(self) -> float:
        """When the last frame that drew is on the screen."""
        return self.shown_ms[-1] if self.shown_ms else 0.0

    def final_ms(self, changed: tuple[bool, ...] | None) -> float:
        """The redraw time: when the last frame that changed the picture is on the screen
        (from then on the screen shows what the redraw settles on), as `changed` says (the
        `changed` of another redraw of the same input, whose pictures were read while this
        one was timed); without it, `done_ms`."""
        if not self.shown_ms or changed is None:
            return self.done_ms
        last = max((i for i, c in enumerate(changed) if c), default=0)
        return self.shown_ms[min(last, len(self.shown_ms) - 1)]

    def __str__(self) -> str:
        changes = "" if self.changed is None else f", {sum(self.changed)} changed the picture"
        return (
            f"{self.done_ms:.0f} ms, first {self.first_ms:.0f} ms"
            f" ({self.drawn} frames drawn{changes})"
        )


# --- Chromium over the DevTools protocol -----------------------------------------------------


class _WebSocket:
    """A WebSocket client, as much as the DevTools protocol needs: text frames out (masked),
    text frames in (possibly fragmented, possibly megabytes: screenshots), no extensions."""

    def __init__(self, url: str, *, timeout_s: float = 60.0) -> None:
        parts = urllib.parse.urlsplit(url)
        if parts.scheme != "ws" or parts.hostname != "127.0.0.1":
            raise ViewerError(f"not a loopback WebSocket: {url}")
        self._sock = socket.create_connection((parts.hostname, parts.port), timeout=timeout_s)
        key = base64.b64encode(os.urandom(16)).decode()
        self._sock.sendall(
            (
                f"GET {parts.path} HTTP/1.1\r\nHost: {parts.netloc}\r\n"
                "Upgrade: websocket\r\nConnection: Upgrade\r\n"
                f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
            ).encode()
        )
        self._buf = b""
        while b"\r\n\r\n" not in self._buf:
            self._fill()
        head, self._buf = self._buf.split(b"\r\n\r\n", 1)
        if b" 101 " not in head.split(b"\r\n", 1)[0]:
            raise ViewerError(f"WebSocket handshake refused: {head[:200]!r}")

    def _fill(self) -> None:
        data = self._sock.recv(1 << 20)
        if not data:
            raise ViewerError("the browser closed its DevTools connection")
        self._buf += data

    def _take(self, n: int) -> bytes:
        while len(self._buf) < n:
            self._fill()
        out, self._buf = self._buf[:n], self._buf[n:]
        return out

    def send(self, text: str) -> None:
        data = text.encode()
        n = len(data)
        if n < 126:
            head = struct.pack(">BB", 0x81, 0x80 | n)
        elif n < 1 << 16:
            head = struct.pack(">BBH", 0x81, 0x80 | 126, n)
        else:
            head = struct.pack(">BBQ", 0x81, 0x80 | 127, n)
        mask = os.urandom(4)
        masked = (
            np.frombuffer(data, np.uint8) ^ np.resize(np.frombuffer(mask, np.uint8), n)
        ).tobytes()
        self._sock.sendall(head + mask + masked)

    def receive(self) -> str:
        parts = []
        while True:
            first, second = self._take(2)
            n = second & 0x7F
            if n == 126:
                (n,) = struct.unpack(">H", self._take(2))
            elif n == 127:
                (n,) = struct.unpack(">Q", self._take(8))
            payload = self._take(n)
            opcode = first & 0x0F
            if opcode == 0x8:
                raise ViewerError("the browser closed its DevTools connection")
            if opcode in (0x9, 0xA):  # ping, pong: Chromium sends none unasked
                continue
            parts.append(payload)
            if first & 0x80:
                return b"".join(parts).decode()

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._sock.close()


class _DevTools:
    """One page's DevTools session: commands and their results; the events that come between
    are kept when `keep` names their method."""

    def __init__(self, url: str, *, keep: tuple[str, ...] = (), timeout_s: float = 60.0) -> None:
        self._ws = _WebSocket(url, timeout_s=timeout_s)
        self._next = 0
        self._keep = keep
        self.events: list[dict] = []

    def call(self, method: str, **params) -> dict:
        self._next += 1
        self._ws.send(json.dumps({"id": self._next, "method": method, "params": params}))
        while True:
            message = json.loads(self._ws.receive())
            if message.get("id") == self._next:
                if "error" in message:
                    raise ViewerError(f"{method}: {message['error']}")
                return message.get("result", {})
            if message.get("method") in self._keep:
                self.events.append(message)

    def wait_for_event(self, method: str, *, timeout_s: float) -> dict:
        """The next event `method` (kept events before it are kept, others dropped)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            message = json.loads(self._ws.receive())
            if message.get("method") == method:
                return message
            if message.get("method") in self._keep:
                self.events.append(message)
        raise ViewerError(f"no {method} within {timeout_s:g} s")

    def close(self) -> None:
        self._ws.close()


def rerun_binary() -> Path:
    """The viewer executable of the installed rerun-sdk (the `rerun` script starts it as a
    child; started directly, its PID is the viewer's own)."""
    import rerun_cli

    return Path(rerun_cli.__file__).parent / "rerun"


def _home_env(home: Path) -> dict[str, str]:
    """HOME and the XDG folders under it (a user's settings, data and caches go there)."""
    home.mkdir(parents=True, exist_ok=True)
    return {
        "HOME": str(home),
        "XDG_CONFIG_HOME": str(home / ".config"),
        "XDG_DATA_HOME": str(home / ".local" / "share"),
        "XDG_CACHE_HOME": str(home / ".cache"),
    }


def rerun_home(home: Path) -> dict[str, str]:
    """Environment for Rerun with `home` as HOME, Rerun's usage analytics disabled there (they
    are on by default); the variables to set."""
    env = _home_env(home)
    done = subprocess.run(
        [str(rerun_binary()), "analytics", "disable"],
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=60,
    )
    config = home / ".config" / "rerun" / "analytics.json"
    if done.returncode != 0 or json.loads(config.read_text()).get("analytics_enabled", True):
        raise ViewerError(f"rerun analytics disable failed:\n{done.stdout}\n{done.stderr}")
    return env


@dataclass
class Viewer:
    """A recording open in the web viewer in headless Chromium (see `open_viewer`)."""

    url: str
    devtools: _DevTools
    shots: Path

    def screenshot(self) -> np.ndarray:
        """The page as it is now: (H, W, 3) uint8 RGB."""
        data = base64.b64decode(self.devtools.call("Page.captureScreenshot", format="png")["data"])
        return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))

    def settle(self, blueprint: Container, *, timeout_s: float = 90.0) -> tuple[np.ndarray, dict]:
        """The first screenshot that shows `blueprint`'s layout and stays unchanged for
        `SETTLE_S`, with the views located on it; ViewerError after `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        last, since = None, time.monotonic()
        while True:
            image = self.screenshot()
            now = time.monotonic()
            if last is None or not np.array_equal(image, last):
                last, since = image, now
            elif now - since >= SETTLE_S:
                with contextlib.suppress(LayoutNotFound):
                    return image, locate_views(image, blueprint)
            if now > deadline:
                path = self.save(image, "unsettled")
                try:
                    locate_views(image, blueprint)
                except LayoutNotFound as e:
                    raise ViewerError(f"no layout after {timeout_s:g} s ({e}); see {path}") from e
                raise ViewerError(f"the page kept changing for {timeout_s:g} s; see {path}")
            time.sleep(0.25)

    def evaluate(self, expression: str):
        """The value of a JavaScript expression in the page."""
        answer = self.devtools.call("Runtime.evaluate", expression=expression, returnByValue=True)
        if "exceptionDetails" in answer:
            raise ViewerError(f"{expression}: {answer['exceptionDetails']}")
        return answer["result"].get("value")

    def click(self, x: int, y: int) -> None:
        """A left click at (x, y) [px], as the mouse would: press, release."""
        for kind in ("mousePressed", "mouseReleased"):
            self.devtools.call(
                "Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", clickCount=1
            )

    def press(self, key: str, code: str, key_code: int, text: str = "") -> None:
        """A key pressed and released (`key`, `code`: the DOM's names; `key_code`: Windows's)."""
        for kind in ("keyDown", "keyUp"):
            extra = {"text": text} if text and kind == "keyDown" else {}
            self.devtools.call(
                "Input.dispatchKeyEvent",
                type=kind, key=key, code=code, windowsVirtualKeyCode=key_code, **extra,
            )  # fmt: skip

    def _frames(self, since: int) -> list[tuple[float, float, int]]:
        return self.evaluate(f"__redrawProbe.frames.slice({since})")

    def idle(self, *, after_ms: float = 0.0, timeout_s: float = REDRAW_TIMEOUT_S) -> int:
        """Wait until the viewer has gone `QUIET_S` of frames without drawing, counted from
        `after_ms` on the page's clock at the earliest (frames, not the clock: while a frame
        takes long to draw, the browser begins none), and its frames come at the display's
        rate again (`STEADY_FRAMES`); the probe's frame count then. Needs `FRAME_PROBE` in the
        page."""
        deadline = time.monotonic() + timeout_s
        while True:
            count = self.evaluate("__redrawProbe.frames.length")
            frames = self._frames(max(0, count - 600))  # the last 10 s
            drawn = [f[1] for f in frames if f[2]]
            quiet = frames and frames[-1][0] - max([after_ms, *drawn]) >= QUIET_S * 1000.0
            if quiet and _steady([f[0] for f in frames[-STEADY_FRAMES:]]):
                return count
            if time.monotonic() > deadline:
                raise ViewerError(f"the viewer kept drawing for {timeout_s:g} s")
            time.sleep(0.2)

    def redraw_after(self, act, *, timeout_s: float = REDRAW_TIMEOUT_S) -> Redraw:
        """Run `act()` (an input: `click`, `press`) on an idle viewer, wait until the viewer
        has drawn nothing for `QUIET_S`, and say how long its redraw took (`Redraw`). Needs
        `FRAME_PROBE` in the page."""
        since = self.idle(timeout_s=timeout_s)
        pressed_before = self.evaluate("__redrawProbe.inputs.length")
        act()
        presses = self.evaluate(f"__redrawProbe.inputs.slice({pressed_before})")
        if not presses:
            raise ViewerError("the page saw no input")
        t0 = presses[0][1]
        self.idle(after_ms=t0, timeout_s=timeout_s)
        frames = self._frames(max(0, since - 600))
        before = [f[3] for f in frames if f[2] and f[1] < t0]
        frames = [f for f in frames if f[1] >= t0]
        drew = [i for i, f in enumerate(frames) if f[2]]
        shown = tuple(frames[i + 1 : i + 3][-1][0] - t0 for i in drew)  # (quiet frames: 2+)
        pictures = [before[-1] if before else None] + [frames[i][3] for i in drew]
        if None in pictures[1:]:
            return Redraw(shown)
        return Redraw(shown, tuple(a != b for a, b in zip(pictures, pictures[1:], strict=False)))

    def read_pictures(self, on: bool) -> None:
        """Have `FRAME_PROBE` hash each drawn frame's picture (slow), or stop."""
        self.evaluate(f"__redrawProbe.read = {'true' if on else 'false'}")

    def save(self, image: np.ndarray, name: str) -> Path:
        """Write `image` as ``<shots>/<name>.png``; its path."""
        self.shots.mkdir(parents=True, exist_ok=True)
        path = self.shots / f"{name}.png"
        Image.fromarray(image).save(path)
        return path

    def off_loopback(self, *, answered: bool) -> list[str]:
        """URLs off this machine that the page asked for (`answered`: that answered it)."""
        method, part = (
            ("Network.responseReceived", "response")
            if answered
            else ("Network.requestWillBeSent", "request")
        )
        urls = {e["params"][part]["url"] for e in self.devtools.events if e["method"] == method}
        return sorted(url for url in urls if _off_loopback(url))


def _off_loopback(url: str) -> bool:
    parts = urllib.parse.urlsplit(url)
    return parts.scheme in ("http", "https", "ws", "wss") and parts.hostname not in _LOOPBACK


_LOOPBACK = ("127.0.0.1", "localhost", "::1")


_CHROMIUM_FLAGS = (
    "--headless=new",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--no-sandbox",
    "--remote-debugging-address=127.0.0.1",
    "--remote-debugging-port=0",
    f"--window-size={WINDOW[0]},{WINDOW[1]}",
    "--hide-scrollbars",
    "--mute-audio",
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-extensions",
    "--disable-sync",
    "--disable-default-apps",
    "--disable-breakpad",
    "--disable-component-update",
    "--disable-background-networking",
    "--disable-domain-reliability",
    "--metrics-recording-only",
    "--disable-crash-reporter",
    "--host-resolver-rules=MAP * ~NOTFOUND , EXCLUDE 127.0.0.1",
)


def _wait_for(predicate, *, timeout_s: float, what: str, log: Path, proc) -> None:
    """Poll `predicate` until it holds; ViewerError, with the end of `log`, should the process
    `proc` (a Popen) exit first or `timeout_s` pass."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if proc.poll() is not None:
            raise ViewerError(f"{what}: exited ({proc.returncode})\n{log.read_text()[-3000:]}")
        if time.monotonic() > deadline:
            raise ViewerError(f"{what}: not up after {timeout_s:g} s\n{log.read_text()[-3000:]}")
        time.sleep(0.05)


def _close_browser(port: int, path: str) -> None:
    """Ask the browser to quit (it then takes its helper processes down with it)."""
    with contextlib.suppress(ViewerError, OSError):
        browser = _DevTools(f"ws://127.0.0.1:{port}{path}", timeout_s=10.0)
        try:
            browser.call("Browser.close")
        finally:
            browser.close()


def _kill_naming(text: str, *, timeout_s: float = 10.0) -> None:
    """SIGKILL, by PID, every process whose command line names `text`; wait until they are
    gone (or only zombies)."""
    deadline = time.monotonic() + timeout_s
    while (left := live_processes_naming(text)) and time.monotonic() < deadline:
        for pid, _ in left:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        time.sleep(0.1)


@contextlib.contextmanager
def open_viewer(
    rrd: Path, workdir: Path, env: dict[str, str], *, on_new_document: str = ""
) -> Iterator[Viewer]:
    """Serve `rrd` with the web viewer on free loopback ports and open it in headless Chromium.

    `env`: from `rerun_home`, for the viewer. The browser gets a HOME of its own in `workdir`,
    where its profile, the logs and the screenshots `Viewer.save` writes go too, so that every
    process it starts (helpers, crash handler) names `workdir` on its command line. On the way
    out, also when the body raises, the browser is asked to quit, then the viewer and the
    browser are stopped by PID, then whatever still names `workdir` is killed by PID.
    """
    if CHROMIUM is None:
        raise ViewerError("chromium is not installed")
    workdir = Path(workdir).resolve()
    workdir.mkdir(parents=True, exist_ok=True)
    group = ProcessGroup(workdir / "logs")
    page, browser_endpoint = None, None
    try:
        grpc_port = free_port_block([0, 1], kinds=(socket.SOCK_STREAM,))
        web_port = grpc_port + 1
        rerun = group.start(
            "rerun",
            [
                str(rerun_binary()), str(rrd), "--serve-web", "--bind", "127.0.0.1",
                "--port", str(grpc_port), "--web-viewer-port", str(web_port),
            ],
            env=env,
        )  # fmt: skip
        _wait_for(
            lambda: "Hosting a web-viewer" in rerun.out() + rerun.err(),
            timeout_s=30.0, what="rerun --serve-web", log=rerun.err_path, proc=rerun.proc,
        )  # fmt: skip
        profile = workdir / "chromium-profile"
        active = profile / "DevToolsActivePort"
        active.unlink(missing_ok=True)  # a browser before this one, on the same profile
        # Whatever the page asks of a host other than loopback goes to a port nobody listens on.
        dead_proxy = free_port_block([0], kinds=(socket.SOCK_STREAM,))
        chromium = group.start(
            "chromium",
            [
                CHROMIUM, *_CHROMIUM_FLAGS, f"--user-data-dir={profile}",
                f"--proxy-server=http://127.0.0.1:{dead_proxy}", "about:blank",
            ],
            env=_home_env(workdir / "browser-home"),
        )  # fmt: skip
        _wait_for(
            lambda: active.exists() and len(active.read_text().split()) >= 2,
            timeout_s=30.0, what="chromium", log=chromium.err_path, proc=chromium.proc,
        )  # fmt: skip
        port, path = active.read_text().split()[:2]
        browser_endpoint = (int(port), path)
        direct = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # no *_proxy
        with direct.open(f"http://127.0.0.1:{port}/json/list", timeout=10) as answer:
            pages = [t for t in json.load(answer) if t.get("type") == "page"]
        page = _DevTools(
            pages[0]["webSocketDebuggerUrl"],
            keep=("Network.requestWillBeSent", "Network.responseReceived"),
        )
        page.call("Network.enable")
        page.call("Page.enable")
        page.call(
            "Emulation.setDeviceMetricsOverride",
            width=WINDOW[0], height=WINDOW[1], deviceScaleFactor=1, mobile=False,
        )  # fmt: skip
        page.call(
            "Emulation.setEmulatedMedia",
            features=[{"name": "prefers-color-scheme", "value": "light"}],
        )
        if on_new_document:
            page.call("Page.addScriptToEvaluateOnNewDocument", source=on_new_document)
        proxy = urllib.parse.quote(f"rerun+http://127.0.0.1:{grpc_port}/proxy", safe="")
        url = f"http://127.0.0.1:{web_port}/?url={proxy}"
        page.call("Page.navigate", url=url)
        page.wait_for_event("Page.loadEventFired", timeout_s=60.0)
        yield Viewer(url, page, workdir / "screenshots")
    finally:
        if page is not None:
            page.close()
        if browser_endpoint is not None:
            _close_browser(*browser_endpoint)
            with contextlib.suppress(subprocess.TimeoutExpired):
                group["chromium"].proc.wait(timeout=10.0)
        group.stop_all()
        _kill_naming(str(workdir))
