"""The PNG previews of ``traffictwin fuse`` and ``traffictwin twin``: mass maps side by side in
the report's colour map, each panel titled, with axes in metres of the reference vehicle's frame,
the reference vehicle (ego) marked, and a legend below that names every colour drawn."""

from __future__ import annotations

import math

import numpy as np

#: pixels of a preview's panels (24 MB as BGR): the upscaling to ~384 px tall stops there, and
#: panels beyond it at scale 1 are subsampled (a 1 x 4096 map asked for a 384x upscale: 17.6 GB)
MAX_PREVIEW_PIXELS = 8_000_000
PREVIEW_HEIGHT = 384  # px the panels are upscaled towards
LEGEND_H = 22  # px of one row of the colour legend
AXIS_H, AXIS_W = 18, 40  # px of the metre axis strips below and left of the panels
#: px rows beside the panels at most: the title strip, the metre axis and two legend rows
_STRIPS = 24 + AXIS_H + 2 * LEGEND_H
EGO_BGR = (200, 90, 0)  # the ego marker's colour (blue): no mass colour is blue


def mass_panels(
    panels: list[tuple[np.ndarray, np.ndarray | None]],
    titles: list[str] | None = None,
    *,
    cell: float | None = None,
    ego: bool = False,
) -> np.ndarray:
    """BGR uint8 image of mass maps side by side, white separators, upscaled to ~384 px tall
    within :data:`MAX_PREVIEW_PIXELS` (every ``step``-th cell when even scale 1 exceeds it),
    the colour map's legend below: each panel ``(masses (2, H, W), u (H, W) or None = 1 - m_free -
    m_occ)``; the report's colour map (:mod:`traffictwin.report.colours`: green = free,
    red = occupied, grey = unknown, mixtures in between). With ``titles`` (one per panel, ASCII:
    OpenCV's Hershey font), a white strip above the panels carries each panel's title, centred
    over it (font shrunk, then the text shortened with ``..``, to fit the panel's width).

    ``cell`` (m per cell) adds axes in metres of the grid's own frame (x forward = up, y left =
    left, the sensor at the centre: :mod:`traffictwin.grid`): ticks under each panel and left of
    them. ``ego`` marks the grid's centre (the reference vehicle, facing up) in every panel. With
    either, the legend also names the mixed colours (and the ego marker)."""
    import cv2

    from traffictwin.report.colours import legend_strip_bgr8, masses_to_bgr8

    if titles is not None and len(titles) != len(panels):
        raise ValueError(f"mass_panels: {len(titles)} titles for {len(panels)} panels")
    scale, step = preview_scale([p[0].shape[1:] for p in panels])
    if step > 1:
        panels = [
            (m[:, ::step, ::step], None if u is None else u[::step, ::step]) for m, u in panels
        ]
    h = panels[0][0].shape[1]
    sep_w = 4 * scale
    parts, widths = [], []
    for k, (mm, uu) in enumerate(panels):
        rgb = masses_to_bgr8(mm, uu)
        parts.append(np.repeat(np.repeat(rgb, scale, axis=0), scale, axis=1) if scale > 1 else rgb)
        widths.append(parts[-1].shape[1])
        if k < len(panels) - 1:
            parts.append(np.full((h * scale, sep_w, 3), 255, np.uint8))
    img = np.concatenate(parts, axis=1)
    if ego:
        x0 = 0
        for w in widths:
            _draw_ego(img, x0 + w // 2, h * scale // 2, max(14, 5 * scale))
            x0 += w + sep_w
    if cell is not None:
        img = np.concatenate([img, _y_axis_strip(widths, sep_w, cell * step, scale)])
    if cell is not None or ego:
        legend = _full_legend(img.shape[1] + (AXIS_W if cell is not None else 0), ego)
    else:
        legend = legend_strip_bgr8(img.shape[1])
    rows = [img, legend]
    if titles is not None:
        font, height = cv2.FONT_HERSHEY_SIMPLEX, 24
        strip = np.full((height, img.shape[1], 3), 255, np.uint8)
        x0 = 0
        for title, w in zip(titles, widths):
            text, size = str(title), 0.5

            def fits(t: str, f: float, w: int = w) -> bool:
                return cv2.getTextSize(t, font, f, 1)[0][0] <= w - 4

            while size > 0.35 and not fits(text, size):
                size -= 0.05
            while len(text) > 3 and not fits(text, size):
                text = text[:-3].rstrip() + ".."
            (tw, th), _ = cv2.getTextSize(text, font, size, 1)
            org = (x0 + max(0, (w - tw) // 2), (height + th) // 2)
            cv2.putText(strip, text, org, font, size, (0, 0, 0), 1, cv2.LINE_AA)
            x0 += w + sep_w
        rows.insert(0, strip)
    if cell is not None:  # the x axis left of the titles, panels and y axis
        above = np.concatenate(rows[:-1], axis=0)
        top = above.shape[0] - img.shape[0]  # the title strip's rows
        left = _x_axis_strip(above.shape[0], top, h, cell * step, scale)
        rows = [np.concatenate([left, above], axis=1), rows[-1]]
    return np.concatenate(rows, axis=0)


def _nice_step(extent_m: float, length_px: int, min_px: int = 56) -> float:
    """A tick spacing (m) of 1, 2 or 5 times a power of ten with ticks at least ``min_px`` apart
    over ``extent_m`` metres drawn ``length_px`` pixels long."""
    need = extent_m * min_px / max(1, length_px)
    k = 10.0 ** math.floor(math.log10(max(need, 1e-9)))
    return next(m * k for m in (1, 2, 5, 10) if m * k >= need)


def _ticks(half_m: float, step_m: float) -> np.ndarray:
    """Multiples of ``step_m`` within ``[-half_m, half_m]`` (m)."""
    n = math.floor(half_m / step_m + 1e-9)
    return np.arange(-n, n + 1) * step_m


def _y_axis_strip(widths: list[int], sep_w: int, cell: float, scale: int) -> np.ndarray:
    """White strip ``(AXIS_H, panels' width, 3)``: under each panel (``widths`` px, ``sep_w`` px
    apart), the ticks and labels of y (m, left positive: the sensor at 0, the panel's left edge
    at +W/2); ``cell`` m per cell drawn ``scale`` px wide."""
    import cv2

    strip = np.full((AXIS_H, sum(widths) + sep_w * (len(widths) - 1), 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    x0 = 0
    for w in widths:
        half = w / scale * cell / 2  # m from the sensor to the panel's side
        for y in _ticks(half, _nice_step(2 * half, w)):
            px = min(max(x0 + int(round((half - y) / cell * scale)), x0), x0 + w - 1)
            cv2.line(strip, (px, 0), (px, 3), (0, 0, 0), 1)
            text = f"{y:g}"
            tw = cv2.getTextSize(text, font, 0.35, 1)[0][0]
            org = (min(max(px - tw // 2, x0), x0 + w - tw), AXIS_H - 4)
            cv2.putText(strip, text, org, font, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
        x0 += w + sep_w
    return strip


def _x_axis_strip(height: int, top: int, rows: int, cell: float, scale: int) -> np.ndarray:
    """White strip ``(height, AXIS_W, 3)`` left of the panels (which start ``top`` px down and are
    ``rows`` cells of ``cell`` m, ``scale`` px each): the ticks and labels of x (m, forward = up,
    the sensor at 0), and the units (``x,y m``) in the corner beside the y axis."""
    import cv2

    strip = np.full((height, AXIS_W, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    px_h = rows * scale
    half = rows * cell / 2
    for x in _ticks(half, _nice_step(2 * half, px_h, min_px=32)):
        py = top + min(max(int(round((half - x) / cell * scale)), 0), px_h - 1)
        cv2.line(strip, (AXIS_W - 4, py), (AXIS_W - 1, py), (0, 0, 0), 1)
        text = f"{x:g}"
        tw, th = cv2.getTextSize(text, font, 0.35, 1)[0]
        org = (AXIS_W - 6 - tw, min(max(py + th // 2, top + th), top + px_h - 1))
        cv2.putText(strip, text, org, font, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    corner = (1, min(height - 4, top + px_h + AXIS_H - 4))
    cv2.putText(strip, "x,y m", corner, font, 0.33, (0, 0, 0), 1, cv2.LINE_AA)
    return strip


def _draw_ego(img: np.ndarray, cx: int, cy: int, size: int) -> None:
    """Draw the ego marker into ``img``: a blue triangle pointing up (forward), white-edged,
    centred on pixel ``(cx, cy)``, ``size`` px tall."""
    import cv2

    half = max(3, size // 2)
    side = half * 2 // 3
    pts = np.array([[cx, cy - half], [cx - side, cy + half], [cx + side, cy + half]], np.int32)
    cv2.fillPoly(img, [pts], EGO_BGR, lineType=cv2.LINE_AA)
    cv2.polylines(img, [pts], True, (255, 255, 255), 1, cv2.LINE_AA)


def _full_legend(width: int, ego: bool) -> np.ndarray:
    """The legend of a preview with axes or ego: the three pure colours, a swatch of the mixtures
    (left to right free to occupied through olive, downwards more unknown: the colours cells
    between the pure ones take) and, with ``ego``, the ego marker; the entries wrap onto a
    second row when one row of ``width`` px is too narrow."""
    import cv2

    from traffictwin.report.colours import LEGEND, masses_to_bgr8

    font, size, pad = cv2.FONT_HERSHEY_SIMPLEX, 0.4, 4
    sw = LEGEND_H - 2 * pad  # a swatch's height (px)
    occ = np.linspace(0.0, 1.0, 2 * sw)[None, :]
    unk = np.linspace(0.0, 0.8, sw)[:, None]
    mix = masses_to_bgr8(np.stack([(1 - occ) * (1 - unk), occ * (1 - unk)]))
    entries: list[tuple[str, np.ndarray | None]] = [
        (label, np.full((sw, sw, 3), np.round(c[::-1] * 255), np.uint8)) for label, c in LEGEND
    ]
    entries.append(("mixed by mass (olive = free + occupied)", mix))
    if ego:
        entries.append(("ego: map 1's vehicle, facing +x", None))
    placed, x, row = [], pad, 0
    for label, swatch in entries:
        sw_w = sw if swatch is None else swatch.shape[1]
        need = sw_w + 4 + cv2.getTextSize(label, font, size, 1)[0][0] + 12
        if x > pad and x + need > width and row == 0:
            x, row = pad, 1
        placed.append((x, row, label, swatch, sw_w))
        x += need
    strip = np.full((LEGEND_H * (row + 1), max(1, width), 3), 255, np.uint8)
    for x, r, label, swatch, sw_w in placed:
        y = r * LEGEND_H + pad
        if swatch is None:
            _draw_ego(strip, x + sw // 2, y + sw // 2, sw)
        else:
            part = swatch[:, : max(0, min(sw_w, strip.shape[1] - x))]
            strip[y : y + sw, x : x + part.shape[1]] = part
        org = (x + sw_w + 4, (r + 1) * LEGEND_H - pad - 1)
        cv2.putText(strip, label, org, font, size, (0, 0, 0), 1, cv2.LINE_AA)
    return strip


def preview_scale(shapes: list[tuple[int, int]]) -> tuple[int, int]:
    """``(scale, step)`` of panels of ``shapes`` (rows, cols) side by side: the upscale towards
    :data:`PREVIEW_HEIGHT` px tall, at most what keeps the whole image (panels, separators, the
    title, axis and legend strips) within :data:`MAX_PREVIEW_PIXELS`; ``step`` > 1 takes every
    ``step``-th cell of panels that exceed it at scale 1."""
    h = max(1, max(s[0] for s in shapes))
    w = sum(max(1, s[1]) for s in shapes)
    seps = 4 * (len(shapes) - 1)

    def pixels(scale: int, step: int) -> int:
        rows = -(-h // step) * scale + _STRIPS
        cols = (sum(-(-max(1, s[1]) // step) for s in shapes) + seps) * scale + AXIS_W
        return rows * cols

    scale, step = max(1, int(round(PREVIEW_HEIGHT / h))), 1
    if pixels(1, 1) > MAX_PREVIEW_PIXELS:
        step = max(1, math.isqrt(h * w // MAX_PREVIEW_PIXELS))
        while pixels(1, step) > MAX_PREVIEW_PIXELS:
            step += 1
        return 1, step
    # largest scale within the budget: rows and cols grow linearly in it (a quadratic's root)
    a = h * (w + seps)
    b = _STRIPS * (w + seps)
    fit = int((-b + math.sqrt(b * b + 4 * a * MAX_PREVIEW_PIXELS)) / (2 * a))
    while fit > 1 and pixels(fit, 1) > MAX_PREVIEW_PIXELS:
        fit -= 1
    return max(1, min(scale, fit)), step


def preview_image(
    m1: np.ndarray, m2w: np.ndarray, m: np.ndarray, u: np.ndarray, cell: float | None = None
) -> np.ndarray:
    """BGR uint8 preview: map 1 | map 2 moved into map 1's frame by the given poses | the fused
    map (its ``u`` = the grey), each titled, map 1's vehicle marked, axes in metres of map 1's
    frame (``cell`` m per cell; none without it), the colour legend below (:func:`mass_panels`)."""
    return mass_panels(
        [(m1, None), (m2w, None), (m, u)],
        titles=["map 1", "map 2 in map 1's frame", "fused (grey = uncertainty u)"],
        cell=cell,
        ego=True,
    )


def twin_preview(
    twin: np.ndarray, contributions: list[np.ndarray], cell: float | None = None
) -> np.ndarray:
    """BGR uint8 preview: the twin | each vehicle's map where the twin put it, titled by the
    maps' order on the command line (map 1 the reference), map 1's vehicle marked, axes in metres
    of map 1's frame (``cell`` m per cell; none without it), the colour legend below
    (:func:`mass_panels`); a left-out map is passed as all zeros (grey = unknown) and titled
    so."""
    titles = ["twin (the maps fused)"]
    for k, c in enumerate(contributions):
        if k == 0:
            titles.append("map 1 (reference)")
        elif not np.any(c):
            titles.append(f"map {k + 1}: left out")
        else:
            titles.append(f"map {k + 1} where the twin put it")
    panels = [(twin, None), *((c, None) for c in contributions)]
    return mass_panels(panels, titles=titles, cell=cell, ego=True)
