#!/usr/bin/env python3
"""False-alarm onsets per attack-free hour by sample rate, from `spoofwatch detect --out` of a clean fleet.

Each vehicle's rate is 1 / its median sampling interval (rounded, at least 1 Hz); its hours are the time
between consecutive rows up to 5 s (longer gaps are outages, not driving).

    python3 scripts/fleet_by_rate.py detections.csv
"""
import csv
import statistics
import sys
from collections import defaultdict

OUTAGE_S = 5.0


def main(path):
    rows = defaultdict(list)
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            rows[r["vehicle_id"]].append((float(r["timestamp_s"]), r["alarm_onset"] == "1"))
    by_rate = defaultdict(lambda: [0.0, 0])
    for samples in rows.values():
        samples.sort()
        steps = [b[0] - a[0] for a, b in zip(samples, samples[1:]) if b[0] > a[0]]
        if not steps:
            continue
        rate = max(1, round(1 / statistics.median(steps)))
        by_rate[rate][0] += sum(s for s in steps if s <= OUTAGE_S) / 3600
        by_rate[rate][1] += sum(1 for _, onset in samples if onset)
    for rate in sorted(by_rate):
        hours, onsets = by_rate[rate]
        print(f"{rate} Hz: {onsets / hours:.2f} per hour ({onsets} onsets in {hours:.1f} h)")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(sys.argv[1])
