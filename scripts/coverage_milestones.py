#!/usr/bin/env python3
"""Distance flown until free coverage first reaches 90 % and 95 %, mean per scenario and
planner, from a bench's curves.csv (harmonic-sim bench writes it).

    python3 scripts/coverage_milestones.py results/curves.csv
"""
import csv
import sys
from collections import defaultdict

ORDER = ["random-frontier", "closest-frontier", "info-gain", "weighted-info-gain", "harmonic-gs", "harmonic"]

runs = defaultdict(list)
for r in csv.DictReader(open(sys.argv[1])):
    runs[(r["scenario"], r["planner"], r["seed"])].append((float(r["path_length_m"]), float(r["coverage_free"])))

table = defaultdict(lambda: defaultdict(list))
for (scenario, planner, _), pts in runs.items():
    for level in (0.90, 0.95):
        d = next((d for d, c in pts if c >= level), None)
        table[(scenario, planner)][level].append(d)

print("| scenario | planner | m to 90 % | m to 95 % |")
print("|---|---|---|---|")
for (scenario, planner) in sorted(table, key=lambda k: (k[0], ORDER.index(k[1]) if k[1] in ORDER else 99)):
    cells = []
    for level in (0.90, 0.95):
        ds = table[(scenario, planner)][level]
        ok = [d for d in ds if d is not None]
        cells.append(f"{sum(ok) / len(ok):.1f}" + ("" if len(ok) == len(ds) else f" ({len(ok)}/{len(ds)} runs)") if ok else "–")
    print(f"| {scenario} | {planner} | {cells[0]} | {cells[1]} |")
