"""The PNG previews of ``traffictwin fuse`` and ``traffictwin twin``: mass maps side by side in
the report's colour map, each panel titled, the colour legend below."""

from __future__ import annotations

import math

import numpy as np

#: pixels of a preview's panels (24 MB as BGR): the upscaling to ~384 px tall stops there, and
#: panels beyond it at scale 1 are subsampled (a 1 x 4096 map asked for a 384x upscale: 17.6 GB)
MAX_PREVIEW_PIXELS = 8_000_000
PREVIEW_HEIGHT = 384  # px the panels are upscaled towards
_STRIPS = 24 + 22  # px rows of the title strip and the colour legend below the panels


def mass_panels(
    panels: list[tuple[np.ndarray, np.ndarray | None]], titles: list[str] | None = None
) -> np.ndarray:
    """BGR uint8 image of mass maps side by side, white separators, upscaled to ~384 px tall
    within :data:`MAX_PREVIEW_PIXELS` (every ``step``-th cell when even scale 1 exceeds it),
    the colour map's legend below: each panel ``(masses (2, H, W), u (H, W) or None = 1 - m_free -
    m_occ)``; the report's colour map (:mod:`traffictwin.report.colours`: green = free,
    red = occupied, grey = unknown, mixtures in between). With ``titles`` (one per panel, ASCII:
    OpenCV's Hershey font), a white strip above the panels carries each panel's title, centred
    over it (font shrunk, then the text shortened with ``..``, to fit the panel's width)."""
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
    rows = [img, legend_strip_bgr8(img.shape[1])]
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
    return np.concatenate(rows, axis=0)


def preview_scale(shapes: list[tuple[int, int]]) -> tuple[int, int]:
    """``(scale, step)`` of panels of ``shapes`` (rows, cols) side by side: the upscale towards
    :data:`PREVIEW_HEIGHT` px tall, at most what keeps the whole image (panels, separators, the
    title and legend strips) within :data:`MAX_PREVIEW_PIXELS`; ``step`` > 1 takes every
    ``step``-th cell of panels that exceed it at scale 1."""
    h = max(1, max(s[0] for s in shapes))
    w = sum(max(1, s[1]) for s in shapes)
    seps = 4 * (len(shapes) - 1)

    def pixels(scale: int, step: int) -> int:
        rows = -(-h // step) * scale + _STRIPS
        cols = (sum(-(-max(1, s[1]) // step) for s in shapes) + seps) * scale
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


def preview_image(m1: np.ndarray, m2w: np.ndarray, m: np.ndarray, u: np.ndarray) -> np.ndarray:
    """BGR uint8 preview: map 1 | map 2 moved into map 1's frame by the given poses | the fused
    map (its ``u`` = the grey), each titled, the colour legend below (:func:`mass_panels`)."""
    return mass_panels(
        [(m1, None), (m2w, None), (m, u)],
        titles=["map 1", "map 2 in map 1's frame", "fused (grey = uncertainty u)"],
    )


def twin_preview(twin: np.ndarray, contributions: list[np.ndarray]) -> np.ndarray:
    """BGR uint8 preview: the twin | each vehicle's map where the twin put it, titled by the
    maps' order on the command line (map 1 the reference), the colour legend below
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
    return mass_panels([(twin, None), *((c, None) for c in contributions)], titles=titles)
