"""Pictures of the board in an attitude, drawn from the attitude's rotation: an SVG for the
station page (imubench.station) and a few lines of text for the terminal.

    board_rotation(up)        R (board -> world, world Z up) that puts board direction `up` up
    board_svg(up, size_px)    SVG: board outline, its connector (rear, −X edge), X/Y/Z arrows, floor
    board_text(up)            the same as characters (a small drawing for the terminal)
    turn_svg(axis, rate_dps)  a turntable step: the board, the axis and the direction of the turn

Geometry in board units: the board is 1.0 long (X, forward), 0.7 wide (Y, left), 0.08 thick;
the connector sits on its −X edge (docs/conventions.md). Seen from the front-right, above,
with an orthographic camera; faces are painted back to front.
"""
from __future__ import annotations

import math

import numpy as np

_L, _W, _T = 1.0, 0.7, 0.08
_CAM_AZ_DEG, _CAM_EL_DEG = -55.0, 22.0
_AXIS_COLOURS = {"X": "#d62728", "Y": "#2ca02c", "Z": "#1f77b4"}


def board_rotation(up) -> np.ndarray:
    """Rotation matrix R (world = R @ board) that turns the board so that its direction `up`
    (the measured gravity direction, board frame) points to world +Z, with the least rotation
    from lying level (so X stays forward as far as it can); upside down turns about X."""
    d = np.asarray(up, dtype=float)
    d = d / np.linalg.norm(d)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(d, z)
    s, c = np.linalg.norm(axis), float(d @ z)
    if s < 1e-9:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    th = math.atan2(s, c)
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


def _camera():
    az, el = math.radians(_CAM_AZ_DEG), math.radians(_CAM_EL_DEG)
    towards = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    right = np.cross([0.0, 0.0, 1.0], towards)
    right /= np.linalg.norm(right)
    upv = np.cross(towards, right)
    return towards, right, upv


def _box(lo, hi):
    """Faces of an axis-aligned box (board frame) as (corner list, outward normal, role)."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    P = lambda x, y, z: np.array([x, y, z], float)  # noqa: E731
    return [
        ([P(x0, y0, z1), P(x1, y0, z1), P(x1, y1, z1), P(x0, y1, z1)], np.array([0, 0, 1.0]), "top"),
        ([P(x0, y0, z0), P(x0, y1, z0), P(x1, y1, z0), P(x1, y0, z0)], np.array([0, 0, -1.0]), "bottom"),
        ([P(x1, y0, z0), P(x1, y1, z0), P(x1, y1, z1), P(x1, y0, z1)], np.array([1.0, 0, 0]), "side"),
        ([P(x0, y0, z0), P(x0, y0, z1), P(x0, y1, z1), P(x0, y1, z0)], np.array([-1.0, 0, 0]), "side"),
        ([P(x0, y1, z0), P(x0, y1, z1), P(x1, y1, z1), P(x1, y1, z0)], np.array([0, 1.0, 0]), "side"),
        ([P(x0, y0, z0), P(x1, y0, z0), P(x1, y0, z1), P(x0, y0, z1)], np.array([0, -1.0, 0]), "side"),
    ]


def _scene(up):
    """Visible faces (screen polygon, depth, role) back to front, the arrows (screen tip,
    label, depth of the tip) and the floor line's screen y, for the board with `up` up."""
    R = board_rotation(up)
    towards, right, upv = _camera()

    def scr(p):
        w = R @ p
        return np.array([w @ right, -(w @ upv)]), float(w @ towards)

    faces = []
    parts = [(_box((-_L / 2, -_W / 2, -_T / 2), (_L / 2, _W / 2, _T / 2)), "board"),
             (_box((-_L / 2 - 0.09, -0.16, -_T / 2 + 0.01), (-_L / 2 + 0.04, 0.16, _T / 2 + 0.09)), "connector")]
    for box, part in parts:
        for corners, normal, role in box:
            if (R @ normal) @ towards <= 1e-6:
                continue                       # faces away from the camera
            pts = [scr(c) for c in corners]
            depth = float(np.mean([d for _, d in pts]))
            faces.append((np.array([p for p, _ in pts]), depth, role if part == "board" else "connector"))
    faces.sort(key=lambda f: f[1])             # far first
    arrows = []
    for i, name in enumerate("XYZ"):
        e = np.zeros(3)
        e[i] = 1.0
        length = 0.85 if name != "Z" else 0.6
        tip, depth = scr(e * length)
        arrows.append((tip, name, depth))
    # the floor: below the lowest point of the board
    corners = np.array([[sx * _L / 2, sy * _W / 2, sz * _T / 2] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    lowest = min(float((R @ c)[2]) for c in corners)
    return faces, arrows, lowest, R


_FILL = {"top": "#3d8f5a", "bottom": "#2b5e3c", "side": "#1f3f2a", "connector": "#c9a227"}


def board_svg(up, size_px: int = 160, title: str | None = None) -> str:
    """An SVG (a string) of the board with board direction `up` pointing up: the board (top
    side green with a white chip mark at its centre, bottom side darker), the connector (gold,
    rear edge), X/Y/Z arrows (red/green/blue, labelled) and the floor under it."""
    faces, arrows, lowest, R = _scene(up)
    towards, right, upv = _camera()
    s = size_px / 2.6
    cx, cy = size_px / 2, size_px / 2 - 0.05 * size_px

    def xy(p):
        return f"{cx + s * p[0]:.1f},{cy + s * p[1]:.1f}"

    out = [f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {size_px} {size_px}" width="{size_px}" '
           f'height="{size_px}" class="board" role="img">']
    if title:
        out.append(f"<title>{_esc(title)}</title>")
    out.append('<defs>' + "".join(
        f'<marker id="ah{n}" viewBox="0 0 10 10" refX="8" refY="5" markerWidth="5" markerHeight="5" '
        f'orient="auto-start-reverse"><path d="M0,0 L10,5 L0,10 z" fill="{c}"/></marker>'
        for n, c in _AXIS_COLOURS.items()) + '</defs>')
    # floor: an ellipse (a shadow) under the board, at the board's lowest point
    fy = cy + s * (-(lowest * upv[2]))
    out.append(f'<ellipse cx="{cx:.1f}" cy="{fy + 6:.1f}" rx="{0.42 * size_px:.1f}" ry="{0.07 * size_px:.1f}" '
               f'fill="#cfd4da" opacity="0.7"/>')
    out.append(f'<text x="{size_px - 4}" y="{size_px - 4}" font-size="{size_px / 14:.0f}" text-anchor="end" '
               f'fill="#6b7280">floor</text>')
    origin = f"{cx:.1f},{cy:.1f}"
    behind = [a for a in arrows if a[2] < 0]
    front = [a for a in arrows if a[2] >= 0]
    for tip, name, _ in behind:
        out.append(_arrow(origin, xy(tip), tip, name, cx, cy, s, size_px, dashed=True))
    for pts, _, role in faces:
        out.append(f'<polygon points="{" ".join(xy(p) for p in pts)}" fill="{_FILL[role]}" stroke="#0f172a" '
                   f'stroke-width="1" stroke-linejoin="round"/>')
        if role == "top":      # the chip on the top side, so top and bottom differ at a glance
            c = pts.mean(axis=0)
            q = [c + 0.28 * (p - c) for p in pts]
            out.append(f'<polygon points="{" ".join(xy(p) for p in q)}" fill="#e5e7eb" stroke="#111827" '
                       f'stroke-width="0.8"/>')
    for tip, name, _ in front:
        out.append(_arrow(origin, xy(tip), tip, name, cx, cy, s, size_px, dashed=False))
    out.append("</svg>")
    return "".join(out)


def _arrow(origin, tip_xy, tip, name, cx, cy, s, size_px, dashed) -> str:
    c = _AXIS_COLOURS[name]
    dash = ' stroke-dasharray="4 3" opacity="0.75"' if dashed else ""
    tx, ty = cx + s * tip[0] * 1.18, cy + s * tip[1] * 1.18
    return (f'<line x1="{origin.split(",")[0]}" y1="{origin.split(",")[1]}" x2="{tip_xy.split(",")[0]}" '
            f'y2="{tip_xy.split(",")[1]}" stroke="{c}" stroke-width="2.2" marker-end="url(#ah{name})"{dash}/>'
            f'<text x="{tx:.1f}" y="{ty + 4:.1f}" font-size="{size_px / 10:.0f}" font-weight="bold" fill="{c}" '
            f'text-anchor="middle" font-family="sans-serif">{name}</text>')


def turn_svg(axis, rate_dps: float | None = None, angle_deg: float | None = None, size_px: int = 160) -> str:
    """A turn step: the board level with the turn axis drawn through it and a curved arrow
    showing the direction (right-hand rule), labelled with the rate or angle."""
    axis = np.asarray(axis, float)
    axis = axis / np.linalg.norm(axis)
    up = axis if axis[2] >= -0.5 else -axis          # the axis about which it turns points up
    base = board_svg(up, size_px)
    sign = 1.0 if (rate_dps or angle_deg or 1.0) >= 0 else -1.0
    sign *= 1.0 if np.allclose(up, axis) else -1.0
    cx, cy = size_px / 2, size_px * 0.24
    r = size_px * 0.2
    sweep = 1 if sign < 0 else 0                     # counter-clockwise seen from above: + about up
    label = f"{rate_dps:+.0f} °/s" if rate_dps is not None else f"{angle_deg:+.0f}°" if angle_deg is not None else ""
    name = "XYZ"[int(np.argmax(np.abs(axis)))]
    arc = (f'<path d="M{cx - r:.1f},{cy:.1f} A{r:.1f},{r * 0.4:.1f} 0 1 {sweep} {cx + r:.1f},{cy:.1f}" fill="none" '
           f'stroke="#7c3aed" stroke-width="2.5" marker-end="url(#ahturn)"/>'
           f'<defs><marker id="ahturn" viewBox="0 0 10 10" refX="8" refY="5" markerWidth="5" markerHeight="5" '
           f'orient="auto-start-reverse"><path d="M0,0 L10,5 L0,10 z" fill="#7c3aed"/></marker></defs>'
           f'<text x="4" y="{size_px - 4:.1f}" font-size="{size_px / 11:.0f}" text-anchor="start" '
           f'fill="#7c3aed" font-family="sans-serif">about {name}: {label}</text>')
    return base.replace("</svg>", arc + "</svg>")


def _esc(s: str) -> str:
    return s.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace('"', "&quot;")


# ------------------------------------------------------------------------- terminal
_CHARS = {"top": "#", "bottom": "%", "side": ":", "connector": "@"}


def board_text(up, width: int = 32, height: int = 13) -> str:
    """The board drawn in characters (width x height cells, a cell twice as high as wide):
    '#' top side (chip side), '%' bottom side, ':' edges, '@' the connector, X/Y/Z at the
    tips of the axes, and the floor '‾' under it."""
    faces, arrows, lowest, R = _scene(up)
    _, _, upv = _camera()
    grid = [[" "] * width for _ in range(height)]
    sx = width / 2.8
    sy = sx / 2.0                                    # a cell is about twice as high as wide
    cx, cy = width / 2, (height - 2) / 2

    def cell(p):
        return cx + sx * p[0], cy + sy * p[1]

    for pts, _, role in faces:
        poly = [cell(p) for p in pts]
        for r in range(height):
            for c in range(width):
                if _inside(c + 0.5, r + 0.5, poly):
                    grid[r][c] = _CHARS[role]
    for tip, name, depth in arrows:
        x, y = cell(tip * 1.15)
        c, r = int(round(x)), int(round(y))
        if 0 <= r < height and 0 <= c < width:
            grid[r][c] = name if depth >= 0 else name.lower()
    drawn = [r for r in range(height) if any(ch in "#%:@" for ch in grid[r])]
    fy = min((max(drawn) + 1) if drawn else height - 1, height - 1)
    for c in range(2, width - 2):
        if grid[fy][c] == " ":
            grid[fy][c] = "‾"
    lines = ["".join(row).rstrip() for row in grid]
    while lines and not lines[-1].strip():
        lines.pop()
    while lines and not lines[0].strip():
        lines.pop(0)
    return "\n".join(lines)


def _inside(x, y, poly) -> bool:
    n = len(poly)
    ok = False
    j = n - 1
    for i in range(n):
        xi, yi = poly[i]
        xj, yj = poly[j]
        if (yi > y) != (yj > y) and x < (xj - xi) * (y - yi) / (yj - yi) + xi:
            ok = not ok
        j = i
    return ok
