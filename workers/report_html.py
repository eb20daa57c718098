"""``report.html``: a mosaic's quality report for people, and its pictures as SVG.

Self-contained and printable: the pictures are inline SVG (the overlap map's raster a PNG data URI inside
it), the style is inline, nothing is fetched from anywhere and no script runs. Every text that comes from a
user (photo and GCP names) is escaped. The same SVGs are written as outputs of their own, which the viewer's
quality card shows as images.

The pictures are drawn in the mosaic's pixel grid (x right, y down; north up when it is georeferenced):

- ``overlap``: how many photos see each cell, with the footprints' outlines;
- ``positions``: footprints, camera positions, each camera's GPS residual and each GCP's residual as arrows
  (exaggerated by a stated factor);
- ``tie_points``: where the tie points are, coloured by how well they agree (planar modes);
- ``residuals``: per photo, the tie-point RMS and the GPS residual as bars.
"""

from __future__ import annotations

import base64
import html
import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from core.labels import label

OVERLAP_COLOURS = ["#d7301f", "#fc8d59", "#fee08b", "#d9ef8b", "#1a9850"]  # 1, 2, 3, 4, 5+ photos
RESIDUAL_CLASSES = [(1.0, "#1a9850", "< 1 px"), (3.0, "#fdae61", "1-3 px"), (math.inf, "#d7191c", "> 3 px")]
DISPLAY_WIDTH = 720  # px of a map figure on screen and paper
MAX_TIE_DOTS = 4000


@dataclass
class FigureData:
    """What the pictures draw, in mosaic pixels (x right, y down)."""

    width: int
    height: int
    gsd_m: float | None  # metres per mosaic pixel; None: not to scale
    footprints: dict[str, np.ndarray]  # photo -> (4, 2) corners
    coverage: np.ndarray  # (gh, gw) uint8 photos per cell; cell = width / gw
    cameras: dict[str, np.ndarray] = field(default_factory=dict)  # photo -> (2,) camera position
    gps: dict[str, np.ndarray] = field(default_factory=dict)  # photo -> (2,) its GPS fix
    gcps: list[tuple[str, str, np.ndarray, np.ndarray]] = field(default_factory=list)  # id, role, known, adjusted
    ties: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (M, 2) tie points
    tie_residuals_px: np.ndarray | None = None  # (M,) photo px; None: not measured per point
    per_photo: list[tuple[str, float | None, float | None]] = field(default_factory=list)  # name, tie RMS, GPS m


def esc(value: Any) -> str:
    return html.escape(str(value), quote=True)


# -- Pictures ------------------------------------------------------------------------------------------------


def figures(data: FigureData) -> dict[str, str]:
    """``REPORT_FIGURES`` name -> SVG document."""
    return {
        "report-overlap.svg": overlap_svg(data),
        "report-positions.svg": positions_svg(data),
        "report-tie-points.svg": tie_points_svg(data),
        "report-residuals.svg": residuals_svg(data),
    }


class _Map:
    """A map figure in mosaic pixels: its SVG frame, and sizes in display pixels turned into mosaic pixels."""

    def __init__(self, data: FigureData, title: str) -> None:
        self.data, self.title = data, title
        self.unit = max(data.width, data.height) / DISPLAY_WIDTH  # mosaic px per display px
        self.margin = 8 * self.unit

    def px(self, display: float) -> float:
        return display * self.unit

    def svg(self, body: list[str], legend: list[tuple[str, str]], note: str = "") -> str:
        d, m = self.data, self.margin
        legend_h = self.px(22 * ((len(legend) + 3) // 4) + (18 if note else 0) + 8)
        w, h = d.width + 2 * m, d.height + 2 * m + legend_h
        display_h = round(DISPLAY_WIDTH * h / w) if d.width >= d.height else round(DISPLAY_WIDTH * h / w)
        parts = [
            '<svg xmlns="http://www.w3.org/2000/svg" xmlns:xlink="http://www.w3.org/1999/xlink" '
            f'width="{DISPLAY_WIDTH}" height="{display_h}" viewBox="{-m:.2f} {-m:.2f} {w:.2f} {h:.2f}" '
            f'font-family="sans-serif" font-size="{self.px(12):.2f}" role="img">',
            f"<title>{esc(self.title)}</title>",
            f'<rect x="{-m:.2f}" y="{-m:.2f}" width="{w:.2f}" height="{h:.2f}" fill="#ffffff"/>',
            f'<rect x="0" y="0" width="{d.width}" height="{d.height}" fill="#f4f4f4" stroke="#bbb" '
            'vector-effect="non-scaling-stroke"/>',
            *body,
            *self._scale_bar(),
            *self._legend(legend, note),
            "</svg>",
        ]
        return "\n".join(parts)

    def _scale_bar(self) -> list[str]:
        gsd = self.data.gsd_m
        if not gsd:
            return []
        metres = _round_length(self.data.width * gsd / 5)
        length = metres / gsd
        x0, y0 = self.px(10), self.data.height - self.px(12)
        text = f"{metres:g} m" if metres >= 1 else f"{metres * 100:g} cm"
        return [
            f'<g stroke="#000" fill="none" vector-effect="non-scaling-stroke"><path d="M{x0:.1f},{y0 - self.px(4):.1f} '
            f'V{y0:.1f} H{x0 + length:.1f} V{y0 - self.px(4):.1f}" stroke-width="{self.px(2):.2f}"/></g>',
            f'<text x="{x0:.1f}" y="{y0 - self.px(6):.1f}">{esc(text)}</text>',
            f'<text x="{self.data.width - self.px(14):.1f}" y="{self.px(16):.1f}" font-weight="bold">N&#8593;</text>',
        ]

    def _legend(self, items: list[tuple[str, str]], note: str) -> list[str]:
        out, y0 = [], self.data.height + self.margin + self.px(6)
        for n, (colour, text) in enumerate(items):
            x, y = (n % 4) * self.data.width / 4, y0 + (n // 4) * self.px(22)
            out.append(
                f'<rect x="{x:.1f}" y="{y:.1f}" width="{self.px(14):.1f}" height="{self.px(14):.1f}" '
                f'fill="{colour}" stroke="#555" vector-effect="non-scaling-stroke"/>'
            )
            out.append(f'<text x="{x + self.px(20):.1f}" y="{y + self.px(12):.1f}">{esc(text)}</text>')
        if note:
            y = y0 + self.px(22) * ((len(items) + 3) // 4) + self.px(10)
            out.append(f'<text x="0" y="{y:.1f}" fill="#444">{esc(note)}</text>')
        return out


def _round_length(metres: float) -> float:
    """A round length near ``metres``: 1, 2 or 5 times a power of ten."""
    if metres <= 0:
        return 1.0
    power = 10 ** math.floor(math.log10(metres))
    return next(f * power for f in (5, 2, 1) if f * power <= metres)


def _polygon(points: np.ndarray, style: str) -> str:
    coords = " ".join(f"{x:.1f},{y:.1f}" for x, y in np.asarray(points).reshape(-1, 2))
    return f'<polygon points="{coords}" {style} vector-effect="non-scaling-stroke"/>'


def overlap_svg(data: FigureData) -> str:
    figure = _Map(data, "Overlap: photos that see each part of the mosaic")
    counts = data.coverage
    rgba = np.zeros((*counts.shape, 4), np.uint8)
    for n, colour in enumerate(OVERLAP_COLOURS, start=1):
        where = counts >= n if n == len(OVERLAP_COLOURS) else counts == n
        r, g, b = (int(colour[k : k + 2], 16) for k in (1, 3, 5))
        rgba[where] = (b, g, r, 210)  # OpenCV writes BGRA
    ok, png = cv2.imencode(".png", rgba)
    uri = "data:image/png;base64," + base64.b64encode(png.tobytes()).decode("ascii") if ok else ""
    body = [
        f'<image x="0" y="0" width="{data.width}" height="{data.height}" preserveAspectRatio="none" '
        f'style="image-rendering:pixelated" href="{uri}" xlink:href="{uri}"/>',
        '<g fill="none" stroke="#333" stroke-width="1" opacity="0.6">',
        *(_polygon(c, "") for c in data.footprints.values()),
        "</g>",
    ]
    covered = counts > 0
    shares = [float((counts[covered] >= 2).mean()) if covered.any() else 0.0]
    legend = [
        (c, f"{n}{'+' if n == len(OVERLAP_COLOURS) else ''} photo{'s' if n > 1 else ''}")
        for n, c in enumerate(OVERLAP_COLOURS, start=1)
    ]
    note = f"{shares[0] * 100:.0f} % of the mosaic is seen by two photos or more"
    return figure.svg(body, legend, note)


def positions_svg(data: FigureData) -> str:
    figure = _Map(data, "Camera positions, GPS and ground control residuals")
    body = [
        '<g fill="none" stroke="#888" stroke-width="1">',
        *(_polygon(c, "") for c in data.footprints.values()),
        "</g>",
    ]
    vectors = [data.gps[n] - c for n, c in data.cameras.items() if n in data.gps]
    vectors += [adjusted - known for _, _, known, adjusted in data.gcps]
    longest = max((float(np.hypot(*v)) for v in vectors), default=0.0)
    factor = _round_length(0.08 * math.hypot(data.width, data.height) / longest) if longest > 0 else 1.0
    factor = max(1.0, factor)
    head = figure.px(5)
    for name, centre in data.cameras.items():
        if name in data.gps:
            body.append(_arrow(centre, centre + (data.gps[name] - centre) * factor, "#d7191c", figure.px(1.5), head))
    for name, (x, y) in data.cameras.items():
        body.append(
            f'<circle cx="{x:.1f}" cy="{y:.1f}" r="{figure.px(3.5):.2f}" fill="#2c7bb6" stroke="#fff" '
            f'vector-effect="non-scaling-stroke"><title>{esc(name)}</title></circle>'
        )
    if len(data.cameras) <= 60:
        body += [
            f'<text x="{x + figure.px(5):.1f}" y="{y - figure.px(5):.1f}" font-size="{figure.px(9):.2f}" '
            f'fill="#123">{esc(name)}</text>'
            for name, (x, y) in data.cameras.items()
        ]
    for gid, role, known, adjusted in data.gcps:
        colour = "#7b3294" if role == "control" else "#008837"
        body.append(_arrow(known, known + (adjusted - known) * factor, colour, figure.px(1.5), head))
        x, y = known
        s = figure.px(6)
        body.append(
            f'<path d="M{x:.1f},{y - s:.1f} L{x + s:.1f},{y + s * 0.7:.1f} L{x - s:.1f},{y + s * 0.7:.1f} Z" '
            f'fill="{colour}"><title>{esc(gid)} ({esc(label("gcp_role", role))})</title></path>'
        )
        body.append(
            f'<text x="{x + s:.1f}" y="{y + s * 2:.1f}" font-size="{figure.px(9):.2f}" '
            f'fill="{colour}">{esc(gid)}</text>'
        )
    legend = [("#2c7bb6", "camera position"), ("#d7191c", "to its GPS fix")]
    if data.gcps:
        legend += [("#7b3294", "control point residual"), ("#008837", "check point residual")]
    note = f"residual arrows drawn {factor:g} x their length" if vectors else "no GPS or ground control to compare"
    return figure.svg(body, legend, note)


def _arrow(start: np.ndarray, end: np.ndarray, colour: str, width: float, head: float) -> str:
    (x0, y0), (x1, y1) = start, end
    angle = math.atan2(y1 - y0, x1 - x0)
    left = (x1 - head * math.cos(angle - 0.4), y1 - head * math.sin(angle - 0.4))
    right = (x1 - head * math.cos(angle + 0.4), y1 - head * math.sin(angle + 0.4))
    return (
        f'<g stroke="{colour}" fill="{colour}"><line x1="{x0:.1f}" y1="{y0:.1f}" x2="{x1:.1f}" y2="{y1:.1f}" '
        f'stroke-width="{width:.2f}"/><path d="M{x1:.1f},{y1:.1f} L{left[0]:.1f},{left[1]:.1f} '
        f'L{right[0]:.1f},{right[1]:.1f} Z" stroke="none"/></g>'
    )


def tie_points_svg(data: FigureData) -> str:
    figure = _Map(data, "Tie points: where the photos are tied together")
    body = [
        '<g fill="none" stroke="#aaa" stroke-width="1">',
        *(_polygon(c, "") for c in data.footprints.values()),
        "</g>",
    ]
    ties, residuals = data.ties, data.tie_residuals_px
    keep = _spread_subset(len(ties), MAX_TIE_DOTS)
    r = figure.px(1.6)
    if residuals is None:
        body += [f'<circle cx="{x:.1f}" cy="{y:.1f}" r="{r:.2f}" fill="#2c7bb6"/>' for x, y in ties[keep]]
        legend = [("#2c7bb6", "tie point")]
    else:
        lower = 0.0
        for upper, colour, _ in RESIDUAL_CLASSES:
            chosen = keep[(residuals[keep] >= lower) & (residuals[keep] < upper)]
            body += [f'<circle cx="{x:.1f}" cy="{y:.1f}" r="{r:.2f}" fill="{colour}"/>' for x, y in ties[chosen]]
            lower = upper
        legend = [(colour, f"misfit {text}") for _, colour, text in RESIDUAL_CLASSES]
    shown = f"{len(keep)} of {len(ties)}" if len(keep) < len(ties) else f"{len(ties)}"
    return figure.svg(body, legend, f"{shown} tie points shown" if len(ties) else "no tie points to show")


def _spread_subset(n: int, at_most: int) -> np.ndarray:
    return np.arange(n) if n <= at_most else np.linspace(0, n - 1, at_most).round().astype(int)


def residuals_svg(data: FigureData) -> str:
    """Bars per photo: tie-point RMS (px) and GPS residual (m), side by side, one row per photo."""
    rows = data.per_photo
    row_h, top, name_w, bar_w = 16, 34, 190, 230
    width, height = name_w + 2 * bar_w + 130, top + row_h * max(len(rows), 1) + 30
    tie_max = max((t for _, t, _ in rows if t is not None), default=0.0) or 1.0
    gps_max = max((g for _, _, g in rows if g is not None), default=0.0) or 1.0
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" viewBox="0 0 {width} {height}" '
        'font-family="sans-serif" font-size="11" role="img"><title>Residuals per photo</title>',
        f'<rect width="{width}" height="{height}" fill="#fff"/>',
        f'<text x="{name_w}" y="14" font-weight="bold">Tie-point RMS (px, max {tie_max:.3g})</text>',
        f'<text x="{name_w + bar_w + 60}" y="14" font-weight="bold">GPS residual (m, max {gps_max:.3g})</text>',
    ]
    for n, (name, tie, gps) in enumerate(rows):
        y = top + n * row_h
        out.append(
            f'<text x="{name_w - 6}" y="{y + 11}" text-anchor="end">{esc(_short(name))}'
            f"<title>{esc(name)}</title></text>"
        )
        for x0, value, top_value, colour, unit in (
            (name_w, tie, tie_max, "#2c7bb6", "px"),
            (name_w + bar_w + 60, gps, gps_max, "#d7191c", "m"),
        ):
            if value is None:
                out.append(f'<text x="{x0}" y="{y + 11}" fill="#888">–</text>')
                continue
            length = max(1.0, bar_w * value / top_value)
            out.append(
                f'<rect x="{x0}" y="{y + 2}" width="{length:.1f}" height="{row_h - 4}" fill="{colour}">'
                f"<title>{esc(name)}: {value:.3f} {unit}</title></rect>"
            )
            out.append(f'<text x="{x0 + length + 4:.1f}" y="{y + 11}" font-size="10">{value:.3g}</text>')
    if not rows:
        out.append(f'<text x="{name_w}" y="{top + 11}" fill="#888">no photos to show</text>')
    out.append("</svg>")
    return "\n".join(out)


def _short(name: str, limit: int = 28) -> str:
    return name if len(name) <= limit else "…" + name[-(limit - 1) :]


# -- The page -------------------------------------------------------------------------------------------------

STYLE = """
body { font-family: system-ui, sans-serif; color: #222; margin: 2rem auto; max-width: 60rem; padding: 0 1rem; }
h1 { font-size: 1.6rem; margin-bottom: .2rem; }
h2 { font-size: 1.2rem; margin-top: 2rem; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; font-size: .85rem; margin: .5rem 0; }
th, td { border: 1px solid #ccc; padding: .2rem .45rem; text-align: left; vertical-align: top; }
td.num, th.num { text-align: right; font-variant-numeric: tabular-nums; }
dl.facts { display: grid; grid-template-columns: max-content auto; gap: .2rem 1rem; }
dl.facts dt { color: #555; } dl.facts dd { margin: 0; }
.warning { background: #fff4e5; border-left: 4px solid #e67e22; padding: .4rem .7rem; margin: .3rem 0; }
.advice { background: #eef6ff; border-left: 4px solid #2c7bb6; padding: .4rem .7rem; margin: .3rem 0; }
figure { margin: 1rem 0; page-break-inside: avoid; } figure svg { max-width: 100%; height: auto; }
figcaption { color: #555; font-size: .85rem; }
.muted { color: #777; }
@media print { body { margin: 0; max-width: none; } h2 { page-break-after: avoid; } a { color: inherit; } }
"""


def report_page(report: dict[str, Any], data: FigureData, svgs: dict[str, str], advice: list[str]) -> str:
    """The whole ``report.html``."""
    mode = report.get("mode", "planar")
    used, rejected = report.get("frames_used", []), report.get("frames_rejected", [])
    sections = [
        "<!doctype html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>Mosaic quality report · {esc(label('mode', mode))}</title>",
        f"<style>{STYLE}</style></head><body>",
        "<h1>Mosaic quality report</h1>",
        f'<p class="muted">{esc(label("mode", mode))} · {len(used)} of {len(used) + len(rejected)} photos used · '
        f"made by Fotoskhema</p>",
        _facts(report),
        "<h2>What to check</h2>",
        *[f'<p class="warning">{esc(w)}</p>' for w in report.get("warnings", [])],
        *[f'<p class="advice">{esc(a)}</p>' for a in advice],
        *(
            []
            if report.get("warnings") or advice
            else ['<p class="muted">Nothing the processing found needs your attention.</p>']
        ),
        _figure(
            svgs["report-overlap.svg"],
            "Overlap map: how many photos see each part of the mosaic. One photo "
            "(red) means no check from a second view there.",
        ),
        _figure(
            svgs["report-positions.svg"],
            "Camera positions on the footprints, and arrows from each camera to "
            "its GPS fix and from each ground control point to where the model puts it.",
        ),
        _figure(svgs["report-tie-points.svg"], "Tie points: the features matched between photos, in the mosaic."),
        _figure(
            svgs["report-residuals.svg"], "Per photo: how well its tie points agree, and its distance from its GPS fix."
        ),
        _pairs_table(report.get("pairs", [])),
        _triangulation(report.get("triangulation")),
        _rejected(rejected),
        _stage_times(report.get("stage_seconds", {})),
        "</body></html>",
    ]
    return "\n".join(s for s in sections if s)


def _facts(report: dict[str, Any]) -> str:
    mosaic = report.get("mosaic") or {}
    rows = [
        ("Mode", label("mode", report.get("mode", "planar"))),
        ("Blending", label("blend", mosaic.get("blend", "feather"))),
        ("Resolution", label("resolution", mosaic.get("resolution", "working"))),
        ("Tie-point RMS", _rms(report.get("tie_point_rms_px"), report.get("tie_point_rms_px_original"))),
        ("Tie points", _int(report.get("tie_points"))),
        ("Ground sampling distance of the mosaic", _length(report.get("gsd_m"))),
        ("Ground sampling distance of the photos", _length(report.get("gsd_original_m"))),
        ("GPS residual RMS", _length(report.get("gps_residual_rms_m"))),
        (
            "Coordinate system",
            report.get("crs") or "none: " + str(report.get("georeference_note") or "not georeferenced"),
        ),
        ("Mosaic size", f"{mosaic.get('width', '–')} × {mosaic.get('height', '–')} px"),
    ]
    precision = report.get("corner_precision")
    if isinstance(precision, dict):
        rows.append(("Frame corners known to (1σ)", _precision(precision)))
    if isinstance(mosaic.get("seam_visibility"), int | float):
        rows.append(("Seam visibility (1 = invisible)", f"{mosaic['seam_visibility']:.2f}"))
    if isinstance(report.get("ortho_surface"), dict):
        rows.append(("Ortho surface", _surface(report["ortho_surface"])))
    triangulation = report.get("triangulation") or {}
    if triangulation:
        rows.append(("Datum", label("datum", str(triangulation.get("datum", "none")))))
        if isinstance(triangulation.get("checkpoint_rmse_m"), int | float):
            rows.append(("Check point RMSE", _length(triangulation["checkpoint_rmse_m"])))
    cells = "".join(f"<dt>{esc(k)}</dt><dd>{esc(v)}</dd>" for k, v in rows)
    return f'<dl class="facts">{cells}</dl>'


def _surface(surface: dict[str, Any]) -> str:
    """What the frames were projected onto, in words (``orthorectify_frames``'s ``surface``)."""
    kind = surface.get("kind")
    if kind == "dense":
        share = surface.get("coverage")
        seen = f"{100 * share:.0f} %" if isinstance(share, int | float) else "–"
        text = (
            f"dense stereo between overlapping photos ({_int(surface.get('pairs'))} pairs, "
            f"{_int(surface.get('dense_points'))} points, {seen} of the ground two photos see; "
            f"{_length(surface.get('cell_m'))} cells), the tie points' surface elsewhere"
        )
    elif kind == "tie_points":
        text = (
            f"a surface gridded from {_int(surface.get('points'))} tie points ({_length(surface.get('cell_m'))} cells)"
        )
    else:
        text = "one plane"
    return f"{text}: {surface['why']}" if isinstance(surface.get("why"), str) else text


def _figure(svg: str, caption: str) -> str:
    return f"<figure>{svg}<figcaption>{esc(caption)}</figcaption></figure>"


def _table(title: str, headers: list[str], rows: list[list[Any]], numeric: set[int], empty: str) -> str:
    if not rows:
        return f"<h2>{esc(title)}</h2><p class='muted'>{esc(empty)}</p>"
    head = "".join(f"<th{' class=num' if k in numeric else ''}>{esc(h)}</th>" for k, h in enumerate(headers))
    body = "".join(
        "<tr>"
        + "".join(f"<td{' class=num' if k in numeric else ''}>{esc(c)}</td>" for k, c in enumerate(row))
        + "</tr>"
        for row in rows
    )
    return f"<h2>{esc(title)}</h2><table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _pairs_table(pairs: list[dict[str, Any]]) -> str:
    """Every pair tried; its tie points' RMS where the mosaic has one per pair (planar: an ortho job's misfits are
    each photo's, in its reprojection table)."""
    with_rms = any(p.get("tie_point_rms_px") is not None for p in pairs)
    rows = [
        [
            p["frames"][0],
            p["frames"][1],
            p.get("matches", 0),
            p.get("inliers", 0),
            "yes" if p.get("used") else "no",
            *([_num(p.get("tie_point_rms_px"), 2)] if with_rms else []),
            p.get("reason_unused") or "",
        ]
        for p in pairs
    ]
    return _table(
        "Photo pairs",
        ["Photo", "Photo", "Matches", "Inliers", "Used", *(["RMS px"] if with_rms else []), "Why not used"],
        rows,
        {2, 3, 5} if with_rms else {2, 3},
        "No pairs were tried.",
    )


def _triangulation(t: dict[str, Any] | None) -> str:
    if not t:
        return ""
    images = [
        [
            i.get("name"),
            label("image_status", str(i.get("status"))),
            _num(i.get("rms_px"), 2),
            _int(i.get("observations")),
            _num(i.get("gps_residual_m"), 3),
        ]
        for i in t.get("images", [])
    ]
    gcps = [
        [
            g.get("id"),
            label("gcp_role", str(g.get("role"))),
            _int(g.get("observations")),
            _num(g.get("residual_px"), 2),
            _vector(g.get("error_m")),
            _num(g.get("error_3d_m"), 3),
        ]
        for g in t.get("gcps", [])
    ]
    params = [
        [label("camera_parameter", k), _num((v or {}).get("initial"), 5), _num((v or {}).get("adjusted"), 5)]
        for k, v in (t.get("self_calibration") or {}).items()
    ]
    return "\n".join(
        [
            _table(
                "Photo-triangulation: per photo",
                ["Photo", "Status", "RMS px", "Observations", "GPS residual m"],
                images,
                {2, 3, 4},
                "No photos.",
            ),
            _table(
                "Ground control points",
                ["Point", "Role", "Photos", "Residual px", "Error east, north, up m", "Error 3D m"],
                gcps,
                {2, 3, 5},
                "No ground control points were used.",
            ),
            _table(
                "Camera refined by the adjustment",
                ["Parameter", "Initial", "Adjusted"],
                params,
                {1, 2},
                "The camera was not refined.",
            ),
        ]
    )


def _rejected(rejected: list[dict[str, Any]]) -> str:
    rows = [[r.get("name"), r.get("reason", "")] for r in rejected]
    return _table("Photos left out", ["Photo", "Why"], rows, set(), "Every photo is in the mosaic.")


def _stage_times(seconds: dict[str, float]) -> str:
    rows = [[label("stage", k), _num(v, 1)] for k, v in seconds.items()]
    if rows:
        rows.append(["Total", _num(sum(v for v in seconds.values() if isinstance(v, int | float)), 1)])
    return _table("Processing time", ["Step", "Seconds"], rows, {1}, "No times recorded.")


def _num(value: Any, digits: int) -> str:
    return f"{value:.{digits}f}" if isinstance(value, int | float) and math.isfinite(value) else "–"


def _int(value: Any) -> str:
    return f"{value:,}" if isinstance(value, int) else "–"


def _length(metres: Any) -> str:
    if not isinstance(metres, int | float) or not math.isfinite(metres):
        return "–"
    return f"{metres * 100:.1f} cm" if abs(metres) < 1 else f"{metres:.2f} m"


def _precision(precision: dict[str, Any]) -> str:
    """ "0.4 cm median, 0.9 cm at strip_000.tif (3.4 photo px)": the adjustment's corner standard errors."""
    px = precision.get("max_photo_px")
    in_px = f" ({px:.1f} photo px)" if isinstance(px, int | float) and math.isfinite(px) else ""
    where = precision.get("worst_frame")
    return (
        f"{_length(precision.get('median_m'))} median, {_length(precision.get('max_m'))}"
        f"{f' at {where}' if where else ''}{in_px}"
    )


def _rms(working: Any, original: Any) -> str:
    text = _num(working, 2)
    return (
        f"{text} px ({_num(original, 2)} px of the full-size photos)"
        if text != "–" and original is not None
        else (f"{text} px" if text != "–" else text)
    )


def _vector(values: Any) -> str:
    if not isinstance(values, list) or not all(isinstance(v, int | float) for v in values):
        return "–"
    return ", ".join(f"{v:.3f}" for v in values)
