"""Inline SVG drawing for the report page: time-series line charts and a fixed oblique 3D view.

Everything returns an ``<svg>`` string (no external references); NaN values break a line.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from html import escape

import numpy as np

# A perceptually ordered colour map (dark blue -> green -> yellow), sampled at 6 stops.
_CMAP = np.array(
    [(68, 1, 84), (65, 68, 135), (42, 120, 142), (34, 168, 132), (122, 209, 81), (253, 231, 37)], dtype=float
)


def colormaps(xs: np.ndarray) -> list[str]:
    """Colours for values ``xs`` in [0, 1] (clipped) as ``#rrggbb``, all at once."""
    return _colour_words(xs).tobytes().decode("ascii").split("\0")[:-1]


_HEX = np.frombuffer(b"0123456789abcdef", np.uint8)


def _colour_words(xs: np.ndarray) -> np.ndarray:
    """`colormaps`' colours as `_text` takes them: (n, 1) words of ASCII codes, ``#rrggbb`` and a NUL."""
    x = np.clip(np.asarray(xs, dtype=float), 0.0, 1.0) * (len(_CMAP) - 1)
    i = np.minimum(x.astype(int), len(_CMAP) - 2)
    c = _CMAP[i] + (x - i)[:, None] * (_CMAP[i + 1] - _CMAP[i])
    rgb = np.round(c).astype(int) @ np.array([1 << 16, 1 << 8, 1])  # (each 0..255: 0xrrggbb)
    chars = np.zeros((len(x), 8), np.uint8)
    chars[:, 0] = ord("#")
    chars[:, 1:7] = _HEX[rgb[:, None] >> np.arange(20, -1, -4) & 15]  # (six hex digits, as '%06x')
    return chars.view(np.uint64)


def colormap(x: float) -> str:
    """Colour for ``x`` in [0, 1] as ``#rrggbb``."""
    return colormaps(np.array([float(x)]))[0]


def nice_ticks(lo: float, hi: float, target: int = 5) -> list[float]:
    """Round tick values covering [lo, hi]."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo]
    raw = (hi - lo) / max(target, 1)
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    start = math.ceil(lo / step - 1e-9) * step
    return [round(start + i * step, 10) for i in range(int((hi - start) / step + 1e-9) + 1)]


def _fmt_tick(v: float) -> str:
    return f"{v:.0f}" if abs(v) >= 10 or float(v).is_integer() else f"{v:.2f}".rstrip("0").rstrip(".")


def downsample(n: int, max_points: int = 800) -> np.ndarray:
    """Indices of at most ``max_points`` evenly spread samples, first and last included."""
    if n <= max_points:
        return np.arange(n)
    idx = np.linspace(0, n - 1, max_points).round().astype(int)  # (non-decreasing: its repeats adjacent)
    return idx[np.concatenate(([True], idx[1:] != idx[:-1]))]


@dataclass(frozen=True)
class Series:
    """One line of a chart: values against the chart's time axis."""

    label: str
    values: np.ndarray
    colour: str
    dashed: bool = False


@dataclass(frozen=True)
class Band:
    """A shaded time interval (a fault window), [start_s, end_s]."""

    start_s: float
    end_s: float
    label: str


@dataclass(frozen=True)
class Chart:
    """A line chart over sim time."""

    title: str
    unit: str
    t_s: np.ndarray
    series: Sequence[Series]
    marks: Sequence[tuple[float, str]] = ()  # vertical lines (time_s, label)
    bands: Sequence[Band] = ()
    hlines: Sequence[tuple[float, str]] = field(default_factory=tuple)  # horizontal lines (value, label)
    width: int = 600
    height: int = 210
    min_span: float = 0.0  # the value axis covers at least this much (so noise does not fill the chart)


def _path(xs: np.ndarray, ys: np.ndarray) -> str:
    """An SVG path through the points; a point that is not finite lifts the pen."""
    ok = np.isfinite(xs) & np.isfinite(ys)
    if not ok.any():
        return ""
    # each run of finite points, one line: M at its first point, L before each of the others
    first = ok & ~np.concatenate(([False], ok[:-1]))
    x, y = _tenths(np.array((xs[ok], ys[ok])))
    return _text([_ahead(np.where(first[ok], ord("M"), ord("L")), x), _ahead(",", y)])


#: the tenths `_tenths` writes from its table: 0.0 to 999.9 (a report's coordinates, in its viewBoxes)
_TABLE_TENTHS = 10_000


@functools.cache
def _tenths_table() -> np.ndarray:
    """``'%.1f'`` of t/10 for 0 <= t < `_TABLE_TENTHS`, then of -t/10 for the same t: a uint64 word
    each, its ASCII codes in order, NUL before (a byte free for `_ahead`) and after (made once, by
    numpy)."""
    t = np.arange(_TABLE_TENTHS)
    whole = t // 10
    chars = np.zeros((2, _TABLE_TENTHS, 8), np.uint8)
    chars[1, :, 1] = ord("-")
    for k, shown in ((2, whole >= 100), (3, whole >= 10), (4, True)):  # hundreds, tens, units
        chars[:, :, k] = np.where(shown, ord("0") + whole // 10 ** (4 - k) % 10, 0)
    chars[:, :, 5] = ord(".")
    chars[:, :, 6] = ord("0") + t % 10
    return chars.reshape(-1, 8).view(np.uint64).ravel()


def _tenths(values: np.ndarray) -> np.ndarray:
    """Each value with one decimal as ``'%.1f'`` writes it, all at once (a call a value took most of a
    report's time): ``values.shape + (w,)`` uint64 words of ASCII codes in order, NULs (nothing) about
    the text (`_text` drops them).

    ``'%.1f'`` rounds the value's exact binary expansion to tenths, a tie (x.25, x.75) to even. Here
    the product ten times the value is rounded to an integer; a product that lands on a half (rare) is
    decided by its rounding error, found exactly (a sum of the exact 8 and 2 times the value). Tenths
    from the table (values below 999.9 in size: a report's coordinates); any other value (not finite,
    larger) written by ``'%.1f'`` itself."""
    v = np.asarray(values, dtype=float)
    a = np.abs(v)
    if not (v.size and a.max() < _TABLE_TENTHS / 10 - 0.1):  # (NaN: not below)
        text = np.array([f"{x:.1f}".encode() for x in v.ravel().tolist()] + [b""])[:-1]
        words = -(-text.itemsize // 8)
        return text.astype(f"S{8 * words}").view(np.uint64).reshape((*v.shape, words))
    y = a * 10.0
    tenths = np.rint(y)
    tie = np.abs(y - tenths) == 0.5
    if tie.any():
        p, q = a * 8.0, a * 2.0  # (exact; y is their sum rounded)
        back = y - p
        err = (p - (y - back)) + (q - back)  # 10 a = y + err exactly
        tenths = np.where(tie & (err > 0), np.ceil(y), np.where(tie & (err < 0), np.floor(y), tenths))
    index = tenths.astype(np.intp) + np.signbit(v) * _TABLE_TENTHS
    return _tenths_table()[index][..., None]


def _text(parts: Sequence[str | np.ndarray]) -> str:
    """Rows of text, all at once: each row the parts in turn, a str the same in every row, an (n, w)
    array of uint64 words (ASCII codes in order, NUL: nothing) a row's own."""
    n = next(len(p) for p in parts if not isinstance(p, str))
    words = [np.frombuffer(p.encode().ljust(-(-len(p) // 8) * 8, b"\0"), np.uint64) if isinstance(p, str)
             else p for p in parts]
    out = np.empty((n, sum(w.shape[-1] for w in words)), np.uint64)
    at = 0
    for w in words:
        out[:, at : at + w.shape[-1]] = w
        at += w.shape[-1]
    return out.tobytes().translate(None, b"\0").decode("ascii")


def _ahead(char: str | np.ndarray, words: np.ndarray) -> np.ndarray:
    """``words`` (n, w) with a character before each row's text, ``char`` or each row's ASCII code
    (n,): in the row's first byte where every row leaves it free (a number from `_tenths`' table),
    else in a word of its own."""
    code = ord(char) if isinstance(char, str) else char
    out = np.array(words, dtype=np.uint64)  # (a copy, contiguous)
    if out.view(np.uint8)[:, 0].any():
        out = np.hstack((np.zeros((len(out), 1), np.uint64), out))
    out.view(np.uint8)[:, 0] = code
    return out


def _points(xy: np.ndarray, sep: str) -> str:
    """The points ``xy`` (n, 2) as x,y with one decimal each, the character ``sep`` between them."""
    c = _tenths(xy)
    return _text([_ahead(sep, c[:, 0]), _ahead(",", c[:, 1])])[1:]


def line_chart(chart: Chart) -> str:
    """An SVG line chart with axes, ticks, legend, shaded bands and vertical marks."""
    w, h = chart.width, chart.height
    left, right, top, bottom = 52, 12, 26, 30
    pw, ph = w - left - right, h - top - bottom
    t = np.asarray(chart.t_s, dtype=float)
    idx = downsample(len(t))
    t = t[idx]
    ys = [np.asarray(s.values, dtype=float)[idx] for s in chart.series]
    finite = [y[np.isfinite(y)] for y in ys] + [np.array([v for v, _ in chart.hlines], dtype=float)]
    allv = np.concatenate(finite) if finite else np.array([])
    if allv.size == 0:
        lo, hi = 0.0, 1.0
    else:
        lo, hi = float(allv.min()), float(allv.max())
        if hi - lo < chart.min_span:
            mid = (hi + lo) / 2
            lo, hi = mid - chart.min_span / 2, mid + chart.min_span / 2
        pad = 0.08 * (hi - lo) if hi > lo else max(abs(hi) * 0.1, 1.0)
        lo, hi = lo - pad, hi + pad
    t0, t1 = (float(t[0]), float(t[-1])) if len(t) else (0.0, 1.0)
    if t1 <= t0:
        t1 = t0 + 1.0

    # (a float in, a float out: a tick's or a mark's place in plain float arithmetic, the same operations
    # numpy does on the series' arrays)
    def sx(v: np.ndarray | float) -> np.ndarray | float:
        return left + (v - t0) / (t1 - t0) * pw

    def sy(v: np.ndarray | float) -> np.ndarray | float:
        return top + (hi - v) / (hi - lo) * ph

    out = [f'<svg class="chart" viewBox="0 0 {w} {h}" width="{w}" height="{h}" role="img">']
    out.append(f"<title>{escape(chart.title)}</title>")
    out.append(
        f'<text x="{left}" y="16" class="ct">{escape(chart.title)}'
        f"{' (' + escape(chart.unit) + ')' if chart.unit else ''}</text>"
    )
    for band in chart.bands:
        b0, b1 = max(band.start_s, t0), min(band.end_s, t1)
        if b1 > b0:
            out.append(
                f'<rect x="{sx(b0):.1f}" y="{top}" width="{float(sx(b1)) - float(sx(b0)):.1f}" '
                f'height="{ph}" class="band"><title>{escape(band.label)}</title></rect>'
            )
    out.append(f'<rect x="{left}" y="{top}" width="{pw}" height="{ph}" class="frame"/>')
    for v in nice_ticks(lo, hi):
        y = float(sy(v))
        out.append(f'<line x1="{left}" x2="{left + pw}" y1="{y:.1f}" y2="{y:.1f}" class="grid"/>')
        out.append(f'<text x="{left - 5}" y="{y + 4:.1f}" class="tk" text-anchor="end">{_fmt_tick(v)}</text>')
    for v in nice_ticks(t0, t1, 8):
        x = float(sx(v))
        out.append(f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{top}" y2="{top + ph}" class="grid"/>')
        out.append(
            f'<text x="{x:.1f}" y="{top + ph + 14}" class="tk" text-anchor="middle">{_fmt_tick(v)}</text>'
        )
    out.append(f'<text x="{left + pw}" y="{h - 2}" class="tk" text-anchor="end">sim time (s)</text>')
    for value, label in chart.hlines:
        y = float(sy(value))
        out.append(
            f'<line x1="{left}" x2="{left + pw}" y1="{y:.1f}" y2="{y:.1f}" class="hline">'
            f"<title>{escape(label)}</title></line>"
        )
    for time_s, label in chart.marks:
        if t0 <= time_s <= t1:
            x = float(sx(time_s))
            out.append(f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{top}" y2="{top + ph}" class="mark"/>')
            out.append(f'<text x="{x + 3:.1f}" y="{top + 10}" class="mk">{escape(label)}</text>')
    xs = np.asarray(sx(t), dtype=float)
    for s, y in zip(chart.series, ys, strict=True):
        d = _path(xs, np.asarray(sy(y), dtype=float))
        if d:
            dash = ' stroke-dasharray="5 3"' if s.dashed else ""
            out.append(f'<path d="{d}" fill="none" stroke="{s.colour}" stroke-width="1.6"{dash}/>')
    lx = left + pw
    for s in reversed(chart.series):
        label = escape(s.label)
        lx -= 18 + 7.0 * len(s.label) + 14
        dash = ' stroke-dasharray="5 3"' if s.dashed else ""
        out.append(
            f'<line x1="{lx:.0f}" x2="{lx + 14:.0f}" y1="12" y2="12" stroke="{s.colour}" '
            f'stroke-width="2"{dash}/><text x="{lx + 18:.0f}" y="16" class="lg">{label}</text>'
        )
    out.append("</svg>")
    return "".join(out)


# --- the 3D view ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class View:
    """An orthographic camera: azimuth and elevation of the direction towards the viewer (rad)."""

    azimuth_rad: float
    elevation_rad: float

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(right, up, towards-viewer) unit vectors in world ENU (read-only; made once a view)."""
        return self._axes

    @functools.cached_property
    def _axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a, e = self.azimuth_rad, self.elevation_rad
        tx, ty, tz = math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)
        rx, ry = -math.sin(a), math.cos(a)
        # up = towards x right, term by term as np.cross computes it (the same bits; right has no z)
        up = np.array([ty * 0.0 - tz * ry, tz * rx - tx * 0.0, tx * ry - ty * rx])
        axes = np.array([rx, ry, 0.0]), up, np.array([tx, ty, tz])
        for v in axes:
            v.flags.writeable = False
        return axes

    def project(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Screen (x right, y up) and depth (towards the viewer) of world points (N, 3)."""
        right, up, towards = self._axes
        p = np.atleast_2d(np.asarray(pts, dtype=float))
        xy = np.empty((len(p), 2))
        xy[:, 0], xy[:, 1] = p @ right, p @ up
        return xy, p @ towards


@dataclass(frozen=True)
class Scene:
    """What the 3D view shows (world ENU, m)."""

    gap_centre_m: np.ndarray
    gap_rotation: np.ndarray  # R: columns e1 (crossing), e0 (long side), -e2 (short side)
    gap_width_m: float
    gap_height_m: float
    lab_min_m: np.ndarray
    lab_max_m: np.ndarray
    pos_m: np.ndarray  # (N, 3) trajectory
    speed_m_s: np.ndarray  # (N,)
    crossing_m: np.ndarray | None = None
    wall_width_m: float = 4.0  # along e0
    wall_height_m: float = 4.0  # along e2

    def gap_corners(self) -> np.ndarray:
        """The opening's four corners (4, 3)."""
        e0, e2 = self.gap_rotation[:, 1], self.gap_rotation[:, 2]
        hw, hh = self.gap_width_m / 2, self.gap_height_m / 2
        c = self.gap_centre_m
        return np.array(
            [c + hw * e0 + hh * e2, c - hw * e0 + hh * e2, c - hw * e0 - hh * e2, c + hw * e0 - hh * e2]
        )

    @functools.cached_property
    def drawn(self) -> tuple[np.ndarray, np.ndarray, float]:
        """The trajectory as every view draws it: the indices of its points drawn (at most 700, finite),
        their colours by speed (``#rrggbb``: (n, 1) words of ASCII codes, as `_text` takes them) and the
        speed of the scale's top (m/s)."""
        pos = np.asarray(self.pos_m, dtype=float)
        ok = np.all(np.isfinite(pos), axis=1)
        idx = downsample(len(pos), 700)
        idx = idx[ok[idx]]
        speed = np.asarray(self.speed_m_s, dtype=float)
        vmax = float(np.nanmax(speed)) if np.any(np.isfinite(speed)) else 1.0
        vmax = max(vmax, 1e-6)
        return idx, _colour_words(speed[idx] / vmax), vmax

    def wall_corners(self) -> np.ndarray:
        """The wall's four corners: a rectangle in the gap's plane, sides along e0 and e2 (4, 3)."""
        e0, e2 = self.gap_rotation[:, 1], self.gap_rotation[:, 2]
        hw, hh = self.wall_width_m / 2, self.wall_height_m / 2
        c = self.gap_centre_m
        return np.array(
            [c + hw * e0 + hh * e2, c - hw * e0 + hh * e2, c - hw * e0 - hh * e2, c + hw * e0 - hh * e2]
        )


def scene_svg(
    scene: Scene, view: View, title: str, width: int = 620, height: int = 460, legend: bool = True
) -> str:
    """The trajectory through the wall's opening, seen by ``view``; coloured by speed."""
    pos = np.asarray(scene.pos_m, dtype=float)
    idx, colours, vmax = scene.drawn
    # the floor shown: the lab's floor cut to 1 m around the trajectory and the wall
    wall, gap = scene.wall_corners(), scene.gap_corners()
    seen = np.vstack([wall, pos[idx]]) if len(idx) else wall
    lab_lo = np.maximum(scene.lab_min_m, np.floor(seen.min(axis=0)) - 1.0)
    lab_hi = np.minimum(scene.lab_max_m, np.ceil(seen.max(axis=0)) + 1.0)
    lab_hi = np.maximum(lab_hi, lab_lo + 1e-3)
    floor = np.array(
        [
            [lab_lo[0], lab_lo[1], 0.0],
            [lab_hi[0], lab_lo[1], 0.0],
            [lab_hi[0], lab_hi[1], 0.0],
            [lab_lo[0], lab_hi[1], 0.0],
        ]
    )
    floor[:, 2] = max(lab_lo[2], 0.0)
    everything = np.vstack([floor, wall, pos[idx] if len(idx) else floor])
    xy_all, _ = view.project(everything)
    lo, hi = xy_all.min(axis=0), xy_all.max(axis=0)
    margin = 28
    scale = min(
        (width - 2 * margin) / max(hi[0] - lo[0], 1e-6), (height - 2 * margin - 20) / max(hi[1] - lo[1], 1e-6)
    )
    ox = (width - scale * (hi[0] - lo[0])) / 2
    oy = (height - 20 - scale * (hi[1] - lo[1])) / 2 + 20
    x0, y0 = lo

    def to_screen(points: np.ndarray) -> np.ndarray:
        xy, _ = view.project(points)
        xy[:, 0], xy[:, 1] = ox + (xy[:, 0] - x0) * scale, height - (oy + (xy[:, 1] - y0) * scale) + 20
        return xy

    def poly(points: np.ndarray) -> str:
        return _points(to_screen(points), " ")

    out = [
        f'<svg class="scene" viewBox="0 0 {width} {height}" width="{width}" height="{height}" role="img">',
        f"<title>{escape(title)}</title>",
        f'<text x="10" y="16" class="ct">{escape(title)}</text>',
    ]
    # floor grid (1 m) inside the lab
    out.append(f'<polygon points="{poly(floor)}" class="floor"/>')
    z0 = floor[0, 2]
    lines = [[[gx, lab_lo[1], z0], [gx, lab_hi[1], z0]]
             for gx in np.arange(math.ceil(lab_lo[0]), math.floor(lab_hi[0]) + 1)]
    lines += [[[lab_lo[0], gy, z0], [lab_hi[0], gy, z0]]
              for gy in np.arange(math.ceil(lab_lo[1]), math.floor(lab_hi[1]) + 1)]
    if lines:  # (all the grid's ends projected at once, a line's two points each)
        ends = _tenths(to_screen(np.array(lines).reshape(-1, 3)).reshape(-1, 4))
        out.append(_text(['<polyline points="', ends[:, 0], _ahead(",", ends[:, 1]), _ahead(" ", ends[:, 2]),
                          _ahead(",", ends[:, 3]), '" class="fgrid"/>']))
    # the trajectory's shadow on the floor
    if len(idx) > 1:
        shadow = pos[idx].copy()
        shadow[:, 2] = z0
        out.append(f'<polyline points="{poly(shadow)}" class="shadow"/>')
    # wall with the opening (even-odd fill leaves the hole), then the trajectory in two halves
    # (behind / in front of the wall as seen by the viewer) so the wall hides what it should.
    e1 = scene.gap_rotation[:, 0]
    opening = poly(gap)
    wall_path = f'<path d="M{poly(wall)}Z M{opening}Z" fill-rule="evenodd" class="wall"/>'
    gap_outline = f'<polygon points="{opening}" class="gapedge"/>'
    _, _, towards = view.axes()
    side = (pos[idx] - scene.gap_centre_m) @ e1 if len(idx) else np.array([])
    viewer_side = 1.0 if float(e1 @ towards) > 0 else -1.0
    in_front = side * viewer_side > 0
    screen = to_screen(pos[idx]) if len(idx) else np.zeros((0, 2))
    point = _tenths(screen)  # (each point's x, y as text once: a point ends two segments)
    ends = np.concatenate([point[:-1], point[1:]], axis=1)  # each segment's (x0, y0, x1, y1)

    def segments(front: bool) -> str:
        """The trajectory's segments with an end on the ``front`` side, a line each."""
        drawn = np.flatnonzero((in_front[:-1] == front) | (in_front[1:] == front))
        if not len(drawn):
            return ""
        e = ends[drawn]
        return _text(['<line x1="', e[:, 0], '" y1="', e[:, 1], '" x2="', e[:, 2], '" y2="', e[:, 3],
                      '" stroke="', colours[drawn], '" class="traj"/>'])

    out += [segments(front=False), wall_path, gap_outline, segments(front=True)]
    if len(idx):
        (sx0, sy0), (ex, ey) = screen[0], screen[-1]
        out.append(f'<circle cx="{sx0:.1f}" cy="{sy0:.1f}" r="6" class="start"><title>start</title></circle>')
        out.append(
            f'<rect x="{ex - 5:.1f}" y="{ey - 5:.1f}" width="10" height="10" class="end">'
            "<title>end</title></rect>"
        )
        out.append(f'<text x="{sx0 + 9:.1f}" y="{sy0 + 4:.1f}" class="lbl">start</text>')
        out.append(f'<text x="{ex + 9:.1f}" y="{ey + 4:.1f}" class="lbl">end</text>')
    if scene.crossing_m is not None and np.all(np.isfinite(scene.crossing_m)):
        ((cx, cy),) = to_screen(np.asarray(scene.crossing_m, dtype=float)[None, :])
        star = " ".join(
            f"{cx + r * math.sin(k * math.pi / 5):.1f},{cy - r * math.cos(k * math.pi / 5):.1f}"
            for k, r in zip(range(10), [9, 4] * 5, strict=True)
        )
        out.append(f'<polygon points="{star}" class="cross"><title>gap crossing</title></polygon>')
    # world axes at the lab's corner
    origin = np.array([lab_lo[0], lab_lo[1], z0])
    for k, (name, colour) in enumerate((("x", "#c0392b"), ("y", "#27ae60"), ("z", "#2c6fbb"))):
        tip = origin.copy()
        tip[k] += 1.0
        (ax0, ay0), (ax1, ay1) = to_screen(np.vstack([origin, tip]))
        out.append(
            f'<line x1="{ax0:.1f}" y1="{ay0:.1f}" x2="{ax1:.1f}" y2="{ay1:.1f}" stroke="{colour}" '
            f'stroke-width="2.5"/><text x="{ax1 + 3:.1f}" y="{ay1 + 4:.1f}" class="lbl" '
            f'fill="{colour}">{name}</text>'
        )
    if legend:
        bx, by = width - 190, height - 22
        for k, colour in enumerate(colormaps(np.arange(40) / 39)):
            out.append(f'<rect x="{bx + 3 * k}" y="{by}" width="3.2" height="9" fill="{colour}"/>')
        out.append(f'<text x="{bx - 6}" y="{by + 8}" class="tk" text-anchor="end">speed 0</text>')
        out.append(f'<text x="{bx + 124}" y="{by + 8}" class="tk">{vmax:.1f} m/s</text>')
    out.append("</svg>")
    return "".join(out)
