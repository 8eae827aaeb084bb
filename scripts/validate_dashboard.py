#!/usr/bin/env python3
"""Checks a Grafana dashboard (deploy/grafana/*.json) offline, beyond parsing as JSON: panel ids are
unique; every panel but a row has queries, each with an expression and a reference id unique in its
panel, on the dashboard's Prometheus data source variable; panels lie within the 24-column grid and
none overlaps another. That the queries name only exported metrics is tested against a real scrape
(tests/tests/dashboard_metrics.rs).

    scripts/validate_dashboard.py deploy/grafana/spoofwatch-dashboard.json [...]
"""

import json
import sys


def problems(dashboard: dict) -> list[str]:
    found = []
    panels = dashboard.get("panels") or []
    if not panels:
        return ["no panels"]
    ids = [p.get("id") for p in panels]
    duplicates = sorted({i for i in ids if ids.count(i) > 1}, key=str)
    if duplicates:
        found.append(f"panel ids used twice: {duplicates}")
    cells = {}
    for panel in panels:
        name = f"panel {panel.get('id')} ({panel.get('title', '')!r})"
        grid = panel.get("gridPos") or {}
        x, y, w, h = (grid.get(k) for k in ("x", "y", "w", "h"))
        if not all(isinstance(v, int) for v in (x, y, w, h)) or w < 1 or h < 1 or x < 0 or x + w > 24:
            found.append(f"{name}: gridPos {grid} is not within the 24-column grid")
            continue
        for cx in range(x, x + w):
            for cy in range(y, y + h):
                other = cells.setdefault((cx, cy), name)
                if other != name:
                    found.append(f"{name} overlaps {other}")
                    break
            else:
                continue
            break
        if panel.get("type") == "row":
            continue
        targets = panel.get("targets") or []
        if not targets:
            found.append(f"{name}: no queries")
        refs = [t.get("refId") for t in targets]
        if len(set(refs)) != len(refs) or None in refs:
            found.append(f"{name}: query refIds missing or repeated: {refs}")
        for target in targets:
            if not str(target.get("expr", "")).strip():
                found.append(f"{name}: query {target.get('refId')} has no expression")
            if (target.get("datasource") or panel.get("datasource") or {}).get("uid") != "${datasource}":
                found.append(f"{name}: query {target.get('refId')} is not on the ${{datasource}} variable")
    return found


def main() -> int:
    failed = False
    for path in sys.argv[1:]:
        with open(path, encoding="utf-8") as f:
            found = problems(json.load(f))
        for problem in found:
            print(f"{path}: {problem}", file=sys.stderr)
        failed |= bool(found)
        if not found:
            print(f"{path}: valid")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
