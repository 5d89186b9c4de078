"""Speed / quality trade-offs: the Pareto front of measured points and the settings it recommends."""

from __future__ import annotations


def pareto_front(points: list[dict], x: str, y: str) -> list[dict]:
    """Points not dominated by another (lower-or-equal ``x`` and higher-or-equal ``y``, one strictly), by ``x``."""
    front = []
    for p in sorted(points, key=lambda p: (p[x], -p[y])):
        if not front or p[y] > front[-1][y]:
            front.append(p)
    return front


def recommend(points: list[dict], tolerance_db: float = 0.5) -> list[dict]:
    """Settings derived from the Pareto fronts: per group, the fastest point within ``tolerance_db`` of the
    best final PSNR ("balanced"), the best ("quality"), and the fastest on the front ("fastest")."""
    out = []
    for group, cost in (("training", "train_s"), ("render", "render_s_per_view")):
        pts = [p for p in points if p["group"] == group and p.get(cost) is not None]
        if not pts:
            continue
        front = pareto_front(pts, cost, "psnr_final")
        best = max(pts, key=lambda p: p["psnr_final"])
        balanced = next(p for p in front if p["psnr_final"] >= best["psnr_final"] - tolerance_db)
        for role, p in (("fastest", front[0]), ("balanced", balanced), ("quality", best)):
            out.append({"group": group, "role": role, "name": p["name"], cost: p[cost],
                        "psnr_final": p["psnr_final"]})
    return out
