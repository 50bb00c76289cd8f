"""Each bundle's straight-line strain in a table, computed from the table and the ligament
file alone (no kneeseat code): an independent check of what `kneeseat kinematics` reports.

Run: `python benchmarks/ligament_strains.py TABLE.npz LIGAMENTS.json [--varus-deg 0]
[--every-deg 10]`. For every flexion value that is a multiple of `--every-deg` (all of them
on a coarser grid) it prints each bundle's largest fibre strain (%), with every point
placed by its body's pose in the table (femur points where they are), and the largest
strain of all with its bundle and flexion.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def rotation(q: np.ndarray) -> np.ndarray:
    """The rotation matrix of a unit quaternion (x, y, z, w)."""
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def strains(table_path: Path, ligaments_path: Path, varus_deg: float,
            every_deg: float) -> list[tuple[float, dict[str, float], list[int]]]:
    """(flexion deg, {bundle: largest fibre strain}, status per body) per printed row."""
    table = np.load(table_path, allow_pickle=False)
    meta = json.loads(str(table['metadata']))
    names = [b['name'] for b in meta['bodies']]
    reference = meta['reference']['name']
    flexion, varus = np.degrees(table['flexion']), np.degrees(table['varus'])
    j = int(np.argmin(np.abs(varus - varus_deg)))
    status = np.array(meta['cells']['status'])
    fibres = json.loads(Path(ligaments_path).read_text())['ligaments']
    scale = {'m': 1.0, 'mm': 1e-3}[json.loads(Path(ligaments_path).read_text()).get('units', 'm')]
    rows = []
    for i, f in enumerate(flexion):
        if len(flexion) > 10 and abs(f / every_deg - round(f / every_deg)) > 1e-6:
            continue
        poses = {reference: (np.eye(3), np.zeros(3))}
        for b, name in enumerate(names):
            poses[name] = (rotation(table['orientation'][b, i, j]), table['position'][b, i, j])
        worst: dict[str, float] = {}
        for fibre in fibres:
            points = [poses[p['body']][0] @ (scale * np.array(p['position'])) + poses[p['body']][1]
                      for p in fibre['points']]
            length = sum(float(np.linalg.norm(b - a)) for a, b in zip(points, points[1:]))
            strain = length / fibre['slack_length_m'] - 1.0
            worst[fibre['bundle']] = max(worst.get(fibre['bundle'], -1.0), strain)
        rows.append((float(f), worst, [int(s) for s in status[:, i, j]]))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('table', type=Path)
    parser.add_argument('ligaments', type=Path)
    parser.add_argument('--varus-deg', type=float, default=0.0)
    parser.add_argument('--every-deg', type=float, default=10.0)
    args = parser.parse_args()
    rows = strains(args.table, args.ligaments, args.varus_deg, args.every_deg)
    bundles = list(rows[0][1])
    print('flexion | ' + ' | '.join(bundles) + ' | status per body')
    top = (-1.0, '', 0.0)
    for flexion, worst, status in rows:
        print(f'{flexion:7.0f} | ' + ' | '.join(f'{100 * worst[b]:5.1f}' for b in bundles)
              + f' | {status}')
        for b in bundles:
            if worst[b] > top[0]:
                top = (worst[b], b, flexion)
    print(f'largest: {100 * top[0]:.1f} % ({top[1]} at flexion {top[2]:g} deg)')


if __name__ == '__main__':
    main()
