#!/usr/bin/env python3
"""Compare the data artifacts of two dermis caches node by node.

    python3 bench/compare_caches.py BASE_CACHE NEW_CACHE [old_id=new_id ...]

For every node of BASE (its index entry), the entry of the same node id (or the renamed one) in
NEW: every array of data.npz must have the same dtype, shape and values (NaN where NaN), other
data files the same bytes; EXR/PNG/PDF/JSON files are derived or carry timings and are skipped.
Prints the differing arrays and "same N  diff N  missing N"; exits 1 on any difference.  Used
to check that a change of structure leaves every result of a scene as it was
(bench/results/structure_identity.json).
"""
import json
import sys
from pathlib import Path
import numpy as np

base, new = Path(sys.argv[1]), Path(sys.argv[2])
ren = dict(a.split('=') for a in sys.argv[3:])

def entry(root, nid):
    idx = root / 'index' / f'{nid}.json'
    if not idx.exists():
        return None
    key = json.loads(idx.read_text())['key']
    return root / nid / key

same = diff = missing = 0
for idx in sorted((base / 'index').glob('*.json')):
    nid = idx.stem
    a = entry(base, nid); b = entry(new, ren.get(nid, nid))
    if b is None or not b.exists():
        print('MISSING', nid); missing += 1; continue
    for f in sorted(a.iterdir()):
        if f.name == 'meta.json':
            continue
        g = b / f.name
        if not g.exists():
            print('MISSING FILE', nid, f.name); missing += 1; continue
        if f.suffix == '.npz':
            za, zb = np.load(f, allow_pickle=False), np.load(g, allow_pickle=False)
            if set(za.files) != set(zb.files):
                print('DIFF KEYS', nid, f.name, set(za.files) ^ set(zb.files)); diff += 1; continue
            for k in za.files:
                x, y = za[k], zb[k]
                if x.dtype != y.dtype or x.shape != y.shape or not np.array_equal(x, y, equal_nan=x.dtype.kind == 'f'):
                    print('DIFF', nid, f.name, k); diff += 1
                else:
                    same += 1
        elif f.suffix in ('.exr', '.png', '.pdf', '.json'):
            continue   # derived files / metadata with timings
        else:
            if f.read_bytes() != g.read_bytes():
                print('DIFF FILE', nid, f.name); diff += 1
            else:
                same += 1
print(f'same {same}  diff {diff}  missing {missing}')
sys.exit(1 if diff or missing else 0)
