"""Point labels that stay readable where points crowd: each label takes the first of a fixed set
of places about its point that covers no other label or marker, stays inside the axes and lies
nearer its own point than any other (greedy, in the points' order). The geometry is pure
functions of display pixels; `annotate_points` measures the labels and draws them on an Axes.
"""

from __future__ import annotations

import math

Box = tuple[float, float, float, float]  # x0, y0, x1, y1 in display pixels
Place = tuple[float, float, str, str]  # a label's offset from its point and its alignment: dx, dy, ha, va


def overlap(a: Box, b: Box) -> float:
    """The area two boxes share (0 when they are apart or only touch)."""
    return max(0.0, min(a[2], b[2]) - max(a[0], b[0])) * max(0.0, min(a[3], b[3]) - max(a[1], b[1]))


def label_candidates(gap: float, height: float, rows: int = 4) -> list[Place]:
    """Where a label may sit about its point, in the order tried: (dx, dy, horizontal, vertical
    alignment), pixels. First the four corners beside the marker, then above and below it, then
    further up and down on either side (drawn with a leader line), `rows` label heights out."""
    near = [(gap, gap, "left", "bottom"), (gap, -gap, "left", "top"), (-gap, gap, "right", "bottom"),
            (-gap, -gap, "right", "top"), (0.0, 2 * gap, "center", "bottom"), (0.0, -2 * gap, "center", "top")]
    far = [(side * 2 * gap, up * (gap + k * height), "left" if side > 0 else "right", "bottom" if up > 0 else "top")
           for k in range(1, rows + 1) for side in (1, -1) for up in (1, -1)]
    return near + far


def label_box(anchor: tuple[float, float], size: tuple[float, float], place: Place) -> Box:
    """The box a label of `size` (width, height) covers at `place` about `anchor`."""
    dx, dy, ha, va = place
    x0 = anchor[0] + dx - {"left": 0.0, "center": size[0] / 2, "right": size[0]}[ha]
    y0 = anchor[1] + dy - (size[1] if va == "top" else 0.0)
    return (x0, y0, x0 + size[0], y0 + size[1])


def distance(box: Box, point: tuple[float, float]) -> float:
    """How far a point lies from a box (0 inside it)."""
    return math.hypot(max(box[0] - point[0], 0.0, point[0] - box[2]), max(box[1] - point[1], 0.0, point[1] - box[3]))


def clash(box: Box, obstacles: list[Box], bounds: Box, own: tuple[float, float],
          others: list[tuple[float, float]]) -> float:
    """How badly a label's box collides: the area it shares with the obstacles, plus the area it
    leaves `bounds` by, plus its whole area when another point lies nearer to it than its own
    (a reader would take it for that point's label)."""
    area = (box[2] - box[0]) * (box[3] - box[1])
    misread = any(distance(box, p) < distance(box, own) for p in others)
    return sum(overlap(box, other) for other in obstacles) + area - overlap(box, bounds) + area * misread


def place_labels(anchors: list[tuple[float, float]], sizes: list[tuple[float, float]], bounds: Box,
                 marker: float = 5.0, gap: float = 4.0) -> list[Place]:
    """A place (label_candidates) for each point's label, in display pixels, chosen greedily in
    the points' order: the first place that covers no label placed before, no marker (a square
    of half-width `marker` about each point) and nothing outside `bounds` (the axes), and that lies
    nearer its own point than any other; where every place collides, the one that collides least.
    Near points (an ablation's variants a few ms and 0.05 dB apart) so get labels that can each be
    read, and be read as theirs."""
    markers = [(x - marker, y - marker, x + marker, y + marker) for x, y in anchors]
    placed: list[Box] = []
    chosen = []
    for i, (anchor, size) in enumerate(zip(anchors, sizes)):
        others = [a for j, a in enumerate(anchors) if j != i and a != anchor]  # a point on top of it misleads no one
        boxes = {place: label_box(anchor, size, place) for place in label_candidates(gap, size[1])}
        costs = {place: clash(box, placed + markers, bounds, anchor, others) for place, box in boxes.items()}
        best = next((place for place, cost in costs.items() if cost == 0.0), min(costs, key=costs.__getitem__))
        chosen.append(best)
        placed.append(boxes[best])
    return chosen


def annotate_points(ax, points: list[tuple[float, float]], labels: list[str], fontsize: float = 7) -> None:
    """Label each data point where place_labels puts it; a label set off from its point gets a
    thin leader line. Call it last, once the axes' limits and layout are final (after
    tight_layout): the places are worked out in display pixels."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig = ax.figure
    canvas = fig.canvas if hasattr(fig.canvas, "get_renderer") else FigureCanvasAgg(fig)  # a bare Figure has none
    renderer = canvas.get_renderer()  # measures the labels
    ax.get_xlim(), ax.get_ylim()  # settles autoscaled limits before data -> pixels
    anchors = [tuple(ax.transData.transform(xy)) for xy in points]
    sizes = []
    for label in labels:
        probe = ax.text(0, 0, label, fontsize=fontsize)
        extent = probe.get_window_extent(renderer)
        sizes.append((extent.width, extent.height))
        probe.remove()
    bb = ax.get_window_extent(renderer)
    to_points = 72.0 / fig.dpi  # xytext is in points, the places in pixels
    for xy, label, size, (dx, dy, ha, va) in zip(points, labels, sizes,
                                                  place_labels(anchors, sizes, (bb.x0, bb.y0, bb.x1, bb.y1))):
        leader = {"arrowstyle": "-", "lw": 0.5, "color": "0.5", "shrinkA": 0, "shrinkB": 3,
                  "relpos": (0.0 if ha == "left" else 1.0, 0.0 if va == "bottom" else 1.0)}
        ax.annotate(label, xy, textcoords="offset points", xytext=(dx * to_points, dy * to_points),
                    fontsize=fontsize, ha=ha, va=va, arrowprops=leader if abs(dy) > size[1] else None)
